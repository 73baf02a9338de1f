"""Robot model: FK against hand-computed poses, analytic IK on all branches, DLS, error model."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fluoronav.geometry import se3
from fluoronav.manipulator.robot import (
    UR10,
    DHRow,
    IKFailure,
    IKSolution,
    RobotErrorModel,
    SerialRobot,
    random_configurations_deg,
    wrap_deg,
)

TOL_MM = 1e-6
TOL_DEG = 1e-6


def _pose_err(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    E = se3.inv(B) @ A
    return float(np.linalg.norm(E[:3, 3])), float(se3.rotation_angle_deg(E[:3, :3]))


def test_ur10_dh_matches_published_table():
    # Universal Robots' DH table for UR10 (CB3), in metres: d1 .1273, a2 −.612, a3 −.5723,
    # d4 .163941, d5 .1157, d6 .0922; alpha π/2, 0, 0, π/2, −π/2, 0.
    np.testing.assert_allclose(UR10.d_mm, [127.3, 0, 0, 163.941, 115.7, 92.2])
    np.testing.assert_allclose(UR10.a_mm, [0, -612.0, -572.3, 0, 0, 0])
    np.testing.assert_allclose(UR10.alpha_rad, [np.pi / 2, 0, 0, np.pi / 2, -np.pi / 2, 0])


def test_fk_zero_configuration_hand_computed():
    # All joints 0: R = Rx(90°) (the three +/−90° twists), p = (a2 + a3, −(d4 + d6), d1 − d5).
    T = UR10.rbase_from_ee(np.zeros(6))
    expected = np.array(
        [
            [1.0, 0.0, 0.0, -1184.3],
            [0.0, 0.0, -1.0, -256.141],
            [0.0, 1.0, 0.0, 11.6],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    np.testing.assert_allclose(T, expected, atol=1e-9)


def test_fk_upright_configuration_hand_computed():
    # q = (0, −90, 0, −90, 0, 0): arm straight up; height d1 + |a2| + |a3| + d5 = 1427.3 mm.
    T = UR10.rbase_from_ee(np.array([0.0, -90.0, 0.0, -90.0, 0.0, 0.0]))
    expected = np.array(
        [
            [-1.0, 0.0, 0.0, 0.0],
            [0.0, 0.0, -1.0, -256.141],
            [0.0, -1.0, 0.0, 1427.3],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    np.testing.assert_allclose(T, expected, atol=1e-9)


def test_dh_row_is_rz_tz_tx_rx():
    rng = np.random.default_rng(3)
    q = rng.uniform(-180, 180, 6)
    T = np.eye(4)
    for qi, row in zip(q, UR10.dh, strict=True):
        Rz = se3.make(
            Rotation.from_euler("z", qi + row.theta_offset_deg, degrees=True).as_matrix(), [0, 0, row.d_mm]
        )
        Tx = se3.make(Rotation.from_euler("x", row.alpha_deg, degrees=True).as_matrix(), [row.a_mm, 0, 0])
        T = T @ Rz @ Tx
    np.testing.assert_allclose(UR10.rbase_from_ee(q), T, atol=1e-9)


def test_fk_is_batched():
    rng = np.random.default_rng(0)
    q = rng.uniform(-180, 180, (2, 3, 6))
    T = UR10.rbase_from_ee(q)
    assert T.shape == (2, 3, 4, 4)
    np.testing.assert_allclose(T[1, 2], UR10.rbase_from_ee(q[1, 2]), atol=1e-12)


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(1)
    q = rng.uniform(-180, 180, 6)
    J = UR10.jacobian(q)
    h = 1e-6  # rad
    T0 = UR10.rbase_from_ee(q)
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = np.rad2deg(h)
        T1 = UR10.rbase_from_ee(q + dq)
        v = (T1[:3, 3] - T0[:3, 3]) / h
        w = se3.rotvec(T1[:3, :3] @ T0[:3, :3].T) / h
        np.testing.assert_allclose(J[:3, j], v, atol=1e-3)
        np.testing.assert_allclose(J[3:, j], w, atol=1e-6)


def test_fk_ik_identity_on_all_branches():
    rng = np.random.default_rng(42)
    n_eight = 0
    for _ in range(60):
        q = rng.uniform(-180, 180, 6)
        T = UR10.rbase_from_ee(q)
        sols = UR10.inverse_kinematics_all(T)
        assert sols, "a pose produced by FK must be reachable"
        # Refinement keeps every closed-form branch (fewer than 8 exist where the elbow cannot reach).
        assert len(sols) == len(UR10.closed_form_ik(T))
        n_eight += len(sols) == 8
        for s in sols:
            ep, er = _pose_err(UR10.rbase_from_ee(s.q_deg), T)
            assert ep < TOL_MM and er < TOL_DEG
        # The configuration that made the pose is one of the branches.
        d = min(float(np.abs(wrap_deg(s.q_deg - q)).max()) for s in sols)
        assert d < TOL_DEG
        assert len({s.branch for s in sols}) == len(sols)
    assert n_eight >= 30  # about 3 in 4 random poses have all 8 branches


def test_selector_returns_branch_nearest_reference():
    rng = np.random.default_rng(7)
    for _ in range(20):
        q = rng.uniform(-170, 170, 6)
        sol = UR10.inverse_kinematics(UR10.rbase_from_ee(q), q_reference_deg=q + rng.normal(0, 2.0, 6))
        assert isinstance(sol, IKSolution)
        np.testing.assert_allclose(sol.q_deg, q, atol=TOL_DEG)


def test_selector_keeps_joint_values_near_reference_beyond_180():
    q = np.array([200.0, -100.0, 80.0, -250.0, -90.0, 300.0])
    sol = UR10.inverse_kinematics(UR10.rbase_from_ee(q), q_reference_deg=q + 1.0)
    assert isinstance(sol, IKSolution)
    np.testing.assert_allclose(sol.q_deg, q, atol=TOL_DEG)


def test_unreachable_poses_fail_explicitly():
    far = se3.make(np.eye(3), [3000.0, 0.0, 0.0])
    res = UR10.inverse_kinematics(far)
    assert isinstance(res, IKFailure) and "unreachable" in res.reason
    # Wrist centre on the base axis lies inside the shoulder cylinder of radius d4.
    inside = se3.make(np.eye(3), [0.0, 0.0, 500.0 + UR10.d_mm[5]])
    assert isinstance(UR10.inverse_kinematics(inside), IKFailure)


def test_ik_of_robot_with_calibration_errors_is_exact():
    true = RobotErrorModel(joint_offset_sigma_deg=0.5, link_length_sigma_mm=2.0, twist_sigma_deg=0.3, seed=5)
    robot = true.true_robot(UR10)
    rng = np.random.default_rng(11)
    for _ in range(10):
        q = rng.uniform(-170, 170, 6)
        T = robot.rbase_from_ee(q)
        sol = robot.inverse_kinematics(T, q_reference_deg=q + 1.0)
        assert isinstance(sol, IKSolution)
        ep, er = _pose_err(robot.rbase_from_ee(sol.q_deg), T)
        assert ep < TOL_MM and er < TOL_DEG
        np.testing.assert_allclose(sol.q_deg, q, atol=1e-5)


def test_non_ur_robot_uses_seeded_dls():
    rows = tuple(replace(r, alpha_deg=r.alpha_deg + 5.0) for r in UR10.dh)
    robot = SerialRobot(dh=rows, name="skewed")
    assert not robot.is_ur_type()
    q = np.array([10.0, -80.0, 70.0, -60.0, -80.0, 20.0])
    T = robot.rbase_from_ee(q)
    with pytest.raises(ValueError, match="q_reference_deg"):
        robot.inverse_kinematics(T)
    with pytest.raises(ValueError, match="UR joint structure"):
        robot.closed_form_ik(T)
    sol = robot.inverse_kinematics(T, q_reference_deg=q + 5.0)
    assert isinstance(sol, IKSolution)
    np.testing.assert_allclose(sol.q_deg, q, atol=1e-6)


def test_error_model_is_seeded_and_modest():
    m = RobotErrorModel(seed=3)
    a, b = m.true_robot(UR10), m.true_robot(UR10)
    assert a == b
    assert m.true_robot(UR10) != RobotErrorModel(seed=4).true_robot(UR10)
    zero = RobotErrorModel(0.0, 0.0, 0.0, 0.0, seed=3).true_robot(UR10)
    q = random_configurations_deg(50, rng=np.random.default_rng(0), center_deg=np.zeros(6), spread_deg=150)
    np.testing.assert_allclose(zero.rbase_from_ee(q), UR10.rbase_from_ee(q), atol=1e-12)
    dev = np.linalg.norm(a.rbase_from_ee(q)[:, :3, 3] - UR10.rbase_from_ee(q)[:, :3, 3], axis=-1)
    # Default errors: sub-millimetre but not negligible flange deviations.
    assert 0.02 < dev.mean() < 1.0


def test_encoder_noise_statistics():
    m = RobotErrorModel(encoder_noise_sigma_deg=0.01)
    q = np.zeros((20000, 6))
    qa = m.actual_joints_deg(q, rng=np.random.default_rng(0))
    assert abs(qa.std() - 0.01) < 0.0003
    assert abs(qa.mean()) < 0.0003


def test_wrap_deg():
    np.testing.assert_allclose(
        wrap_deg(np.array([-180.0, 180.0, 190.0, -190.0, 540.0])), [180, 180, -170, 170, 180]
    )


def test_dhrow_frozen():
    row = DHRow(1.0, 2.0, 3.0)
    with pytest.raises(AttributeError):
        row.a_mm = 2.0  # type: ignore[misc]
