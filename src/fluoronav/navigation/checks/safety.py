"""The checks a registration must pass before the robot may act on it: their thresholds.

Each CM registration is checked per view (:mod:`fluoronav.registration.cm.checks`); a view that fails is left
out while enough views remain, otherwise the navigation refuses. The robot's commands are bounded: no joint
turns more than ``max_joint_motion_deg``; the first move carries the CM tip and turns the CM only so far
(``max_move_mm``, ``max_move_deg``); the correction, a translation, stays small (``max_correction_mm``,
``max_correction_deg``) and within what the agreement of the kinematics and the verification images can vouch
for (``max_motion_tip_mm``), unless unambiguous images overrule the kinematics (``overrule_min_views``,
``overrule_max_landmark_residual_mm``). A command beyond a bound is refused naming the plan, the value and the
bound. The thresholds live in :class:`SafetyConfig`; docs/navigation.md ("Checks") says what each does and
docs/validation.md ("The checks' thresholds") what data they rest on.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from fluoronav.registration.cm.checks import MAX_MOTION_TIP_MM, CMCheckConfig
from fluoronav.settings import setting

__all__ = ["SafetyConfig"]


@dataclass(frozen=True)
class SafetyConfig:
    """Thresholds of the registration checks and bounds of the robot's commands.

    Attributes:
        cm: the CM registration's per-view checks (:class:`CMCheckConfig`): a view's registered A
            or B at most ``max_landmark_residual_mm`` (mm at the detector) from the detected one,
            its gradient NCC on the registered CM's outline at least ``min_edge_ncc``, and
            ``min_views`` views that must pass for a CM registration to stand (a view that fails is
            left out only while this many remain). Its ``max_shape_departure_sigmas`` is
            ``max_fbg_departure_sigmas`` for the first registration (:meth:`cm_checks`).
        max_motion_tip_mm: the verification's CM tip (femur frame) may differ at most this much from
            the kinematic prediction (the robot's and the first registration's errors together).
        verify_min_views: ``cm.min_views`` for a verification of two views whose CM is fused with the
            robot's kinematics (``VerificationConfig.fuse_kinematics``). One view with the
            kinematics' depth is what a one-image verification is: a view whose detection is wrong
            may be left out of two down to one, rather than refuse where one image alone would
            pass. Three views keep ``cm.min_views``: left out down to one they could no longer
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
        detection_check_min_views: where the verification's detections (or the CM registered from
            them) lie more than ``max_motion_tip_mm`` from the kinematic prediction, the CM is
            registered from the prediction on the images alone
            (:mod:`~fluoronav.navigation.disagreement`); the refusal names the detection rather
            than the kinematics where that CM stays at the prediction, its outline passes ``cm``'s
            edge check in at least this many views, and a view's detected landmarks lie further
            than ``cm.max_landmark_residual_mm`` from it. Fewer views cannot tell which is wrong.
        max_fbg_departure_sigmas: the first registration's CM shape may depart from the FBG reading
            by at most its prior's tolerance plus this many of its σ (the case's stated
            ``fbg_sigma_deg``, or the flat-bottomed default's walls): a shape pulled further has
            been bent to make up for a base that is off (check ``fbg_shape``,
            :func:`~fluoronav.registration.cm.checks.judge_shape`). None: not checked.
    """

    cm: CMCheckConfig = setting(doc="the CM registration's per-view checks", default_factory=CMCheckConfig)
    max_motion_tip_mm: float = setting(
        MAX_MOTION_TIP_MM,
        "the verification's CM tip may differ this much from the kinematics",
        unit="mm",
        ge=0,
    )
    verify_min_views: int = setting(
        1, "cm.min_views of a two-view verification fused with the kinematics", ge=1
    )
    max_joint_motion_deg: float = setting(30.0, "no joint of a command may turn by more", unit="deg", ge=0)
    max_move_mm: float = setting(
        200.0, "the first move may carry the CM tip at most this far", unit="mm", ge=0
    )
    max_move_deg: float = setting(90.0, "the first move may turn the CM at most this much", unit="deg", ge=0)
    max_correction_mm: float = setting(
        10.0, "the correction may move the CM tip at most this far", unit="mm", ge=0
    )
    max_correction_deg: float = setting(
        5.0, "the correction may turn the CM at most this much", unit="deg", ge=0
    )
    max_joint_reading_deg: float = setting(
        0.5, "the verification's joint readings may differ this much from the command", unit="deg", ge=0
    )
    overrule_min_views: int = setting(
        3, "views that must pass for the images to overrule the kinematics", ge=1
    )
    overrule_max_landmark_residual_mm: float = setting(
        1.0, "for the images to overrule, every view's landmarks within this of the detected", unit="mm", ge=0
    )
    consistent_views_max_cost_px: float = setting(
        3.0, "views agree on a CM where their centreline fit's mean cost is within this", unit="px", ge=0
    )
    detection_check_min_views: int = setting(
        2, "views whose outline must fit the CM at the prediction for a detection to be named", ge=2
    )
    max_fbg_departure_sigmas: float | None = setting(
        4.0,
        "the first CM shape's departure from the FBG reading beyond its tolerance; none: unchecked",
        unit="sigma",
        ge=0,
    )

    def cm_checks(self, *, fused_views: int | None = None, fbg: bool = False) -> CMCheckConfig:
        """The thresholds of a CM registration; ``fused_views``: the number of views of a
        verification whose CM is fused with the robot's kinematics (two or fewer may stand on
        ``verify_min_views``), None for any other registration; ``fbg``: its shape's prior is the
        FBG reading (the first registration), checked by ``max_fbg_departure_sigmas``."""
        two_fused = fused_views is not None and fused_views <= 2
        return dataclasses.replace(
            self.cm,
            min_views=self.verify_min_views if two_fused else self.cm.min_views,
            max_shape_departure_sigmas=self.max_fbg_departure_sigmas if fbg else None,
        )
