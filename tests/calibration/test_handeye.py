"""Tracker-based hand-eye baselines (OpenCV adapters), degeneracy checks and the eq. 9/10 tip chains."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fluoronav.calibration.handeye import (
    AX_XB_METHODS,
    AX_YB_METHODS,
    calibrate_hand_eye,
    calibrate_robot_world_hand_eye,
    check_motion,
    handeye_residuals,
    simulate_tracker_calibration,
    tip_errors,
    tip_rbase_image_chain,
    tip_rbase_tracker_chain,
    transform_error,
)
from fluoronav.calibration.results import HandEyeFailure, HandEyeResult
from fluoronav.calibration.tracker import DEFAULT_BODY, OpticalTracker
from fluoronav.geometry import se3
from fluoronav.manipulator.robot import UR10, random_configurations_deg

# OpenCV's solvers reach ~1e-11 on noise-free data (LI's Y ~1e-9 mm); the stated tolerance is 1e-6.
TOL_DEG = 1e-6
TOL_MM = 1e-6
HOME = np.array([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])
X_TRUE = se3.make(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), [20.0, -35.0, 110.0])
Y_TRUE = se3.make(Rotation.from_rotvec([0.1, 2.0, -0.4]).as_matrix(), [-300.0, 1500.0, 400.0])
ALL = [(m, calibrate_hand_eye) for m in AX_XB_METHODS] + [
    (m, calibrate_robot_world_hand_eye) for m in AX_YB_METHODS
]


def _data(sigma: float, *, n: int = 30, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    q = random_configurations_deg(n, rng=np.random.default_rng(100), center_deg=HOME, spread_deg=20.0)
    return simulate_tracker_calibration(
        UR10,
        UR10,
        q,
        ee_from_marker=X_TRUE,
        rbase_from_tracker=Y_TRUE,
        tracker=OpticalTracker(marker_sigma_mm=sigma),
        body=DEFAULT_BODY,
        rng=np.random.default_rng(seed),
    )


@pytest.mark.parametrize(("method", "solve"), ALL)
def test_noise_free_recovers_x_and_y(method, solve):
    A, B = _data(0.0)
    res = solve(A, B, method=method)
    assert isinstance(res, HandEyeResult)
    assert res.method == method and res.n_poses == 30
    rot, trans = transform_error(res.ee_from_marker, X_TRUE)
    assert rot < TOL_DEG and trans < TOL_MM
    rot, trans = transform_error(res.rbase_from_tracker, Y_TRUE)
    assert rot < TOL_DEG and trans < TOL_MM
    assert res.residual_translation_mm.max() < TOL_MM and res.residual_rotation_deg.max() < TOL_DEG


@pytest.mark.parametrize(("method", "solve"), ALL)
def test_error_grows_smoothly_with_noise(method, solve):
    # Same seed at every σ: the noise realisation is scaled, so errors should scale ~linearly.
    sigmas = [0.025, 0.05, 0.1, 0.2]
    rot, trans = [], []
    for s in sigmas:
        res = solve(*_data(s, seed=7), method=method)
        assert isinstance(res, HandEyeResult)
        r, t = transform_error(res.ee_from_marker, X_TRUE)
        rot.append(r)
        trans.append(t)
    rot_a, trans_a = np.array(rot), np.array(trans)
    assert np.all(np.diff(rot_a) > 0) and np.all(np.diff(trans_a) > 0)
    np.testing.assert_allclose(rot_a[1:] / rot_a[:-1], 2.0, rtol=0.15)
    np.testing.assert_allclose(trans_a[1:] / trans_a[:-1], 2.0, rtol=0.15)
    # Bounds at the default tracker noise σ = 0.1 mm (30 poses, ±20° joint spread).
    bound_mm = 2.0 if method in AX_XB_METHODS else 8.0
    assert rot_a[2] < 0.5 and trans_a[2] < bound_mm


def test_residuals_reflect_tracker_noise():
    A, B = _data(0.1, seed=3)
    res = calibrate_hand_eye(A, B, method="TSAI")
    assert isinstance(res, HandEyeResult)
    # The marker-origin loop error is of the order of the marker noise (σ = 0.1 mm per axis).
    assert 0.05 < res.mean_residual_translation_mm < 0.5
    rot, trans = handeye_residuals(A, B, X_TRUE, Y_TRUE)
    assert 0.05 < trans.mean() < 0.5 and rot.mean() < 0.3


@pytest.mark.parametrize(("method", "solve"), ALL)
def test_too_few_poses_fail(method, solve):
    A, B = _data(0.0, n=2)
    res = solve(A, B, method=method)
    assert isinstance(res, HandEyeFailure) and "too few" in res.reason and not res.ok


@pytest.mark.parametrize(("method", "solve"), ALL)
def test_single_axis_rotation_is_degenerate(method, solve):
    # Only the last joint moves: every relative rotation is about the flange z axis.
    q = np.tile(HOME, (10, 1))
    q[:, 5] += np.linspace(-60, 60, 10)
    A = UR10.rbase_from_ee(q)
    B = se3.inv(Y_TRUE) @ A @ X_TRUE
    res = solve(A, B, method=method)
    assert isinstance(res, HandEyeFailure) and "degenerate" in res.reason


def test_pure_translation_is_degenerate():
    A = np.tile(UR10.rbase_from_ee(HOME), (6, 1, 1))
    A[:, :3, 3] += np.random.default_rng(0).normal(0, 50, (6, 3))
    assert check_motion(A) is not None
    assert check_motion(UR10.rbase_from_ee(HOME + np.random.default_rng(1).normal(0, 15, (6, 6)))) is None


def test_wrong_adapter_would_not_close_the_loop():
    # Guards the adapter: feeding tracker_from_marker where OpenCV expects target2cam gives a wrong X.
    import cv2

    A, B = _data(0.0)
    R, t = cv2.calibrateHandEye(
        [a[:3, :3] for a in A], [a[:3, 3:4] for a in A], [b[:3, :3] for b in B], [b[:3, 3:4] for b in B]
    )
    assert transform_error(se3.make(R, t.reshape(3)), X_TRUE)[1] > 1.0


def test_tip_chains_eq9_eq10_agree_on_truth():
    rng = np.random.default_rng(4)
    n = 12
    q = random_configurations_deg(n, rng=rng, center_deg=HOME, spread_deg=15.0)
    rbase_from_ee = UR10.rbase_from_ee(q)
    ee_from_cm = se3.make(Rotation.from_rotvec([0.0, 0.2, 0.1]).as_matrix(), [5.0, -3.0, 180.0])
    ee_from_os = se3.make(Rotation.from_rotvec([0.5, 0.0, 0.0]).as_matrix(), [40.0, 0.0, 120.0])
    # The tip segment moves relative to the CM base with the bending (one pose per configuration).
    cm_from_cmt = se3.make(Rotation.from_rotvec(rng.normal(0, 0.1, (n, 3))).as_matrix(), [0.0, 2.0, 25.0])
    cmt_from_ot = se3.make(Rotation.from_rotvec([0.0, 0.0, 1.0]).as_matrix(), [10.0, 10.0, 0.0])
    tip_cmt = np.array([0.0, 0.0, 6.0])
    tip_ot = (se3.inv(cmt_from_ot) @ np.append(tip_cmt, 1.0))[:3]
    rbase_from_tracker = Y_TRUE
    rbase_from_carm = se3.make(Rotation.from_rotvec([1.2, 0.0, 0.3]).as_matrix(), [-800.0, 0.0, 300.0])
    tracker_from_os = se3.inv(rbase_from_tracker) @ rbase_from_ee @ ee_from_os
    tracker_from_ot = se3.inv(rbase_from_tracker) @ rbase_from_ee @ ee_from_cm @ cm_from_cmt @ cmt_from_ot
    carm_from_cm = se3.inv(rbase_from_carm) @ rbase_from_ee @ ee_from_cm
    tip_carm = (
        np.einsum("nij,j->ni", (carm_from_cm @ cm_from_cmt)[:, :3, :3], tip_cmt)
        + (carm_from_cm @ cm_from_cmt)[:, :3, 3]
    )
    truth = (
        np.einsum("nij,j->ni", (rbase_from_ee @ ee_from_cm @ cm_from_cmt)[:, :3, :3], tip_cmt)
        + (rbase_from_ee @ ee_from_cm @ cm_from_cmt)[:, :3, 3]
    )
    p9 = tip_rbase_tracker_chain(rbase_from_ee, ee_from_os, tracker_from_os, tracker_from_ot, tip_ot)
    p10 = tip_rbase_image_chain(rbase_from_ee, ee_from_cm, carm_from_cm, tip_carm)
    np.testing.assert_allclose(p9, truth, atol=1e-9)
    np.testing.assert_allclose(p10, truth, atol=1e-9)
    assert tip_errors(p9, p10).max_mm < 1e-9
    # A 1 mm translation error of the image-based hand-eye (ee frame) moves every eq. 10 tip by 1 mm.
    bad = ee_from_cm.copy()
    bad[:3, 3] += [0.6, 0.0, 0.8]
    err = tip_errors(p9, tip_rbase_image_chain(rbase_from_ee, bad, carm_from_cm, tip_carm))
    np.testing.assert_allclose(err.per_pose_mm, 1.0, atol=1e-9)
    assert err.std_mm < 1e-9


def test_unknown_method_and_bad_shapes():
    A, B = _data(0.0, n=4)
    with pytest.raises(ValueError, match="unknown"):
        calibrate_hand_eye(A, B, method="SHAH")
    with pytest.raises(ValueError, match="unknown"):
        calibrate_robot_world_hand_eye(A, B, method="TSAI")
    with pytest.raises(ValueError, match="equal N"):
        calibrate_hand_eye(A, B[:3])


def test_accuracy_experiment_runs_and_is_exact_without_noise():
    from fluoronav.calibration.experiments import tracker_baseline_accuracy

    exact = tracker_baseline_accuracy(marker_sigma_mm=0.0, robot_errors=False, n_poses=10, seeds=(0,))
    assert set(exact) == set(AX_XB_METHODS) | set(AX_YB_METHODS)
    assert all(r < TOL_DEG and t < TOL_MM for r, t in exact.values())
    noisy = tracker_baseline_accuracy(marker_sigma_mm=0.0, robot_errors=True, n_poses=20, seeds=(0,))
    assert all(0.01 < t < 2.0 for _, t in noisy.values())
