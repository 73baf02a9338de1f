"""Tracker-based hand-eye calibration baselines (OpenCV) and the paper's tip validation (eqs. 9, 10).

Setting (paper Fig. 6): a marker body ``marker`` (the paper's O_s) is fixed to the end effector and
the tracker is static relative to the robot base. Per pose i, ``rbase_from_ee_i · X = Y ·
tracker_from_marker_i`` with the constant unknowns X = ``ee_from_marker`` (the hand-eye matrix) and
Y = ``rbase_from_tracker``. OpenCV's names ``a2b`` mean our ``b_from_a``: the marker plays OpenCV's
camera on the gripper and the tracker its static target (``calibrateHandEye``, AX = XB) or world
(``calibrateRobotWorldHandEye``, AX = YB); the argument table is in docs/robot-and-calibration.md.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import cv2
import numpy as np

from fluoronav.calibration.results import HandEyeFailure, HandEyeResult, TipErrors
from fluoronav.calibration.tracker import OpticalTracker, RigidBody
from fluoronav.geometry import se3
from fluoronav.manipulator.robot import RobotErrorModel, SerialRobot

__all__ = [
    "AX_XB_METHODS",
    "AX_YB_METHODS",
    "calibrate_hand_eye",
    "calibrate_robot_world_hand_eye",
    "check_motion",
    "estimate_rbase_from_tracker",
    "handeye_residuals",
    "simulate_tracker_calibration",
    "tip_errors",
    "tip_rbase_image_chain",
    "tip_rbase_tracker_chain",
    "transform_error",
]

logger = logging.getLogger(__name__)

AX_XB_METHODS: dict[str, int] = {
    "TSAI": cv2.CALIB_HAND_EYE_TSAI,
    "PARK": cv2.CALIB_HAND_EYE_PARK,
    "HORAUD": cv2.CALIB_HAND_EYE_HORAUD,
    "ANDREFF": cv2.CALIB_HAND_EYE_ANDREFF,
    "DANIILIDIS": cv2.CALIB_HAND_EYE_DANIILIDIS,
}
AX_YB_METHODS: dict[str, int] = {
    "SHAH": cv2.CALIB_ROBOT_WORLD_HAND_EYE_SHAH,
    "LI": cv2.CALIB_ROBOT_WORLD_HAND_EYE_LI,
}


def _split(T: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(N, 4, 4) → OpenCV's lists of (3, 3) rotations and (3, 1) translations."""
    return [np.ascontiguousarray(t[:3, :3]) for t in T], [np.ascontiguousarray(t[:3, 3:4]) for t in T]


def _inputs(rbase_from_ee: np.ndarray, tracker_from_marker: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    A = se3.as_transform_array(rbase_from_ee, "rbase_from_ee")
    B = se3.as_transform_array(tracker_from_marker, "tracker_from_marker")
    if A.ndim != 3 or A.shape != B.shape:
        raise ValueError(f"expected two (N, 4, 4) stacks of equal N, got {A.shape} and {B.shape}")
    return A, B


def check_motion(
    rbase_from_ee: np.ndarray,
    *,
    min_poses: int = 3,
    min_rotation_deg: float = 1.0,
    min_axis_spread_deg: float = 5.0,
) -> HandEyeFailure | None:
    """Reject data that cannot determine X: too few poses or rotations about (nearly) one axis.

    The relative rotations ``ee_i_from_ee_j`` over all pairs with an angle ≥ ``min_rotation_deg``
    give unit axes a_k; the scatter matrix M = mean(a_k a_kᵀ) has eigenvalues λ1 ≥ λ2 ≥ λ3 and
    ``spread = 2·atan(sqrt(λ2/λ1))`` equals the angle between two equally represented axes. X is
    unique only when at least two non-parallel axes occur, so spread < ``min_axis_spread_deg`` fails.

    Returns:
        ``None`` if the motion is usable, else a :class:`HandEyeFailure` saying why.
    """
    A = se3.as_transform_array(rbase_from_ee, "rbase_from_ee")
    n = A.shape[0] if A.ndim == 3 else 0
    if n < min_poses:
        return HandEyeFailure(f"too few poses: {n} < {min_poses}", n_poses=n)
    i, j = np.triu_indices(n, k=1)
    rel = np.swapaxes(A[i, :3, :3], -1, -2) @ A[j, :3, :3]
    rv = se3.rotvec(rel)
    ang = np.linalg.norm(rv, axis=-1)
    keep = ang >= np.deg2rad(min_rotation_deg)
    if np.count_nonzero(keep) < 2:
        return HandEyeFailure(
            f"degenerate motion: fewer than two relative rotations ≥ {min_rotation_deg}°", n_poses=n
        )
    axes = rv[keep] / ang[keep, None]
    lam = np.linalg.eigvalsh(np.einsum("ki,kj->ij", axes, axes) / len(axes))[::-1]
    spread = float(np.rad2deg(2.0 * np.arctan(np.sqrt(max(lam[1], 0.0) / lam[0]))))
    if spread < min_axis_spread_deg:
        return HandEyeFailure(
            f"degenerate motion: relative rotation axes spread {spread:.3g}° < {min_axis_spread_deg}°",
            n_poses=n,
        )
    return None


def estimate_rbase_from_tracker(
    rbase_from_ee: np.ndarray, tracker_from_marker: np.ndarray, ee_from_marker: np.ndarray
) -> np.ndarray:
    """Y given X: chordal mean of ``rbase_from_ee_i · X · inv(tracker_from_marker_i)`` → (4, 4)."""
    A, B = _inputs(rbase_from_ee, tracker_from_marker)
    Ys = A @ ee_from_marker @ se3.inv(B)
    return se3.make(se3.mean_rotation(Ys[:, :3, :3]), Ys[:, :3, 3].mean(axis=0))


def handeye_residuals(
    rbase_from_ee: np.ndarray,
    tracker_from_marker: np.ndarray,
    ee_from_marker: np.ndarray,
    rbase_from_tracker: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pose loop closure ``inv(Y · tracker_from_marker_i) · rbase_from_ee_i · X``.

    Returns:
        (rotation_deg (N,), translation_mm (N,)); both zero for consistent data.
    """
    A, B = _inputs(rbase_from_ee, tracker_from_marker)
    E = se3.inv(rbase_from_tracker @ B) @ A @ ee_from_marker
    return se3.rotation_angle_deg(E[:, :3, :3]), np.linalg.norm(E[:, :3, 3], axis=-1)


def transform_error(estimated: np.ndarray, reference: np.ndarray) -> tuple[float, float]:
    """(rotation_deg, translation_mm) of ``inv(reference) · estimated``."""
    E = se3.inv(np.asarray(reference, dtype=np.float64)) @ np.asarray(estimated, dtype=np.float64)
    return float(se3.rotation_angle_deg(E[:3, :3])), float(np.linalg.norm(E[:3, 3]))


def _finish(
    A: np.ndarray, B: np.ndarray, X: np.ndarray, Y: np.ndarray, method: str, formulation: str
) -> HandEyeResult | HandEyeFailure:
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(Y))):
        return HandEyeFailure("solver returned non-finite values", method=method, n_poses=len(A))
    rot, trans = handeye_residuals(A, B, X, Y)
    return HandEyeResult(
        ee_from_marker=X,
        rbase_from_tracker=Y,
        residual_rotation_deg=rot,
        residual_translation_mm=trans,
        method=method,
        formulation=formulation,
        n_poses=len(A),
    )


def calibrate_hand_eye(
    rbase_from_ee: np.ndarray,
    tracker_from_marker: np.ndarray,
    *,
    method: str = "TSAI",
    min_axis_spread_deg: float = 5.0,
) -> HandEyeResult | HandEyeFailure:
    """AX = XB through ``cv2.calibrateHandEye`` (adapter in the module docstring).

    Args:
        rbase_from_ee: (N, 4, 4) robot forward kinematics per pose, mm.
        tracker_from_marker: (N, 4, 4) tracker readings of the end-effector marker body.
        method: one of :data:`AX_XB_METHODS`.
        min_axis_spread_deg: degeneracy threshold of :func:`check_motion`.

    Returns:
        :class:`HandEyeResult` (Y from :func:`estimate_rbase_from_tracker`) or :class:`HandEyeFailure`.
    """
    key = method.upper()
    if key not in AX_XB_METHODS:
        raise ValueError(f"unknown AX=XB method {method!r}; choose from {sorted(AX_XB_METHODS)}")
    A, B = _inputs(rbase_from_ee, tracker_from_marker)
    bad = check_motion(A, min_axis_spread_deg=min_axis_spread_deg)
    if bad is not None:
        return HandEyeFailure(bad.reason, method=key, n_poses=bad.n_poses)
    Rg, tg = _split(A)
    Rt, tt = _split(se3.inv(B))
    try:
        R, t = cv2.calibrateHandEye(Rg, tg, Rt, tt, method=AX_XB_METHODS[key])
    except cv2.error as exc:
        return HandEyeFailure(f"OpenCV error: {exc}", method=key, n_poses=len(A))
    X = se3.make(np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64).reshape(3))
    Y = estimate_rbase_from_tracker(A, B, X) if np.all(np.isfinite(X)) else np.full((4, 4), np.nan)
    return _finish(A, B, X, Y, key, "AX=XB")


def calibrate_robot_world_hand_eye(
    rbase_from_ee: np.ndarray,
    tracker_from_marker: np.ndarray,
    *,
    method: str = "SHAH",
    min_axis_spread_deg: float = 5.0,
) -> HandEyeResult | HandEyeFailure:
    """AX = YB through ``cv2.calibrateRobotWorldHandEye``: solves X and Y jointly.

    Args and returns as :func:`calibrate_hand_eye`; ``method`` one of :data:`AX_YB_METHODS`.
    """
    key = method.upper()
    if key not in AX_YB_METHODS:
        raise ValueError(f"unknown AX=YB method {method!r}; choose from {sorted(AX_YB_METHODS)}")
    A, B = _inputs(rbase_from_ee, tracker_from_marker)
    bad = check_motion(A, min_axis_spread_deg=min_axis_spread_deg)
    if bad is not None:
        return HandEyeFailure(bad.reason, method=key, n_poses=bad.n_poses)
    Rw, tw = _split(se3.inv(B))  # world2cam = marker_from_tracker
    Rb, tb = _split(se3.inv(A))  # base2gripper = ee_from_rbase
    try:
        R_b2w, t_b2w, R_g2c, t_g2c = cv2.calibrateRobotWorldHandEye(Rw, tw, Rb, tb, method=AX_YB_METHODS[key])
    except cv2.error as exc:
        return HandEyeFailure(f"OpenCV error: {exc}", method=key, n_poses=len(A))
    tracker_from_rbase = se3.make(np.asarray(R_b2w, float), np.asarray(t_b2w, float).reshape(3))
    marker_from_ee = se3.make(np.asarray(R_g2c, float), np.asarray(t_g2c, float).reshape(3))
    return _finish(A, B, se3.inv(marker_from_ee), se3.inv(tracker_from_rbase), key, "AX=YB")


def simulate_tracker_calibration(
    true_robot: SerialRobot,
    nominal_robot: SerialRobot,
    q_reported_deg: np.ndarray,
    *,
    ee_from_marker: np.ndarray,
    rbase_from_tracker: np.ndarray,
    tracker: OpticalTracker,
    body: RigidBody,
    rng: np.random.Generator,
    error_model: RobotErrorModel | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Synthetic calibration data: what the controller reports and what the tracker measures.

    The joints physically sit at ``actual_joints_deg(q_reported)`` (encoder noise of
    ``error_model``, none if ``None``); the marker's true pose follows from ``true_robot``; the
    reported kinematics use ``nominal_robot`` at the reported joints.

    Returns:
        (rbase_from_ee reported (N, 4, 4), tracker_from_marker measured (N, 4, 4)).
    """
    q_rep = np.asarray(q_reported_deg, dtype=np.float64)
    q_act = q_rep if error_model is None else error_model.actual_joints_deg(q_rep, rng=rng)
    tracker_from_marker_true = se3.inv(rbase_from_tracker) @ true_robot.rbase_from_ee(q_act) @ ee_from_marker
    measured = tracker.track(tracker_from_marker_true, body, rng=rng).tracker_from_body
    return nominal_robot.rbase_from_ee(q_rep), measured


def tip_rbase_tracker_chain(
    rbase_from_ee: np.ndarray,
    ee_from_os: np.ndarray,
    tracker_from_os: np.ndarray,
    tracker_from_ot: np.ndarray,
    tip_ot_mm: np.ndarray,
) -> np.ndarray:
    """Eq. 9: the tip in the robot base frame through the tracker chain.

    ``p_rbase = rbase_from_ee · ee_from_os · inv(tracker_from_os) · tracker_from_ot · p_ot`` with
    O_s the shaft marker (hand-eye X of the tracker calibration) and O_t the tip-segment marker.

    Args:
        rbase_from_ee, tracker_from_os, tracker_from_ot: (N, 4, 4); ee_from_os: (4, 4).
        tip_ot_mm: (3,) or (N, 3) tip point in the O_t frame.

    Returns:
        (N, 3) tip positions in the robot base frame, mm.
    """
    T = rbase_from_ee @ ee_from_os @ se3.inv(tracker_from_os) @ tracker_from_ot
    p = np.broadcast_to(np.asarray(tip_ot_mm, dtype=np.float64), (*T.shape[:-2], 3))
    return np.einsum("...ij,...j->...i", T[..., :3, :3], p) + T[..., :3, 3]


def tip_rbase_image_chain(
    rbase_from_ee: np.ndarray,
    ee_from_cm: np.ndarray,
    carm_from_cm: np.ndarray,
    tip_carm_mm: np.ndarray,
) -> np.ndarray:
    """Eq. 10: the tip in the robot base frame through the image-based hand-eye chain.

    ``p_rbase = rbase_from_ee · ee_from_cm · inv(carm_from_cm) · p_carm`` where ``p_carm`` is the
    registered tip (``carm_from_cmt · p_cmt`` in the paper; equivalently ``carm_from_cm ·
    tip_cm(control points)``).

    Args:
        rbase_from_ee, carm_from_cm: (N, 4, 4); ee_from_cm: (4, 4); tip_carm_mm: (N, 3).

    Returns:
        (N, 3) tip positions in the robot base frame, mm.
    """
    T = rbase_from_ee @ ee_from_cm @ se3.inv(carm_from_cm)
    p = np.asarray(tip_carm_mm, dtype=np.float64)
    return np.einsum("...ij,...j->...i", T[..., :3, :3], p) + T[..., :3, 3]


def tip_errors(tip_a_mm: np.ndarray | Sequence[float], tip_b_mm: np.ndarray | Sequence[float]) -> TipErrors:
    """Per-pose Euclidean distance between two tip estimates (N, 3), e.g. eq. 9 vs eq. 10."""
    a = np.atleast_2d(np.asarray(tip_a_mm, dtype=np.float64))
    b = np.atleast_2d(np.asarray(tip_b_mm, dtype=np.float64))
    return TipErrors(per_pose_mm=np.linalg.norm(a - b, axis=-1))
