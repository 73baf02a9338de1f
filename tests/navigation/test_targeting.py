"""Eq. 7 and eq. 8 in a_from_b naming: the robot target reproduces the plan under perfect registration;
the kinematic prediction of the CM after a move."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fluoronav.geometry import se3
from fluoronav.manipulator.robot import UR10, RobotErrorModel
from fluoronav.navigation.planning import plan_from_dict, planned_femur_from_cm
from fluoronav.navigation.targeting import (
    UnreachableTarget,
    femur_from_cm_registered,
    joint_motion_deg,
    least_motion_target,
    predicted_femur_from_cm,
    rbase_from_ee_target,
    robot_target,
    swept_tip_path,
    tip_correction_target,
)

EE_FROM_CM = se3.make(Rotation.from_rotvec([0.0, 0.15, -0.1]).as_matrix(), [4.0, -2.0, 210.0])
RBASE_FROM_CARM = se3.make(Rotation.from_rotvec([1.3, -0.2, 0.4]).as_matrix(), [-700.0, 150.0, 450.0])
Q_TARGET_TRUE = np.array([15.0, -100.0, 95.0, -80.0, -85.0, 10.0])
PLAN = plan_from_dict(
    {"target_name": "entry_left", "entry_point_mm": [-60.0, 20.0, 35.0], "direction": [0.3, -0.2, 0.9]}
)


def _pose_err(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    E = se3.inv(B) @ A
    return float(np.linalg.norm(E[:3, 3])), float(se3.rotation_angle_deg(E[:3, :3]))


def _scene(q_regi_offset_deg: np.ndarray):
    """Femur placed so that the plan is reached at Q_TARGET_TRUE; registration at a nearby pose."""
    femur_from_cm_tar = planned_femur_from_cm(PLAN)
    rbase_from_femur = UR10.rbase_from_ee(Q_TARGET_TRUE) @ EE_FROM_CM @ se3.inv(femur_from_cm_tar)
    q_regi = Q_TARGET_TRUE + q_regi_offset_deg
    carm_from_cm = se3.inv(RBASE_FROM_CARM) @ UR10.rbase_from_ee(q_regi) @ EE_FROM_CM
    carm_from_femur = se3.inv(RBASE_FROM_CARM) @ rbase_from_femur
    return femur_from_cm_tar, rbase_from_femur, q_regi, carm_from_cm, carm_from_femur


def test_eq7_maps_cm_points_into_the_femur_frame():
    rng = np.random.default_rng(0)
    carm_from_femur = se3.make(Rotation.random(random_state=1).as_matrix(), rng.normal(0, 100, 3))
    carm_from_cm = se3.make(Rotation.random(random_state=2).as_matrix(), rng.normal(0, 100, 3))
    p_cm = np.append(rng.normal(0, 20, 3), 1.0)
    p_femur_via_carm = np.linalg.solve(carm_from_femur, carm_from_cm @ p_cm)
    np.testing.assert_allclose(
        femur_from_cm_registered(carm_from_femur, carm_from_cm) @ p_cm, p_femur_via_carm
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_perfect_registration_reproduces_the_plan(seed):
    offset = np.random.default_rng(seed).uniform(-12.0, 12.0, 6)
    femur_from_cm_tar, rbase_from_femur, q_regi, carm_from_cm, carm_from_femur = _scene(offset)
    target, q = robot_target(
        UR10,
        q_regi,
        ee_from_cm=EE_FROM_CM,
        carm_from_femur=carm_from_femur,
        carm_from_cm=carm_from_cm,
        femur_from_cm_target=femur_from_cm_tar,
    )
    # Move the (perfect) robot there and look at the CM relative to the femur.
    femur_from_cm_after = se3.inv(rbase_from_femur) @ UR10.rbase_from_ee(q) @ EE_FROM_CM
    ep, er = _pose_err(femur_from_cm_after, femur_from_cm_tar)
    assert ep < 1e-9 and er < 1e-9
    ep, er = _pose_err(UR10.rbase_from_ee(q), target)
    assert ep < 1e-9 and er < 1e-9
    # The IK selector picks the branch nearest the registration pose: the configuration we built from.
    np.testing.assert_allclose(q, Q_TARGET_TRUE, atol=1e-6)


def test_eq8_equals_inverse_of_the_paper_form():
    # Read the paper's T_A^B as a_from_b: T_ee^Rbase = ee_from_rbase, T_CM^ee = cm_from_ee,
    # T_Femur^CM = femur_from_cm. Then the printed eq. 8 is the inverse of ours.
    femur_from_cm_tar, _, q_regi, carm_from_cm, carm_from_femur = _scene(np.full(6, 5.0))
    femur_from_cm_regi = femur_from_cm_registered(carm_from_femur, carm_from_cm)
    ours = rbase_from_ee_target(UR10.rbase_from_ee(q_regi), EE_FROM_CM, femur_from_cm_regi, femur_from_cm_tar)
    T_ee_rbase_regi = se3.inv(UR10.rbase_from_ee(q_regi))
    T_cm_ee = se3.inv(EE_FROM_CM)
    paper = (
        np.linalg.inv(T_cm_ee)
        @ np.linalg.inv(femur_from_cm_tar)
        @ femur_from_cm_regi
        @ T_cm_ee
        @ T_ee_rbase_regi
    )
    np.testing.assert_allclose(se3.inv(paper), ours, atol=1e-9)
    # Eq. 7 as printed in that reading: T_Femur^CM = T_Femur^Carm · inv(T_CM^Carm).
    paper7 = se3.inv(carm_from_femur) @ np.linalg.inv(se3.inv(carm_from_cm))
    np.testing.assert_allclose(paper7, femur_from_cm_regi, atol=1e-9)


def test_cm_registration_error_propagates_as_predicted():
    # carm_from_cm estimated with an error E in the CM frame: the CM ends at F_r · E⁻¹ · F_r⁻¹ · F_t.
    femur_from_cm_tar, rbase_from_femur, q_regi, carm_from_cm, carm_from_femur = _scene(np.full(6, -6.0))
    E = se3.make(Rotation.from_rotvec([0.0, 0.01, 0.005]).as_matrix(), [0.5, -0.3, 1.0])
    _, q = robot_target(
        UR10,
        q_regi,
        ee_from_cm=EE_FROM_CM,
        carm_from_femur=carm_from_femur,
        carm_from_cm=carm_from_cm @ E,
        femur_from_cm_target=femur_from_cm_tar,
    )
    F_r = femur_from_cm_registered(carm_from_femur, carm_from_cm)
    predicted = F_r @ se3.inv(E) @ se3.inv(F_r) @ femur_from_cm_tar
    after = se3.inv(rbase_from_femur) @ UR10.rbase_from_ee(q) @ EE_FROM_CM
    ep, er = _pose_err(after, predicted)
    assert ep < 1e-8 and er < 1e-8
    assert _pose_err(after, femur_from_cm_tar)[0] > 0.5


def test_robot_calibration_errors_give_submillimetre_repositioning():
    # The controller uses the nominal UR10; the physical arm has the default errors.
    true = RobotErrorModel(seed=1).true_robot(UR10)
    femur_from_cm_tar = planned_femur_from_cm(PLAN)
    rbase_from_femur = true.rbase_from_ee(Q_TARGET_TRUE) @ EE_FROM_CM @ se3.inv(femur_from_cm_tar)
    q_regi = Q_TARGET_TRUE + np.array([8.0, -6.0, 5.0, 7.0, -9.0, 10.0])
    carm_from_cm = se3.inv(RBASE_FROM_CARM) @ true.rbase_from_ee(q_regi) @ EE_FROM_CM  # true registration
    carm_from_femur = se3.inv(RBASE_FROM_CARM) @ rbase_from_femur
    _, q = robot_target(
        UR10,
        q_regi,
        ee_from_cm=EE_FROM_CM,
        carm_from_femur=carm_from_femur,
        carm_from_cm=carm_from_cm,
        femur_from_cm_target=femur_from_cm_tar,
    )
    after = se3.inv(rbase_from_femur) @ true.rbase_from_ee(q) @ EE_FROM_CM
    ep, er = _pose_err(after, femur_from_cm_tar)
    assert 1e-4 < ep < 1.0 and er < 0.1


def test_unreachable_target_raises():
    femur_from_cm_tar, _, q_regi, carm_from_cm, carm_from_femur = _scene(np.zeros(6))
    far = femur_from_cm_tar.copy()
    far[:3, 3] += [4000.0, 0.0, 0.0]
    with pytest.raises(UnreachableTarget, match="UR10"):
        robot_target(
            UR10,
            q_regi,
            ee_from_cm=EE_FROM_CM,
            carm_from_femur=carm_from_femur,
            carm_from_cm=carm_from_cm,
            femur_from_cm_target=far,
        )


def test_tip_correction_slides_the_registered_cm_onto_the_planned_tip_without_rotating() -> None:
    rng = np.random.default_rng(4)
    R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    femur_from_cm = se3.make(R, rng.uniform(-50, 50, 3))
    tip_cm = np.array([2.0, -1.0, 38.0])
    target_tip = rng.uniform(-50, 50, 3)
    T = tip_correction_target(femur_from_cm, tip_cm, target_tip)
    np.testing.assert_allclose(T[:3, :3], R, atol=1e-12)
    np.testing.assert_allclose(T[:3, :3] @ tip_cm + T[:3, 3], target_tip, atol=1e-9)
    # already on the target: no move
    T0 = tip_correction_target(T, tip_cm, target_tip)
    np.testing.assert_allclose(T0, T, atol=1e-9)


def test_the_predicted_cm_after_a_move_is_where_the_robot_took_it() -> None:
    """With a true hand-eye matrix and a femur that stays with the robot base, the CM registered before
    the move, moved by the robot's motion, is the CM the robot's kinematics put there."""
    femur_from_cm_tar, rbase_from_femur, q_regi, carm_from_cm, carm_from_femur = _scene(
        np.array([3.0, -2.0, 4.0, 1.0, -3.0, 2.0])
    )
    femur_from_cm = femur_from_cm_registered(carm_from_femur, carm_from_cm)
    pred = predicted_femur_from_cm(
        UR10, q_regi, Q_TARGET_TRUE, ee_from_cm=EE_FROM_CM, femur_from_cm=femur_from_cm
    )
    after = se3.inv(rbase_from_femur) @ UR10.rbase_from_ee(Q_TARGET_TRUE) @ EE_FROM_CM
    mm, deg = _pose_err(pred, after)
    assert mm < 1e-9 and deg < 1e-9
    mm, deg = _pose_err(pred, femur_from_cm_tar)  # the scene puts the target at Q_TARGET_TRUE
    assert mm < 1e-9 and deg < 1e-9
    # no move: the registered pose
    same = predicted_femur_from_cm(UR10, q_regi, q_regi, ee_from_cm=EE_FROM_CM, femur_from_cm=femur_from_cm)
    np.testing.assert_allclose(same, femur_from_cm, atol=1e-9)


def _rolled_scene(true_roll_deg: float, q_offset_deg: np.ndarray):
    """Femur placed so that the free-roll plan turned by ``true_roll_deg`` is reached at
    Q_TARGET_TRUE; the CM registered at Q_TARGET_TRUE + ``q_offset_deg``."""
    rbase_from_femur = (
        UR10.rbase_from_ee(Q_TARGET_TRUE)
        @ EE_FROM_CM
        @ se3.inv(planned_femur_from_cm(PLAN, roll_deg=true_roll_deg))
    )
    q_regi = Q_TARGET_TRUE + q_offset_deg
    carm_from_cm = se3.inv(RBASE_FROM_CARM) @ UR10.rbase_from_ee(q_regi) @ EE_FROM_CM
    carm_from_femur = se3.inv(RBASE_FROM_CARM) @ rbase_from_femur
    return q_regi, {
        "ee_from_cm": EE_FROM_CM,
        "carm_from_femur": carm_from_femur,
        "carm_from_cm": carm_from_cm,
    }


def test_the_least_motion_roll_beats_the_fixed_roll_and_stays_within_30_degrees() -> None:
    """A UR-10 working pose whose CM is rolled 120° from the plan's default roll: the fixed roll turns
    the joints far, the free roll barely more than the registration pose's own offset."""
    assert PLAN.roll_free
    offset = np.array([4.0, -6.0, 5.0, 3.0, -4.0, 6.0])
    q_regi, kw = _rolled_scene(120.0, offset)
    _, q_fixed = robot_target(UR10, q_regi, femur_from_cm_target=planned_femur_from_cm(PLAN), **kw)
    fixed = float(joint_motion_deg(q_regi, q_fixed).max())
    best = least_motion_target(UR10, q_regi, lambda r: planned_femur_from_cm(PLAN, roll_deg=r), **kw)
    assert fixed > 60.0
    assert best.joint_motion_deg <= 30.0 and best.joint_motion_deg < fixed
    assert best.joint_motion_deg <= np.abs(offset).max() + 1e-6
    assert abs(best.roll_deg - 120.0) < 20.0
    assert best.n_reachable == 72
    # the command is the plan's pose at that roll, reached within IK tolerance
    np.testing.assert_allclose(best.femur_from_cm_target, planned_femur_from_cm(PLAN, roll_deg=best.roll_deg))
    np.testing.assert_allclose(
        UR10.rbase_from_ee(best.joints_target_deg), best.rbase_from_ee_target, atol=1e-6
    )
    assert best.joint_motion_deg == pytest.approx(
        float(joint_motion_deg(q_regi, best.joints_target_deg).max())
    )
    # no roll of a 1° scan does better (the refinement found the minimum), and the search is repeatable
    scan = []
    for r in np.arange(-180.0, 180.0, 1.0):
        _, q = robot_target(UR10, q_regi, femur_from_cm_target=planned_femur_from_cm(PLAN, roll_deg=r), **kw)
        scan.append(float(joint_motion_deg(q_regi, q).max()))
    assert best.joint_motion_deg <= min(scan) + 1e-6
    again = least_motion_target(UR10, q_regi, lambda r: planned_femur_from_cm(PLAN, roll_deg=r), **kw)
    assert again.roll_deg == best.roll_deg and np.array_equal(again.joints_target_deg, best.joints_target_deg)


def test_the_least_motion_search_skips_unreachable_rolls_and_refuses_when_none_is() -> None:
    q_regi, kw = _rolled_scene(0.0, np.zeros(6))
    calls: list[float] = []

    def only_near_zero(r: float) -> np.ndarray:
        calls.append(r)
        far = se3.make(np.eye(3), [5000.0, 0.0, 0.0])  # out of the arm's reach
        return planned_femur_from_cm(PLAN, roll_deg=r) if abs(r) <= 20.0 else far

    best = least_motion_target(UR10, q_regi, only_near_zero, **kw)
    assert best.n_reachable == 9 and abs(best.roll_deg) <= 20.0
    assert best.joint_motion_deg == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(UnreachableTarget, match="no roll"):
        least_motion_target(UR10, q_regi, lambda r: se3.make(np.eye(3), [5000.0, 0.0, 0.0]), **kw)


def test_joint_motion_is_wrapped() -> None:
    np.testing.assert_allclose(
        joint_motion_deg(np.array([170.0, 0.0, -90.0]), np.array([-170.0, 30.0, -90.0])), [20.0, 30.0, 0.0]
    )


def test_the_swept_path_of_a_joint_move_is_measured_against_the_straight_segment() -> None:
    tip = np.array([0.0, 0.0, 60.0])
    q0 = Q_TARGET_TRUE
    q1 = Q_TARGET_TRUE + np.array([30.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    path = swept_tip_path(UR10, q0, q1, ee_from_cm=EE_FROM_CM, tip_cm_mm=tip, n_samples=201)
    p0 = se3.apply(UR10.rbase_from_ee(q0) @ EE_FROM_CM, tip)
    p1 = se3.apply(UR10.rbase_from_ee(q1) @ EE_FROM_CM, tip)
    np.testing.assert_allclose(path.tip_rbase_mm[[0, -1]], [p0, p1], atol=1e-9)
    assert path.straight_mm == pytest.approx(float(np.linalg.norm(p1 - p0)))
    # a base turn sweeps an arc about the base axis: its length and sagitta
    r = float(np.linalg.norm(p0[:2]))
    assert path.length_mm == pytest.approx(r * np.radians(30.0), rel=1e-3)
    assert path.max_deviation_mm == pytest.approx(r * (1 - np.cos(np.radians(15.0))), rel=1e-3)
    still = swept_tip_path(UR10, q0, q0, ee_from_cm=EE_FROM_CM, tip_cm_mm=tip)
    assert still.length_mm == 0.0 and still.max_deviation_mm == 0.0
