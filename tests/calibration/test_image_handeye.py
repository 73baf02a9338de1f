"""Image-based hand-eye calibration (eqs. 5, 6)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from fluoronav.calibration.image_handeye import (
    ImageHandEyeConfig,
    ImageHandEyeProblem,
    calibrate_hand_eye_from_images,
    default_handeye_levels,
    initial_world_from_rbase_pnp,
)
from fluoronav.calibration.results import HandEyeFailure
from fluoronav.geometry import se3
from fluoronav.geometry.carm import carm_camera
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.manipulator.robot import UR10
from fluoronav.registration.cm import CMView
from fluoronav.registration.priors import GaussianParameterPrior

HOME = np.array([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])


def _synthetic(m: int, rng: np.random.Generator, *, rotate: bool = True):
    """Exact landmark geometry: robot FK, hand-eye, a camera looking at the CM working pose."""
    X = se3.make(Rotation.from_rotvec([0.05, -0.1, 0.08]).as_matrix(), [3.0, -2.0, 200.0])
    q = HOME + (rng.uniform(-15, 15, (m, 6)) if rotate else np.zeros((m, 6)))
    if not rotate:
        q[:, 0] += np.linspace(0.0, 0.0, m)
    A = UR10.rbase_from_ee(q)
    cm0 = A[0] @ X
    cam = carm_camera(
        lao_rao_deg=0.0, cran_caud_deg=90.0, source_to_isocenter_mm=450.0, isocenter_world=cm0[:3, 3]
    )
    kin = CMKinematics()
    cp = np.array([2.0, -1.0, 0.5, 1.0, -2.0])
    ab = kin.landmarks_cm(torch.as_tensor(cp)).numpy()
    views = []
    for k, T in enumerate(A @ X):
        lm = cam.project(ab @ T[:3, :3].T + T[:3, 3])
        views.append(CMView(np.zeros((cam.rows, cam.cols), np.float32), cam, landmarks_px=lm, name=f"p{k}"))
    return views, A, X, cp


def test_too_few_poses_is_an_explicit_failure() -> None:
    views, A, X, cp = _synthetic(2, np.random.default_rng(0))
    res = calibrate_hand_eye_from_images(views, A, initial_ee_from_cm=X, initial_control_points_deg=cp)
    assert isinstance(res, HandEyeFailure) and not res.ok
    assert "too few poses" in res.reason and res.n_poses == 2


def test_degenerate_motion_is_an_explicit_failure() -> None:
    views, A, X, cp = _synthetic(5, np.random.default_rng(1), rotate=False)
    A = A.copy()
    A[:, :3, 3] += np.arange(5)[:, None] * np.array([10.0, 5.0, 0.0])  # translations only
    res = calibrate_hand_eye_from_images(views, A, initial_ee_from_cm=X, initial_control_points_deg=cp)
    assert isinstance(res, HandEyeFailure)
    assert "degenerate" in res.reason


def test_pnp_initialisation_recovers_the_robot_base_from_exact_landmarks() -> None:
    views, A, X, cp = _synthetic(6, np.random.default_rng(2))
    W = initial_world_from_rbase_pnp(views, A, X, cp)
    assert W is not None
    # the camera's world frame is the robot base frame in this synthetic setup
    rot, trans = se3.rotation_angle_deg(W[:3, :3]), np.linalg.norm(W[:3, 3])
    assert rot < 1e-3 and trans < 1e-2


def test_levels_have_seventeen_parameters_and_the_first_stage_holds_the_hand_eye() -> None:
    levels = default_handeye_levels()
    assert all(len(lv.sigma) == 17 for lv in levels)
    assert max(levels[0].sigma[6:12]) < 1e-3 < min(levels[1].sigma[6:12])


def test_shape_prior_is_free_within_the_fbg_tolerance_with_gaussian_walls() -> None:
    """Default shape prior: ½ Σ (max(|cp − cp0| − 1°, 0) / 0.25°)² (a Gaussian σ 1° held the shape
    at the FBG reading and the hand-eye tilt absorbed its error)."""
    views, A, X, cp = _synthetic(5, np.random.default_rng(4))
    W = initial_world_from_rbase_pnp(views, A, X, cp)
    assert W is not None
    problem = ImageHandEyeProblem(
        views, A, initial_ee_from_cm=X, initial_control_points_deg=cp, initial_world_from_rbase=W
    )
    (prior,) = [p for p in problem.registration.priors if isinstance(p, GaussianParameterPrior)]
    x0 = problem.param.initial()
    x = np.stack([x0, x0, x0])
    x[1, 12:] += 0.9  # inside the tolerance
    x[2, 12:] -= 1.5  # 0.5° beyond it: 5 × ½ (0.5 / 0.25)² = 10
    x[:, :12] += 3.0  # pose and hand-eye parameters carry no prior
    got = prior(torch.as_tensor(x)).numpy()
    np.testing.assert_allclose(got, [0.0, 0.0, 10.0], atol=1e-9)


@pytest.mark.slow
def test_recovers_a_known_hand_eye_from_physics_images() -> None:
    """Perfect robot (nominal = true, no encoder noise), exact landmarks, physics images of the
    phantom (384², 6 poses), initial hand-eye 5°/5 mm off. Bars from noisy runs of such
    scenes (M = 4-8 with robot errors and ±3 px landmarks: tip 0.16-1.04 mm,
    translation 0.05-0.38 mm, rotation 2.0-2.1°, residual 0.5-0.7 px at 384²): tip < 1 mm,
    translation < 1 mm, rotation and axis tilt < 3° (better than the initial 5°), residual < 2 px."""
    from fluoronav.calibration.handeye import transform_error
    from fluoronav.manipulator.robot import RobotErrorModel
    from fluoronav.simulation.articulated import anatomy_and_simulator as _anatomy
    from fluoronav.simulation.robot_scene import (
        perturb_transform,
        sample_handeye_scenario,
        simulate_scenario_images,
    )

    volume, sim = _anatomy("phantom", 0, 384, "cpu")
    rng = np.random.default_rng(3)
    sc = sample_handeye_scenario(volume, rng, n_poses=6)
    perfect = RobotErrorModel(
        joint_offset_sigma_deg=0.0, link_length_sigma_mm=0.0, twist_sigma_deg=0.0, encoder_noise_sigma_deg=0.0
    )
    assert perfect.true_robot(UR10).rbase_from_ee(sc.q_deg[:1]) == pytest.approx(
        UR10.rbase_from_ee(sc.q_deg[:1])
    )
    W = sc.world_from_rbase @ UR10.rbase_from_ee(sc.q_deg) @ sc.ee_from_cm
    images = simulate_scenario_images(sc, sim, seed=5, image_size=384, world_from_cm=W)
    kin = CMKinematics()
    ab = kin.landmarks_cm(torch.as_tensor(sc.control_points_deg)).numpy()
    views = [
        CMView(s.image, s.camera, landmarks_px=s.camera.project(ab @ T[:3, :3].T + T[:3, 3]), name=f"p{m}")
        for m, (s, T) in enumerate(zip(images, W, strict=True))
    ]
    X0 = perturb_transform(sc.ee_from_cm, rng, 5.0, 5.0)
    res = calibrate_hand_eye_from_images(
        views,
        UR10.rbase_from_ee(sc.q_deg),
        initial_ee_from_cm=X0,
        initial_control_points_deg=sc.control_points_deg,
        config=ImageHandEyeConfig(),
        seed=0,
    )
    assert res.ok
    from fluoronav.studies.handeye_trials import axis_and_roll_deg, tip_rbase

    rot, trans = transform_error(res.ee_from_cm, sc.ee_from_cm)
    A = UR10.rbase_from_ee(sc.q_deg)
    tip_est = tip_rbase(A, res.ee_from_cm, res.control_points_deg, kin)
    tip_true = tip_rbase(A, sc.ee_from_cm, sc.control_points_deg, kin)
    assert np.linalg.norm(tip_est - tip_true, axis=1).mean() < 1.0
    assert trans < 1.0 and rot < 3.0
    assert axis_and_roll_deg(res.ee_from_cm, sc.ee_from_cm)["handeye_axis_deg"] < 3.0
    assert np.all(res.residuals_px < 2.0)
