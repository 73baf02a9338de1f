"""The checks a registration must pass before the robot may act on it: their thresholds.

A surgical navigation must know when it is wrong. Each CM registration is checked per view
(:mod:`fluoronav.registration.cm.checks`): the registered landmarks against the detected ones and
the registered CM's outline against the image. A view that fails is left out and the CM registered
again without it while enough views remain; otherwise the navigation refuses. The verification's CM
is also checked against the robot's own account of the move: the first registration moved by the
nominal kinematics between the two joint readings
(:func:`fluoronav.navigation.targeting.predicted_femur_from_cm`) must agree with what the
verification images show; where it does not, a second start from that prediction is tried, and a
verification that still fails gives no corrective command.

The robot's commands are bounded too: the first move and the correction may turn no joint by
more than ``max_joint_motion_deg``, the first move may carry the CM tip and turn the CM only so far
(``max_move_mm``, ``max_move_deg``), and the correction, which only translates, must be small
(``max_correction_mm``, ``max_correction_deg``) and no larger than the agreement between the robot's
kinematics and the verification images can vouch for: its tip translation may exceed the planned
tip's distance from the kinematic prediction by at most ``max_motion_tip_mm``. Where the images
demand more than that, either they or the kinematics are wrong, and the robot must not move on
either's word. A command beyond a bound is refused with the plan's name, the measured value and the
bound.

The thresholds live in :class:`SafetyConfig`; docs/validation.md ("The checks' thresholds") gives
the data they were chosen on.
"""

from __future__ import annotations

from dataclasses import dataclass

from fluoronav.registration.cm.checks import MAX_MOTION_TIP_MM, CMCheckConfig

__all__ = ["SafetyConfig"]


@dataclass(frozen=True)
class SafetyConfig:
    """Thresholds of the registration checks and bounds of the robot's commands.

    Attributes:
        max_landmark_residual_mm: a view's registered A or B may lie at most this far (mm at the
            detector) from the detected one.
        min_edge_ncc: a view's gradient NCC on the registered CM's outline must reach this.
        max_motion_tip_mm: the verification's CM tip (femur frame) may differ at most this much from
            the kinematic prediction (the robot's and the first registration's errors together).
        min_views: views that must pass for a CM registration to stand.
        max_joint_motion_deg: no joint of a command (first move or correction) may turn by more
            than this (degrees, wrapped). Near a patient, with the CM at the bone, a large joint
            turn is a hazard in itself: the arm's links sweep far even when the tip travels little.
        max_move_mm: the first move may carry the CM tip at most this far (mm, between its
            registered pose and the target). The working pose is chosen within a hand's breadth of
            the entry point; the bound stops a wrong registration or plan from sending the robot
            across the table while letting every such approach through.
        max_move_deg: the first move may turn the CM by at most this (degrees, geodesic, registered
            pose to target). The working pose points the CM roughly at the hip; a larger turn means
            the plan or a registration is not what the approach assumed.
        max_correction_mm: the correction may move the CM tip at most this far (mm). A correction
            fixes the robot's residual error after a move that reached the plan, not a new approach.
        max_correction_deg: the correction may turn the CM at most this much (degrees); it only
            translates, so anything above numerical noise is a fault.
    """

    max_landmark_residual_mm: float = CMCheckConfig.max_landmark_residual_mm
    min_edge_ncc: float = CMCheckConfig.min_edge_ncc
    max_motion_tip_mm: float = MAX_MOTION_TIP_MM
    min_views: int = CMCheckConfig.min_views
    max_joint_motion_deg: float = 30.0
    max_move_mm: float = 200.0
    max_move_deg: float = 90.0
    max_correction_mm: float = 10.0
    max_correction_deg: float = 5.0

    def cm_checks(self) -> CMCheckConfig:
        """The per-view thresholds of a CM registration."""
        return CMCheckConfig(
            max_landmark_residual_mm=self.max_landmark_residual_mm,
            min_edge_ncc=self.min_edge_ncc,
            min_views=self.min_views,
        )
