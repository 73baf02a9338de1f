"""The robot's commands measured and bounded: each bound refuses with its check and the plan's name."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fluoronav.geometry import se3
from fluoronav.manipulator.robot import UR10
from fluoronav.navigation.commands import (
    CommandMotion,
    check_correction,
    check_first_move,
    correction_allowed_mm,
    measure_command,
)
from fluoronav.navigation.result import NavigationRefused
from fluoronav.navigation.safety import SafetyConfig
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
