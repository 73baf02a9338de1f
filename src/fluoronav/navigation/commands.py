"""The robot's commands measured and bounded: joint motion, the CM tip's swept path, the move's size.

Every command (the first move, the correction) is measured before it is given: each joint's turn,
the path the CM tip sweeps while the joints move linearly (its length and its largest deviation
from the straight segment), and how far the CM tip travels and the CM turns from its registered
pose to the target. The measurements go into the stage's diagnostics; a command beyond a bound of
:class:`~fluoronav.navigation.checks.safety.SafetyConfig` is refused (:class:`NavigationRefused`)
naming the plan, the measured value and the bound. The verification is judged here too: its joint
readings against the command (:func:`check_joint_readings`), the CM its images show against where
the kinematics put it (:func:`judge_kinematics`: agree, overrule with a warning, or refuse) and a
disagreement named for its cause: the kinematics, a wrong detection, or one view that cannot tell.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fluoronav.geometry import se3
from fluoronav.manipulator.robot import SerialRobot
from fluoronav.navigation.checks.safety import SafetyConfig
from fluoronav.navigation.result import NavigationRefused
from fluoronav.navigation.targeting import SweptPath, joint_motion_deg, swept_tip_path

__all__ = [
    "CommandMotion",
    "KinematicsVerdict",
    "at_prediction_said",
    "check_correction",
    "check_first_move",
    "check_joint_readings",
    "correction_allowed_mm",
    "judge_kinematics",
    "measure_command",
    "name_kinematics_disagreement",
    "name_one_view_disagreement",
    "refuse_wrong_detection",
    "undetected_refused",
    "undetected_warning",
    "view_check_warning",
    "wrong_detection_warning",
]


@dataclass(frozen=True)
class CommandMotion:
    """What a command does to the robot and the CM.

    Attributes:
        joint_motion_deg: (n_joints,) how far each joint turns (degrees, wrapped).
        swept: the CM tip's path under linear joint interpolation (robot base frame).
        tip_move_mm: the CM tip's displacement, registered pose → target (femur frame).
        rotation_deg: the CM's rotation, registered pose → target (degrees, geodesic).
    """

    joint_motion_deg: np.ndarray
    swept: SweptPath
    tip_move_mm: float
    rotation_deg: float

    @property
    def max_joint_motion_deg(self) -> float:
        return float(np.max(self.joint_motion_deg))

    def diagnostics(self) -> dict[str, Any]:
        """The JSON-ready stage diagnostics (``joint_motion_deg`` is the largest joint's turn)."""
        return {
            "joint_motion_deg": self.max_joint_motion_deg,
            "joint_motion_per_joint_deg": [float(v) for v in self.joint_motion_deg],
            "swept_path_mm": self.swept.length_mm,
            "swept_straight_mm": self.swept.straight_mm,
            "swept_max_deviation_mm": self.swept.max_deviation_mm,
            "tip_move_mm": self.tip_move_mm,
            "rotation_deg": self.rotation_deg,
        }


def measure_command(
    robot: SerialRobot,
    q_from_deg: np.ndarray,
    q_to_deg: np.ndarray,
    *,
    ee_from_cm: np.ndarray,
    tip_cm_mm: np.ndarray,
    femur_from_cm_from: np.ndarray,
    femur_from_cm_to: np.ndarray,
    tip_to_cm_mm: np.ndarray | None = None,
) -> CommandMotion:
    """Measure a command (joints ``q_from_deg`` → ``q_to_deg``).

    Args:
        robot: the kinematic model the controller uses.
        q_from_deg, q_to_deg: (n_joints,) joints now and commanded.
        ee_from_cm: (4, 4) hand-eye matrix.
        tip_cm_mm: (3,) the CM tip in its base frame (its shape now).
        femur_from_cm_from, femur_from_cm_to: (4, 4) the CM registered now and its target.
        tip_to_cm_mm: (3,) the tip in the target's shape; ``tip_cm_mm`` by default.
    """
    tip_to = tip_cm_mm if tip_to_cm_mm is None else tip_to_cm_mm
    A = se3.as_transform_array(femur_from_cm_from, "femur_from_cm_from")
    B = se3.as_transform_array(femur_from_cm_to, "femur_from_cm_to")
    return CommandMotion(
        joint_motion_deg=joint_motion_deg(q_from_deg, q_to_deg),
        swept=swept_tip_path(robot, q_from_deg, q_to_deg, ee_from_cm=ee_from_cm, tip_cm_mm=tip_cm_mm),
        tip_move_mm=float(np.linalg.norm(se3.apply(B, tip_to) - se3.apply(A, tip_cm_mm))),
        rotation_deg=float(se3.rotation_angle_deg(A[:3, :3].T @ B[:3, :3])),
    )


def _refuse_joints(m: CommandMotion, safety: SafetyConfig, stage: str, what: str, plan_name: str) -> None:
    if m.max_joint_motion_deg > safety.max_joint_motion_deg:
        j = int(np.argmax(m.joint_motion_deg))
        raise NavigationRefused(
            stage,
            "joint_motion",
            f"plan '{plan_name}': the {what} would turn joint {j + 1} by {m.max_joint_motion_deg:.1f}°, "
            f"more than the bound {safety.max_joint_motion_deg:g}° (max_joint_motion_deg)",
        )


def check_first_move(m: CommandMotion, safety: SafetyConfig, *, plan_name: str, stage: str = "robot") -> None:
    """Refuse a first move beyond ``max_move_mm``, ``max_move_deg`` or ``max_joint_motion_deg``.

    Raises:
        NavigationRefused: check ``move_length``, ``move_rotation`` or ``joint_motion``.
    """
    if m.tip_move_mm > safety.max_move_mm:
        raise NavigationRefused(
            stage,
            "move_length",
            f"plan '{plan_name}': the first move would carry the CM tip {m.tip_move_mm:.1f} mm, "
            f"more than the bound {safety.max_move_mm:g} mm (max_move_mm)",
        )
    if m.rotation_deg > safety.max_move_deg:
        raise NavigationRefused(
            stage,
            "move_rotation",
            f"plan '{plan_name}': the first move would turn the CM by {m.rotation_deg:.1f}°, "
            f"more than the bound {safety.max_move_deg:g}° (max_move_deg)",
        )
    _refuse_joints(m, safety, stage, "first move", plan_name)


def correction_allowed_mm(safety: SafetyConfig, predicted_tip_error_mm: float) -> float:
    """The largest correction (mm) the verification can vouch for.

    The kinematics predict where the move put the CM tip; the verification images may disagree with
    that by up to ``max_motion_tip_mm``. So the tip can be at most ``predicted_tip_error_mm`` (the
    planned tip's distance from the prediction) + ``max_motion_tip_mm`` from the plan; a correction
    larger than that rests on images that contradict the robot.
    """
    return float(predicted_tip_error_mm) + safety.max_motion_tip_mm


def check_correction(
    m: CommandMotion,
    safety: SafetyConfig,
    *,
    plan_name: str,
    predicted_tip_error_mm: float,
    images_overrule: bool = False,
    stage: str = "correct",
) -> None:
    """Refuse a correction beyond ``max_correction_mm``, ``max_correction_deg``, what the
    verification vouches for (:func:`correction_allowed_mm`; not where ``images_overrule``: the
    images were judged unambiguous enough to be trusted over the kinematics,
    :mod:`fluoronav.navigation.checks.safety`) or ``max_joint_motion_deg``.

    Raises:
        NavigationRefused: check ``correction_length``, ``correction_rotation``,
            ``correction_within_uncertainty`` or ``joint_motion``.
    """
    if m.tip_move_mm > safety.max_correction_mm:
        raise NavigationRefused(
            stage,
            "correction_length",
            f"plan '{plan_name}': the correction would move the CM tip {m.tip_move_mm:.1f} mm, "
            f"more than the bound {safety.max_correction_mm:g} mm (max_correction_mm)",
        )
    if m.rotation_deg > safety.max_correction_deg:
        raise NavigationRefused(
            stage,
            "correction_rotation",
            f"plan '{plan_name}': the correction would turn the CM by {m.rotation_deg:.2f}°, "
            f"more than the bound {safety.max_correction_deg:g}° (max_correction_deg)",
        )
    allowed = correction_allowed_mm(safety, predicted_tip_error_mm)
    if not images_overrule and m.tip_move_mm > allowed:
        raise NavigationRefused(
            stage,
            "correction_within_uncertainty",
            f"plan '{plan_name}': the correction of {m.tip_move_mm:.1f} mm is more than the "
            f"verification vouches for, {allowed:.1f} mm (the planned tip {predicted_tip_error_mm:.1f} mm "
            f"from the kinematic prediction + max_motion_tip_mm {safety.max_motion_tip_mm:g} mm)",
        )
    _refuse_joints(m, safety, stage, "correction", plan_name)


def check_joint_readings(
    reading_minus_command_deg: np.ndarray, safety: SafetyConfig, *, stage: str = "verify_joints"
) -> None:
    """Refuse joints read with the verification images that differ from the first move's command.

    Args:
        reading_minus_command_deg: (n_joints,) how far each joint read lies from its command
            (degrees, wrapped: :func:`~fluoronav.navigation.targeting.joint_motion_deg`).
        safety: the bound ``max_joint_reading_deg``.

    Raises:
        NavigationRefused: check ``joint_readings``, naming the joint that differs most.

    Notes:
        The differences are measured by the caller, as a command's motion is, so that they are
        recorded in the stage's diagnostics whether or not the readings are refused.
    """
    dq = np.asarray(reading_minus_command_deg, np.float64)
    if float(np.max(dq)) > safety.max_joint_reading_deg:
        j = int(np.argmax(dq))
        raise NavigationRefused(
            stage,
            "joint_readings",
            f"the joints read with the verification images differ from the commanded ones by "
            f"{dq[j]:.2f}° (joint {j + 1}; at most {safety.max_joint_reading_deg:g}°, "
            "max_joint_reading_deg): the robot did not reach its command or its joint readings are "
            "wrong; check the joint readings",
        )


@dataclass(frozen=True)
class KinematicsVerdict:
    """The verification's CM judged against the robot's kinematics (:func:`judge_kinematics`).

    Attributes:
        images_overrule: True where they disagree and the images are trusted over the kinematics.
        warning: what the user must be told where the images overrule; "" otherwise.
    """

    images_overrule: bool
    warning: str = ""


def judge_kinematics(
    cm_diagnostics: Mapping[str, Any],
    left_out: Mapping[str, str],
    safety: SafetyConfig,
    *,
    stage: str = "correct",
) -> KinematicsVerdict:
    """The verification's CM against the robot's kinematics (:mod:`fluoronav.navigation.checks.safety`).

    Args:
        cm_diagnostics: the ``verify_cm`` stage's diagnostics: ``motion_tip_mm`` (how far the CM
            tip the images show is from the kinematic prediction), ``views_used``, per view
            ``landmark_residual_mm``, and optionally ``tries`` and ``left_out``.
        left_out: the views the bones' checks left out of the verification, name → why.
        safety: the bounds ``max_motion_tip_mm``, ``max_correction_mm``, ``overrule_min_views``
            and ``overrule_max_landmark_residual_mm``.

    Returns:
        Not overruling where they agree (within ``max_motion_tip_mm``); overruling, with the
        warning, where they disagree and the images are unambiguous enough to be trusted over the
        kinematics.

    Raises:
        NavigationRefused: (check ``kinematics_disagree``; ``detection_or_kinematics`` where one
            view was used: it cannot tell its detection from the kinematics) they disagree and the
            images cannot overrule the kinematics, or the disagreement is beyond a correction.
    """
    tip_mm = float(cm_diagnostics["motion_tip_mm"])
    if tip_mm <= safety.max_motion_tip_mm:
        return KinematicsVerdict(images_overrule=False)
    said = (
        f"the CM the verification images show is {tip_mm:.1f} mm from where the robot's kinematics put "
        f"it (at most {safety.max_motion_tip_mm:g} mm): check the hand-eye matrix and the joint readings"
    )
    check = "kinematics_disagree"
    if len(cm_diagnostics["views_used"]) == 1:  # one view's CM may be the one that is wrong
        said += " (one image cannot tell whether its detection or the kinematics is wrong: a second view can)"
        check = "detection_or_kinematics"
    if tip_mm > safety.max_correction_mm:
        raise NavigationRefused(
            stage,
            check,
            f"{said}, and that the images were taken after the move; more than a correction may "
            f"move ({safety.max_correction_mm:g} mm, max_correction_mm)",
        )
    why_not = _ambiguity(cm_diagnostics, left_out, safety)
    if why_not:
        raise NavigationRefused(stage, check, f"{said}; the images cannot overrule them: {why_not}")
    n = len(cm_diagnostics["views_used"])
    worst = max(float(v["landmark_residual_mm"] or 0.0) for v in cm_diagnostics["views"].values())
    return KinematicsVerdict(
        images_overrule=True,
        warning=f"{said}. Corrected from the images: {n} views agree (landmarks within {worst:.2f} mm), "
        "and a correction measured in the images does not depend on the hand-eye translation.",
    )


def name_kinematics_disagreement(
    exc: NavigationRefused, cm_diagnostics: Mapping[str, Any], safety: SafetyConfig, *, evidence: str = ""
) -> NavigationRefused:
    """A refusal of the verification's CM registration, named for its cause where that is the
    kinematics: the CM's landmarks triangulated from the verification images lie more than
    ``max_motion_tip_mm`` from where the robot's kinematics put them, and the views agree on them
    (their centreline fit within ``consistent_views_max_cost_px``).

    Notes:
        A CM that is far from the kinematic prediction is often hard to register (the search
        starts at the prediction among the images' own starts, and the ROI and landmark prior sit
        where the kinematics say), so the registration's own check, not the kinematics, refuses
        first (a landmark residual, with a hand-eye matrix that is off by a centimetre). What a
        user must check then is the hand-eye matrix and the joint readings; the registration's
        failure stays in the reason. Views that disagree among themselves (a wrong
        detection) say nothing about the kinematics, and the refusal is left as it was.
        ``evidence``: what the images showed at the prediction (:func:`at_prediction_said`), said
        before the registration's failure.

    Returns:
        ``exc`` itself, or a refusal with check ``kinematics_disagree`` (same stage and view).
    """
    gap = float(cm_diagnostics.get("prediction_gap_mm", float("nan")))
    cost = float(cm_diagnostics.get("init_cost_px", float("nan")))
    if exc.check == "kinematics_disagree" or not (
        gap > safety.max_motion_tip_mm and cost <= safety.consistent_views_max_cost_px
    ):
        return exc
    return NavigationRefused(
        exc.stage,
        "kinematics_disagree",
        f"the CM's landmarks in the verification images are {gap:.1f} mm from where the robot's "
        f"kinematics put them (at most {safety.max_motion_tip_mm:g} mm): check the hand-eye matrix "
        f"and the joint readings; {evidence + '; ' if evidence else ''}the CM could not be registered "
        f"there ({exc.check}: {exc.detail})",
        view=exc.view,
    )


def name_one_view_disagreement(
    exc: NavigationRefused, cm_diagnostics: Mapping[str, Any], safety: SafetyConfig
) -> NavigationRefused:
    """A refusal of a verification of one view whose CM's landmarks lie more than
    ``max_motion_tip_mm`` from the kinematic prediction (``prediction_gap_mm``, the reprojection
    distance at the CM's depth): one image cannot tell a detection that found another structure from
    kinematics that are off, and says so (check ``detection_or_kinematics``, same stage and view);
    ``exc`` itself where they agree."""
    gap = float(cm_diagnostics.get("prediction_gap_mm", float("nan")))
    if not gap > safety.max_motion_tip_mm:
        return exc
    return NavigationRefused(
        exc.stage,
        "detection_or_kinematics",
        f"the CM's landmarks in the one verification image are {gap:.1f} mm from where the robot's "
        f"kinematics put them (at most {safety.max_motion_tip_mm:g} mm): one image cannot tell whether "
        "its detection (another structure found) or the kinematics (the hand-eye matrix, the joint "
        f"readings) are wrong; take a second verification view; the CM could not be registered there "
        f"({exc.check}: {exc.detail})",
        view=exc.view,
    )


def _offsets_said(offsets_mm: Mapping[str, float]) -> str:
    return ", ".join(f"{name} ({mm:.1f} mm)" for name, mm in offsets_mm.items())


def at_prediction_said(at_prediction: Mapping[str, Any], min_edge_ncc: float) -> str:
    """What the CM registered from the kinematic prediction on the images alone showed (the
    ``verify_cm`` stage's ``at_prediction``: its views' ``edge_ncc``, its ``motion_tip_mm``)."""
    ncc = {n: float(v["edge_ncc"]) for n, v in at_prediction["views"].items()}
    fit = sum(v >= min_edge_ncc for v in ncc.values())
    return (
        f"registered from the kinematic prediction on the images alone, the CM's outline fits {fit} of "
        f"{len(ncc)} views (edge NCC {min(ncc.values()):.2f} at worst, at least {min_edge_ncc:g}) and "
        f"ends {float(at_prediction['motion_tip_mm']):.1f} mm from the prediction"
    )


def _wrong_detection_said(
    offsets_mm: Mapping[str, float],
    gap_mm: float,
    safety: SafetyConfig,
    failed: NavigationRefused | None = None,
) -> str:
    """``failed``: the detections' registration refused on a view's check (their CM within
    ``max_motion_tip_mm`` of the prediction); None: their CM lay beyond it."""
    said = f"the landmarks detected in {_offsets_said(offsets_mm)} lie elsewhere than the CM the images show"
    if failed is None:
        said += (
            f" where the robot's kinematics put it: the detections' CM is {gap_mm:.1f} mm from the "
            f"prediction (at most {safety.max_motion_tip_mm:g} mm)"
        )
    else:
        said += (
            " where the robot's kinematics put it: the CM registered from the detections failed its "
            f"checks ({failed.check} in {failed.view}: {failed.detail})"
        )
    return said + (
        ", while the CM registered there on the images alone fits them; the detector found another "
        "structure, the hand-eye matrix and the joint readings agree with the images"
    )


def refuse_wrong_detection(
    offsets_mm: Mapping[str, float],
    gap_mm: float,
    safety: SafetyConfig,
    *,
    why: str,
    stage: str = "verify_cm",
    failed: NavigationRefused | None = None,
) -> NavigationRefused:
    """The refusal (check ``detection_disagrees``) of a verification whose detections are wrong
    (:func:`~fluoronav.navigation.disagreement.images_side_with`): ``offsets_mm`` per view how far its
    detected landmarks lie from the CM at the prediction (mm at the detector), ``gap_mm`` how far the
    detections' CM lies from the prediction, ``why`` why it does not go on with the CM there."""
    return NavigationRefused(
        stage,
        "detection_disagrees",
        f"{_wrong_detection_said(offsets_mm, gap_mm, safety, failed)}; not corrected from it: {why}",
        view=", ".join(offsets_mm),
    )


def wrong_detection_warning(
    offsets_mm: Mapping[str, float],
    gap_mm: float,
    safety: SafetyConfig,
    *,
    failed: NavigationRefused | None = None,
) -> str:
    """The warning of a verification that goes on with the CM at the prediction where its
    detections are wrong (check ``detection_disagrees``; arguments as :func:`refuse_wrong_detection`)."""
    said = _wrong_detection_said(offsets_mm, gap_mm, safety, failed)
    return (
        f"detection_disagrees: {said}. Corrected from the CM registered at the prediction, which passed "
        "every view's check; check the detection in those views"
    )


def view_check_warning(failed: NavigationRefused) -> str:
    """The warning of a verification that goes on with the CM registered at the kinematic prediction
    on the images alone after the detections' registration failed a view's check (``failed``) while
    the detections agree with that CM."""
    return (
        f"{failed.check}: the CM registered from the detections failed its checks in {failed.view} "
        f"({failed.detail}); registered from the kinematic prediction on the images alone it passed "
        "every view's check, and the navigation goes on with it"
    )


def undetected_refused(views: Sequence[Any], exc: NavigationRefused) -> NavigationRefused:
    """The refusal of a verification whose views showed the detector no CM, after the CM registered
    from the kinematic prediction on the images alone refused too (``exc``): check ``views_with_cm``
    (stage ``verify_detect``), with that registration's failure as the evidence."""
    names = ", ".join(v.name for v in views)
    return NavigationRefused(
        "verify_detect",
        "views_with_cm",
        f"the CM was found in 0 of {len(views)} views, and registered from the kinematic prediction "
        f"on the images alone it failed its checks (stage {exc.stage}, check {exc.check}: {exc.detail})",
        view=names,
    )


def undetected_warning(views: Sequence[Any]) -> str:
    """The warning of a verification that went on without a detection (``register_undetected``)."""
    names = ", ".join(v.name for v in views)
    return (
        f"views_with_cm: the CM was found in none of the verification views ({names}); "
        "registered from the kinematic prediction on the images alone, it passed every view's check. "
        "Check the detection in those views"
    )


def _ambiguity(cm_diag: Mapping[str, Any], left_out: Mapping[str, str], safety: SafetyConfig) -> str:
    """Why the verification's images cannot overrule the kinematics ("" where they can)."""
    if left_out or cm_diag.get("left_out"):
        return f"views left out ({', '.join({**left_out, **cm_diag.get('left_out', {})})})"
    if int(cm_diag.get("tries", 1)) > 1:
        return "the images' own starts failed their checks"
    n = len(cm_diag["views_used"])
    if n < safety.overrule_min_views:
        return f"{n} views passed, {safety.overrule_min_views} needed (overrule_min_views)"
    res = [
        float(v["landmark_residual_mm"])
        for v in cm_diag["views"].values()
        if v["landmark_residual_mm"] is not None
    ]
    if len(res) < n:
        missing = [k for k, v in cm_diag["views"].items() if v["landmark_residual_mm"] is None]
        return f"no CM detected in {', '.join(missing)} to check the registered landmarks against"
    if max(res) > safety.overrule_max_landmark_residual_mm:
        return (
            f"a view's landmarks are {max(res):.2f} mm from the detected ones "
            f"(at most {safety.overrule_max_landmark_residual_mm:g} mm, overrule_max_landmark_residual_mm)"
        )
    return ""
