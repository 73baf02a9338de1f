"""Hand-eye calibration of the CM on the robot (the hand-eye matrix ``ee_from_cm``), and its baselines.

- :mod:`~fluoronav.calibration.image_handeye`: the paper's image-based calibration (§II-D, eqs. 5–6): a
  multiple-CM registration of M images of one static C-arm, unknowns the hand-eye, robot base and CM shape;
- :mod:`~fluoronav.calibration.handeye`: tracker-based AX = XB / AX = YB baselines (OpenCV) and the
  paper's tip validation (eqs. 9, 10);
- :mod:`~fluoronav.calibration.tracker`: a simulated optical tracker (marker bodies, Kabsch poses);
- :mod:`~fluoronav.calibration.results`: the result types (numpy float64, frozen).

The robot model (DH, IK, kinematic errors) is :mod:`fluoronav.manipulator.robot`; frames and
equations are in docs/robot-and-calibration.md.
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.calibration.handeye import (
        AX_XB_METHODS,
        AX_YB_METHODS,
        calibrate_hand_eye,
        calibrate_robot_world_hand_eye,
        check_motion,
        estimate_rbase_from_tracker,
        handeye_residuals,
        simulate_tracker_calibration,
        tip_errors,
        tip_rbase_image_chain,
        tip_rbase_tracker_chain,
        transform_error,
    )
    from fluoronav.calibration.image_handeye import (
        ImageHandEyeConfig,
        ImageHandEyeProblem,
        ImageHandEyeResult,
        calibrate_hand_eye_from_images,
        default_handeye_levels,
        initial_world_from_rbase_pnp,
    )
    from fluoronav.calibration.results import HandEyeFailure, HandEyeResult, TipErrors
    from fluoronav.calibration.tracker import DEFAULT_BODY, OpticalTracker, RigidBody, TrackedPose, kabsch

__all__ = [
    "AX_XB_METHODS",  # OpenCV calibrateHandEye methods by name (TSAI, PARK, HORAUD, ANDREFF, ...)
    "AX_YB_METHODS",  # OpenCV calibrateRobotWorldHandEye methods by name (SHAH, LI)
    "DEFAULT_BODY",  # planar asymmetric 4-marker body with NDI-tool-like spacing
    "HandEyeFailure",  # a calibration that could not be solved, with the reason
    "HandEyeResult",  # a tracker-based calibration: X = ee_from_marker, Y, per-pose residuals
    "ImageHandEyeConfig",  # settings of the image-based calibration (levels, priors, ROI)
    "ImageHandEyeProblem",  # the 17-parameter image-based problem, built once (for inspection)
    "ImageHandEyeResult",  # the image-based calibration: ee_from_cm, robot base, CM shape, trace
    "OpticalTracker",  # simulated optical tracker with Gaussian marker noise
    "RigidBody",  # a marker body: marker centres in its own frame, mm
    "TipErrors",  # distances between two estimates of the same tip (eq. 9 vs eq. 10)
    "TrackedPose",  # a tracker reading of a body: pose, noisy markers, fit residual (FRE)
    "calibrate_hand_eye",  # AX = XB through cv2.calibrateHandEye (tracker baseline)
    "calibrate_hand_eye_from_images",  # the image-based calibration from M views of one C-arm
    "calibrate_robot_world_hand_eye",  # AX = YB through cv2.calibrateRobotWorldHandEye
    "check_motion",  # refuses too few poses or rotations about (nearly) one axis
    "default_handeye_levels",  # the image-based calibration's registration levels
    "estimate_rbase_from_tracker",  # Y given X: chordal mean over the poses
    "handeye_residuals",  # per-pose loop closure of AX = YB: rotation °, translation mm
    "initial_world_from_rbase_pnp",  # closed-form PnP start of the robot base from the landmarks
    "kabsch",  # least-squares rigid transform between point sets
    "simulate_tracker_calibration",  # robot poses and tracker readings of a simulated robot
    "tip_errors",  # TipErrors of two (N, 3) tip estimates (per pose; mean, std, max)
    "tip_rbase_image_chain",  # eq. 10: the tip in the robot base through the image-based chain
    "tip_rbase_tracker_chain",  # eq. 9: the tip in the robot base through the tracker chain
    "transform_error",  # (rotation °, translation mm) of inv(reference) · estimated
]

__getattr__, __dir__ = lazy_face(__name__)
