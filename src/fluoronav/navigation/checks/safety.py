"""The checks a registration must pass before the robot may act on it: their thresholds.

A surgical navigation must know when it is wrong. Each CM registration is checked per view
(:mod:`fluoronav.registration.cm.checks`): the registered landmarks against the detected ones and
the registered CM's outline against the image. A view that fails is left out and the CM registered
again without it while enough views remain; otherwise the navigation refuses.

The robot's commands are bounded too: the first move and the correction may turn no joint by
more than ``max_joint_motion_deg``, the first move may carry the CM tip and turn the CM only so far
(``max_move_mm``, ``max_move_deg``), and the correction, which only translates, must be small
(``max_correction_mm``, ``max_correction_deg``) and no larger than the agreement between the robot's
kinematics and the verification images can vouch for: its tip translation may exceed the planned
tip's distance from the kinematic prediction by at most ``max_motion_tip_mm``, unless the images
overrule the kinematics (below). A command beyond a bound is refused with the plan's name, the
measured value and the bound.

The verification finds the CM where its images show it (the kinematic prediction is one start
among the images' own, not a gate), then compares the two. Joint readings that differ from the
command are refused at once. A disagreement beyond ``max_motion_tip_mm`` with readings that match
the command points at the hand-eye matrix (or the first registration): the images are then
trusted over the kinematics only when they are unambiguous (``overrule_min_views`` views passed,
none left out, landmarks within ``overrule_max_landmark_residual_mm``) and the correction is within
``max_correction_mm``. That is safe because the correction is a relative move measured in the
images: a translation of the CM from where the images show it, executed from the current joints,
so a hand-eye translation error cancels and a hand-eye rotation error δ turns the correction by δ
(a 10 mm correction with a 3° error errs by 0.5 mm). The result then carries a warning naming the
disagreement.

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
        min_views: views that must pass for a CM registration to stand (a view that fails is left
            out only while this many remain).
        verify_min_views: the same for a verification of two views whose CM is fused with the
            robot's kinematics (``VerificationConfig.fuse_kinematics``). One view with the
            kinematics' depth is what a one-image verification is: a view whose detection is wrong
            may be left out of two down to one, rather than refuse where one image alone would
            pass. Three views keep ``min_views``: left out down to one they could no longer
            overrule kinematics that are wrong (a hand-eye matrix 10 mm off), which two views
            from the images' own starts can correct.
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
        max_joint_reading_deg: the joints read with the verification images may differ from the
            commanded ones by at most this (degrees, any joint). A robot that did not reach its
            command, or readings that are wrong, make every kinematic account of the move wrong,
            and a correction computed from those readings would be too.
        overrule_min_views: where the verification's CM disagrees with the kinematics by more than
            ``max_motion_tip_mm``, it is corrected from the images only when at least this many
            verification views passed the CM's checks and none was left out, from the images' own
            start ...
        overrule_max_landmark_residual_mm: ... and every view's registered landmarks lie within
            this of the detected ones (mm at the detector). Otherwise the navigation refuses,
            naming the hand-eye matrix and the joint readings.
        consistent_views_max_cost_px: where the verification's CM fails its checks, the refusal
            names the kinematics when the views agree on a CM (their multi-view centreline fit's
            mean cost within this, pixels at the detection's resolution) that lies more than
            ``max_motion_tip_mm`` from the prediction.
        max_fbg_departure_sigmas: the first registration's CM shape may depart from the FBG reading
            by at most its prior's tolerance plus this many of its σ (the case's stated
            ``fbg_sigma_deg``, or the flat-bottomed default's walls): a shape pulled further has
            been bent to make up for a base that is off (check ``fbg_shape``,
            :func:`~fluoronav.registration.cm.checks.judge_shape`). None: not checked.
    """

    max_landmark_residual_mm: float = CMCheckConfig.max_landmark_residual_mm
    min_edge_ncc: float = CMCheckConfig.min_edge_ncc
    max_motion_tip_mm: float = MAX_MOTION_TIP_MM
    min_views: int = CMCheckConfig.min_views
    verify_min_views: int = 1
    max_joint_motion_deg: float = 30.0
    max_move_mm: float = 200.0
    max_move_deg: float = 90.0
    max_correction_mm: float = 10.0
    max_correction_deg: float = 5.0
    max_joint_reading_deg: float = 0.5
    overrule_min_views: int = 3
    overrule_max_landmark_residual_mm: float = 1.0
    consistent_views_max_cost_px: float = 3.0
    max_fbg_departure_sigmas: float | None = 4.0

    def cm_checks(self, *, fused_views: int | None = None, fbg: bool = False) -> CMCheckConfig:
        """The thresholds of a CM registration; ``fused_views``: the number of views of a
        verification whose CM is fused with the robot's kinematics (two or fewer may stand on
        ``verify_min_views``), None for any other registration; ``fbg``: its shape's prior is the
        FBG reading (the first registration), checked by ``max_fbg_departure_sigmas``."""
        two_fused = fused_views is not None and fused_views <= 2
        return CMCheckConfig(
            max_landmark_residual_mm=self.max_landmark_residual_mm,
            min_edge_ncc=self.min_edge_ncc,
            min_views=self.verify_min_views if two_fused else self.min_views,
            max_shape_departure_sigmas=self.max_fbg_departure_sigmas if fbg else None,
        )
