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

The thresholds live in :class:`SafetyConfig`; docs/validation.md ("The checks' thresholds") gives
the data they were chosen on.
"""

from __future__ import annotations

from dataclasses import dataclass

from fluoronav.registration.cm.checks import MAX_MOTION_TIP_MM, CMCheckConfig

__all__ = ["SafetyConfig"]


@dataclass(frozen=True)
class SafetyConfig:
    """Thresholds of the registration checks.

    Attributes:
        max_landmark_residual_mm: a view's registered A or B may lie at most this far (mm at the
            detector) from the detected one.
        min_edge_ncc: a view's gradient NCC on the registered CM's outline must reach this.
        max_motion_tip_mm: the verification's CM tip (femur frame) may differ at most this much from
            the kinematic prediction (the robot's and the first registration's errors together).
        min_views: views that must pass for a CM registration to stand.
    """

    max_landmark_residual_mm: float = CMCheckConfig.max_landmark_residual_mm
    min_edge_ncc: float = CMCheckConfig.min_edge_ncc
    max_motion_tip_mm: float = MAX_MOTION_TIP_MM
    min_views: int = CMCheckConfig.min_views

    def cm_checks(self) -> CMCheckConfig:
        """The per-view thresholds of a CM registration."""
        return CMCheckConfig(
            max_landmark_residual_mm=self.max_landmark_residual_mm,
            min_edge_ncc=self.min_edge_ncc,
            min_views=self.min_views,
        )
