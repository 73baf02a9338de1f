"""Plan files: parsing, validation errors naming the file, and the planned CM pose."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from fluoronav.errors import InputError
from fluoronav.geometry import se3
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.navigation.planning import (
    Plan,
    _frame_axes,
    load_plan,
    plan_from_dict,
    planned_femur_from_cm,
    save_plan,
)

GOOD = {
    "target_name": "entry_left",
    "entry_point_mm": [12.0, -30.5, 80.0],
    "direction": [0.0, 3.0, -4.0],
    "insertion_depth_mm": 5.0,
}


def _write(tmp_path, obj, name="plan.json"):
    p = tmp_path / name
    p.write_text(obj if isinstance(obj, str) else json.dumps(obj))
    return p


def test_load_valid_plan_normalises_direction(tmp_path):
    plan = load_plan(_write(tmp_path, GOOD))
    assert plan.target_name == "entry_left"
    np.testing.assert_allclose(plan.direction_world, [0.0, 0.6, -0.8])
    np.testing.assert_allclose(plan.tip_target_world_mm, [12.0, -27.5, 76.0])
    assert plan.bending_direction_world is None and plan.control_points_deg is None


def test_round_trip(tmp_path):
    plan = plan_from_dict({**GOOD, "bending_direction": [1, 0, 0], "control_points_deg": [1, 2, 3, 4, 5]})
    back = load_plan(save_plan(plan, tmp_path / "p.json"))
    np.testing.assert_allclose(back.entry_point_world_mm, plan.entry_point_world_mm)
    np.testing.assert_allclose(back.direction_world, plan.direction_world)
    assert back.control_points_deg is not None
    np.testing.assert_allclose(back.control_points_deg, [1, 2, 3, 4, 5])
    assert back.insertion_depth_mm == 5.0


def test_ras_plan_is_converted_to_lps(tmp_path):
    plan = load_plan(_write(tmp_path, {**GOOD, "coordinate_system": "RAS"}))
    np.testing.assert_allclose(plan.entry_point_world_mm, [-12.0, 30.5, 80.0])
    np.testing.assert_allclose(plan.direction_world, [0.0, -0.6, -0.8])


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("", "empty"),
        ("{not json", "not valid JSON"),
        ([1, 2], "JSON object"),
        ({k: v for k, v in GOOD.items() if k != "direction"}, "missing 'direction'"),
        ({**GOOD, "direction": [0, 0, 0]}, "non-zero"),
        ({**GOOD, "direction": [0, 1]}, "list of 3"),
        ({**GOOD, "entry_point_mm": [0, "a", 1]}, "only numbers"),
        ({**GOOD, "insertion_depth_mm": -1}, "≥ 0"),
        ({**GOOD, "target_name": ""}, "target_name"),
        ({**GOOD, "bending_direction": [0, 6, -8]}, "parallel"),
        ({**GOOD, "coordinate_system": "XYZ"}, "coordinate_system"),
        ({**GOOD, "extra": 1}, "unknown key"),
    ],
)
def test_bad_plans_raise_input_error_naming_the_file(tmp_path, content, message):
    p = _write(tmp_path, content)
    with pytest.raises(InputError, match=message) as info:
        load_plan(p)
    assert info.value.source == str(p)


def test_missing_file(tmp_path):
    with pytest.raises(InputError, match="cannot read") as info:
        load_plan(tmp_path / "nope.json")
    assert "nope.json" in info.value.source


@pytest.mark.parametrize("cps", [None, [3.0, -2.0, 5.0, 1.0, -4.0]])
def test_planned_pose_puts_tip_on_target_with_axis_along_direction(cps):
    plan = plan_from_dict({**GOOD, "control_points_deg": cps, "bending_direction": [1.0, 1.0, 0.0]})
    kin = CMKinematics()
    T = planned_femur_from_cm(plan, kinematics=kin)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    np.testing.assert_allclose(T[:3, 2], plan.direction_world, atol=1e-12)
    # +y is the bending direction's part orthogonal to the axis.
    b = np.array([1.0, 1.0, 0.0])
    b = b - b.dot(plan.direction_world) * plan.direction_world
    np.testing.assert_allclose(T[:3, 1], b / np.linalg.norm(b), atol=1e-12)
    cp = torch.zeros(5, dtype=torch.float64) if cps is None else torch.tensor(cps, dtype=torch.float64)
    tip_cm = kin.tip_cm(cp).numpy()
    np.testing.assert_allclose(T[:3, :3] @ tip_cm + T[:3, 3], plan.tip_target_world_mm, atol=1e-9)


def test_straight_cm_origin_sits_tip_length_before_target():
    plan = plan_from_dict(GOOD)
    T = planned_femur_from_cm(plan)
    tip_z = CMKinematics().config.tip_z_mm
    np.testing.assert_allclose(T[:3, 3], plan.tip_target_world_mm - tip_z * plan.direction_world, atol=1e-9)


def test_femur_from_world_is_applied():
    plan = plan_from_dict(GOOD)
    F = se3.make(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), [10.0, 20.0, 30.0])
    np.testing.assert_allclose(
        planned_femur_from_cm(plan, femur_from_world=F), F @ planned_femur_from_cm(plan)
    )


def test_plan_dataclass_is_frozen():
    plan = plan_from_dict(GOOD)
    assert isinstance(plan, Plan)
    with pytest.raises(AttributeError):
        plan.target_name = "x"  # type: ignore[misc]


def test_neck_entry_plan_puts_the_tip_on_the_entry_along_the_neck() -> None:
    import numpy as np

    from fluoronav.manipulator import CMKinematics
    from fluoronav.navigation.planning import neck_entry_plan, planned_femur_from_cm

    entry, head = np.array([80.0, 10.0, -40.0]), np.array([40.0, 15.0, -5.0])
    plan = neck_entry_plan(entry, head)
    np.testing.assert_allclose(np.linalg.norm(plan.direction_world), 1.0)
    np.testing.assert_allclose(plan.tip_target_world_mm, entry)
    T = planned_femur_from_cm(plan, kinematics=CMKinematics())
    np.testing.assert_allclose(T[:3, 2], (head - entry) / np.linalg.norm(head - entry), atol=1e-12)


def test_a_plan_without_bending_direction_leaves_the_roll_free() -> None:
    assert plan_from_dict(GOOD).roll_free
    assert not plan_from_dict({**GOOD, "bending_direction": [1.0, 0.0, 0.0]}).roll_free


@pytest.mark.parametrize("bend", [None, [1.0, 1.0, 0.0]])
def test_roll_zero_is_the_plans_own_pose_exactly(bend) -> None:
    """A fixed-roll plan keeps today's pose bitwise: the frame from the bending direction, the tip on
    the target."""
    plan = plan_from_dict(
        {**GOOD, "bending_direction": bend, "control_points_deg": [3.0, -2.0, 5.0, 1.0, -4.0]}
    )
    kin = CMKinematics()
    R = _frame_axes(plan.direction_world, plan.bending_direction_world)
    tip_cm = kin.tip_cm(torch.as_tensor(plan.control_points_deg, dtype=torch.float64)).numpy()
    expected = se3.make(R, plan.tip_target_world_mm - R @ tip_cm)
    assert np.array_equal(planned_femur_from_cm(plan, kinematics=kin), expected)
    assert np.array_equal(planned_femur_from_cm(plan, kinematics=kin, roll_deg=0.0), expected)


@pytest.mark.parametrize("roll_deg", [-135.0, 30.0, 90.0, 170.0])
def test_the_roll_family_keeps_tip_and_axis_for_a_bent_cm(roll_deg: float) -> None:
    plan = plan_from_dict({**GOOD, "control_points_deg": [8.0, 6.0, 4.0, 6.0, 8.0]})
    kin = CMKinematics()
    tip_cm = kin.tip_cm(torch.as_tensor(plan.control_points_deg, dtype=torch.float64)).numpy()
    T0 = planned_femur_from_cm(plan, kinematics=kin)
    T = planned_femur_from_cm(plan, kinematics=kin, roll_deg=roll_deg)
    np.testing.assert_allclose(se3.apply(T, tip_cm), plan.tip_target_world_mm, atol=1e-9)
    np.testing.assert_allclose(T[:3, 2], plan.direction_world, atol=1e-12)
    # a right-handed turn by roll_deg about the direction, through the tip target
    turn = Rotation.from_rotvec(np.radians(roll_deg) * plan.direction_world).as_matrix()
    np.testing.assert_allclose(T[:3, :3], turn @ T0[:3, :3], atol=1e-12)
    tip = plan.tip_target_world_mm
    np.testing.assert_allclose(T[:3, 3], tip + turn @ (T0[:3, 3] - tip), atol=1e-9)
    assert se3.rotation_angle_deg(T0[:3, :3].T @ T[:3, :3]) == pytest.approx(abs(roll_deg), abs=1e-6)
