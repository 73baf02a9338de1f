"""The robot's commands measured and bounded: each bound refuses with its check and the plan's name."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fluoronav.geometry import se3
from fluoronav.manipulator.robot import UR10
from fluoronav.navigation.checks.safety import SafetyConfig
from fluoronav.navigation.commands import (
    CommandMotion,
    KinematicsVerdict,
    at_prediction_said,
    check_correction,
    check_first_move,
    check_joint_readings,
    correction_allowed_mm,
    judge_kinematics,
    measure_command,
    name_kinematics_disagreement,
    name_one_view_disagreement,
    refuse_wrong_detection,
    wrong_detection_warning,
)
from fluoronav.navigation.result import NavigationRefused
from fluoronav.navigation.targeting import SweptPath

SAFETY = SafetyConfig()


def _motion(*, joints_deg: float = 5.0, tip_mm: float = 1.0, rotation_deg: float = 0.0) -> CommandMotion:
    return CommandMotion(
        joint_motion_deg=np.array([1.0, joints_deg, 0.0, 0.0, 0.0, 0.0]),
        swept=SweptPath(tip_mm, tip_mm, 0.0, np.zeros((2, 3))),
        tip_move_mm=tip_mm,
        rotation_deg=rotation_deg,
    )


def test_a_move_within_every_bound_passes() -> None:
    check_first_move(_motion(joints_deg=29.0, tip_mm=150.0, rotation_deg=60.0), SAFETY, plan_name="entry")
    check_correction(
        _motion(joints_deg=2.0, tip_mm=2.5, rotation_deg=0.0),
        SAFETY,
        plan_name="entry",
        predicted_tip_error_mm=0.0,
    )


@pytest.mark.parametrize(
    ("motion", "check", "words"),
    [
        (_motion(joints_deg=31.0), "joint_motion", "joint 2 by 31.0°, more than the bound 30°"),
        (_motion(tip_mm=201.0), "move_length", "201.0 mm, more than the bound 200 mm"),
        (_motion(rotation_deg=91.0), "move_rotation", "91.0°, more than the bound 90°"),
    ],
)
def test_each_bound_of_the_first_move_refuses_naming_the_plan(
    motion: CommandMotion, check: str, words: str
) -> None:
    with pytest.raises(NavigationRefused) as info:
        check_first_move(motion, SAFETY, plan_name="entry_left")
    assert info.value.stage == "robot" and info.value.check == check
    assert "plan 'entry_left'" in info.value.detail and words in info.value.detail


@pytest.mark.parametrize(
    ("motion", "predicted_mm", "check", "words"),
    [
        (_motion(tip_mm=11.0), 9.0, "correction_length", "11.0 mm, more than the bound 10 mm"),
        (_motion(tip_mm=1.0, rotation_deg=6.0), 0.0, "correction_rotation", "6.00°, more than the bound 5°"),
        (_motion(tip_mm=3.5), 0.2, "correction_within_uncertainty", "vouches for, 3.2 mm"),
        (_motion(joints_deg=31.0, tip_mm=1.0), 0.0, "joint_motion", "the correction would turn joint 2"),
    ],
)
def test_each_bound_of_the_correction_refuses_naming_the_plan(
    motion: CommandMotion, predicted_mm: float, check: str, words: str
) -> None:
    with pytest.raises(NavigationRefused) as info:
        check_correction(motion, SAFETY, plan_name="entry_left", predicted_tip_error_mm=predicted_mm)
    assert info.value.stage == "correct" and info.value.check == check
    assert "plan 'entry_left'" in info.value.detail and words in info.value.detail


def test_the_correction_the_verification_vouches_for_grows_with_the_kinematic_miss() -> None:
    """The planned tip 4 mm from where the kinematics put it: a 6.5 mm correction is within
    4 + max_motion_tip_mm, and refused with max_motion_tip_mm halved."""
    assert correction_allowed_mm(SAFETY, 4.0) == pytest.approx(4.0 + SAFETY.max_motion_tip_mm)
    check_correction(_motion(tip_mm=6.5), SAFETY, plan_name="p", predicted_tip_error_mm=4.0)
    strict = dataclasses.replace(SAFETY, max_motion_tip_mm=SAFETY.max_motion_tip_mm / 2)
    with pytest.raises(NavigationRefused, match="correction_within_uncertainty"):
        check_correction(_motion(tip_mm=6.5), strict, plan_name="p", predicted_tip_error_mm=4.0)


def test_images_that_overrule_the_kinematics_lift_only_the_vouching_bound() -> None:
    """Unambiguous images trusted over the kinematics: a 6.5 mm correction with the planned tip 0.2 mm
    from the prediction passes; the length and rotation bounds still hold."""
    with pytest.raises(NavigationRefused, match="correction_within_uncertainty"):
        check_correction(_motion(tip_mm=6.5), SAFETY, plan_name="p", predicted_tip_error_mm=0.2)
    check_correction(
        _motion(tip_mm=6.5), SAFETY, plan_name="p", predicted_tip_error_mm=0.2, images_overrule=True
    )
    with pytest.raises(NavigationRefused, match="correction_length"):
        check_correction(
            _motion(tip_mm=11.0), SAFETY, plan_name="p", predicted_tip_error_mm=0.2, images_overrule=True
        )


def test_the_bounds_are_frozen_config() -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        SAFETY.max_joint_motion_deg = 90.0  # type: ignore[misc]
    assert (SAFETY.max_joint_motion_deg, SAFETY.max_correction_mm, SAFETY.max_correction_deg) == (
        30.0,
        10.0,
        5.0,
    )


def test_a_command_is_measured_from_the_registered_pose_to_the_target() -> None:
    q0 = np.array([15.0, -100.0, 95.0, -80.0, -85.0, 10.0])
    q1 = q0 + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 20.0])
    A = se3.make(np.eye(3), [0.0, 0.0, 0.0])
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    B = se3.make(turn, [3.0, 4.0, 0.0])
    m = measure_command(
        UR10, q0, q1, ee_from_cm=np.eye(4), tip_cm_mm=np.zeros(3), femur_from_cm_from=A, femur_from_cm_to=B
    )
    np.testing.assert_allclose(m.joint_motion_deg, [0, 0, 0, 0, 0, 20.0], atol=1e-12)
    assert m.tip_move_mm == pytest.approx(5.0) and m.rotation_deg == pytest.approx(90.0)
    # a wrist-only turn about the flange axis leaves a tip on that axis where it is
    assert m.swept.length_mm == pytest.approx(0.0, abs=1e-9)
    d = m.diagnostics()
    assert d["joint_motion_deg"] == pytest.approx(20.0) and len(d["joint_motion_per_joint_deg"]) == 6
    assert {"swept_path_mm", "swept_max_deviation_mm", "tip_move_mm", "rotation_deg"} <= set(d)


def test_joint_readings_beyond_the_bound_are_refused_naming_the_joint() -> None:
    check_joint_readings(np.array([0.1, 0.5, 0.0, 0.0, 0.0, 0.2]), SAFETY)  # at the bound: passes
    with pytest.raises(NavigationRefused) as info:
        check_joint_readings(np.array([0.1, 0.2, 0.0, 0.0, 3.0, 0.2]), SAFETY)
    assert info.value.stage == "verify_joints" and info.value.check == "joint_readings"
    assert "by 3.00° (joint 5; at most 0.5°, max_joint_reading_deg)" in info.value.detail


def _cm_diag(tip_mm: float, residuals_mm: list[float | None], **more: object) -> dict[str, object]:
    names = [f"view{k}" for k in range(len(residuals_mm))]
    return {
        "motion_tip_mm": tip_mm,
        "views_used": names,
        "views": {n: {"landmark_residual_mm": r} for n, r in zip(names, residuals_mm, strict=True)},
        **more,
    }


def test_the_images_and_kinematics_that_agree_are_not_overruled() -> None:
    tip_mm = SAFETY.max_motion_tip_mm
    assert judge_kinematics(_cm_diag(tip_mm, [5.0]), {}, SAFETY) == KinematicsVerdict(False, "")


def test_unambiguous_images_overrule_the_kinematics_with_a_warning() -> None:
    verdict = judge_kinematics(
        _cm_diag(5.0, [0.3, 0.8, 0.5]), {}, dataclasses.replace(SAFETY, overrule_min_views=2)
    )
    assert verdict.images_overrule
    assert verdict.warning.startswith("the CM the verification images show is 5.0 mm from where the robot's")
    assert "Corrected from the images: 3 views agree (landmarks within 0.80 mm)" in verdict.warning


@pytest.mark.parametrize(
    ("tip_mm", "diag", "left_out", "words"),
    [
        (12.0, {}, {}, "more than a correction may move (10 mm, max_correction_mm)"),
        (5.0, {}, {"view2": "edge_ncc"}, "cannot overrule them: views left out (view2)"),
        (5.0, {"left_out": {"view1": "ncc"}}, {}, "views left out (view1)"),
        (5.0, {"tries": 2}, {}, "the images' own starts failed their checks"),
        (5.0, {"few": True}, {}, "2 views passed, 3 needed (overrule_min_views)"),
        (5.0, {"far": True}, {}, "landmarks are 1.50 mm from the detected ones (at most 1 mm"),
        (5.0, {"unknown": True}, {}, "no CM detected in view1 to check the registered landmarks against"),
    ],
)
def test_ambiguous_images_cannot_overrule_the_kinematics(
    tip_mm: float, diag: dict, left_out: dict[str, str], words: str
) -> None:
    residuals: list[float | None] = [0.3, 0.3, 0.3]
    if diag.pop("few", False):
        residuals = [0.3, 0.3]
    if diag.pop("far", False):
        residuals = [0.3, 1.5, 0.3]
    if diag.pop("unknown", False):
        residuals = [0.3, None, 0.3]
    with pytest.raises(NavigationRefused) as info:
        judge_kinematics(_cm_diag(tip_mm, residuals, **diag), left_out, SAFETY)
    assert info.value.stage == "correct" and info.value.check == "kinematics_disagree"
    assert f"{tip_mm:.1f} mm from where the robot's kinematics put it" in info.value.detail
    assert words in info.value.detail


@pytest.mark.parametrize(
    ("gap_mm", "cost_px", "named"),
    [(10.2, 0.9, True), (2.5, 0.9, False), (10.2, 7.0, False), (float("nan"), 0.9, False)],
)
def test_a_failed_verification_cm_far_from_the_kinematics_names_them(
    gap_mm: float, cost_px: float, named: bool
) -> None:
    """The views agree on a CM 10.2 mm from the prediction and its registration failed: the reason
    names the hand-eye matrix and the joint readings, and keeps the registration's failure. Within
    ``max_motion_tip_mm`` (2.5 mm), with views that disagree (7 px) or without a gap: unchanged."""
    exc = NavigationRefused(
        "verify_cm", "landmark_residual", "registered landmarks 11.86 mm from the detected ones", view="AP"
    )
    diag = {"prediction_gap_mm": gap_mm, "init_cost_px": cost_px}
    out = name_kinematics_disagreement(exc, diag, SAFETY)
    if not named:
        assert out is exc
        return
    assert (out.stage, out.check, out.view) == ("verify_cm", "kinematics_disagree", "AP")
    assert out.detail.startswith(
        "the CM's landmarks in the verification images are 10.2 mm from where the robot's kinematics"
    )
    assert "check the hand-eye matrix and the joint readings" in out.detail
    assert out.detail.endswith("(landmark_residual: registered landmarks 11.86 mm from the detected ones)")


def test_one_view_that_disagrees_with_the_kinematics_says_it_cannot_tell_which_is_wrong() -> None:
    with pytest.raises(NavigationRefused) as err:
        judge_kinematics(_cm_diag(5.0, [0.3]), {}, SAFETY)
    assert err.value.check == "detection_or_kinematics"
    assert "one image cannot tell whether its detection or the kinematics is wrong" in str(err.value)
    with pytest.raises(NavigationRefused) as err:
        judge_kinematics(_cm_diag(5.0, [0.3, 0.4]), {}, SAFETY)
    assert err.value.check == "kinematics_disagree" and "one image cannot tell" not in str(err.value)


def test_one_view_far_from_the_kinematics_refused_by_its_registration_says_it_cannot_tell() -> None:
    exc = NavigationRefused("verify_cm", "edge_ncc", "NCC 0.31 (at least 0.7)", view="AP")
    out = name_one_view_disagreement(exc, {"prediction_gap_mm": 8.4}, SAFETY)
    assert (out.stage, out.check, out.view) == ("verify_cm", "detection_or_kinematics", "AP")
    assert out.detail.startswith("the CM's landmarks in the one verification image are 8.4 mm")
    assert "take a second verification view" in out.detail and out.detail.endswith(
        "(edge_ncc: NCC 0.31 (at least 0.7))"
    )
    assert name_one_view_disagreement(exc, {"prediction_gap_mm": 2.0}, SAFETY) is exc
    assert name_one_view_disagreement(exc, {}, SAFETY) is exc


def test_a_wrong_detection_is_named_with_its_views_and_how_far_off() -> None:
    off = {"AP (verify)": 14.23, "B (verify)": 12.0}
    exc = refuse_wrong_detection(off, 10.2, SAFETY, why="the CM there fails the edge check in C (verify)")
    assert (exc.stage, exc.check, exc.view) == ("verify_cm", "detection_disagrees", "AP (verify), B (verify)")
    assert exc.detail.startswith("the landmarks detected in AP (verify) (14.2 mm), B (verify) (12.0 mm) lie")
    assert "10.2 mm from the prediction" in exc.detail and exc.detail.endswith("edge check in C (verify)")
    warning = wrong_detection_warning(off, 10.2, SAFETY)
    assert warning.startswith("detection_disagrees: the landmarks detected in AP (verify) (14.2 mm)")
    assert "Corrected from the CM registered at the prediction" in warning


def test_what_the_images_showed_at_the_prediction_goes_into_the_kinematics_refusal() -> None:
    at = {"views": {"AP": {"edge_ncc": 0.91}, "B": {"edge_ncc": 0.42}}, "motion_tip_mm": 0.8}
    said = at_prediction_said(at, 0.7)
    assert said == (
        "registered from the kinematic prediction on the images alone, the CM's outline fits 1 of 2 views "
        "(edge NCC 0.42 at worst, at least 0.7) and ends 0.8 mm from the prediction"
    )
    exc = NavigationRefused("verify_cm", "landmark_residual", "registered landmarks 11.86 mm off", view="AP")
    out = name_kinematics_disagreement(
        exc, {"prediction_gap_mm": 10.2, "init_cost_px": 0.9}, SAFETY, evidence=said
    )
    assert f"joint readings; {said}; the CM could not be registered there" in out.detail
