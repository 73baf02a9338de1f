"""Centreline-based initialisation (paper §II-B): geometry, cost, search and failure modes.

The scenes are made from the CM model itself (projected landmarks and centreline): acceptable for the
initialiser's unit tests; the registration studies use physics-simulated images.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from fluoronav.errors import InputError, RegistrationFailure
from fluoronav.geometry import carm_camera
from fluoronav.geometry.rotations import euler_to_matrix
from fluoronav.manipulator import CMKinematics
from fluoronav.registration.centerline import (
    CenterlineInitConfig,
    centerline_cost,
    centerline_initialize,
    depth_range_about,
    evaluate_centerline_init,
    poses_from_depth_theta,
    roll_about_axis_deg,
    synthetic_centerline_scene,
)

CP = np.array([3.0, 5.0, -2.0, 4.0, 6.0])


def _oblique_scene() -> tuple:
    """CIOS Fusion AP camera at 450 mm; a strongly bent CM (~95° in total) in an oblique pose."""
    camera = carm_camera(source_to_isocenter_mm=450.0)
    T = np.eye(4)
    T[:3, :3] = euler_to_matrix("xyz", torch.tensor([60.0, 20.0, 35.0], dtype=torch.float64)).numpy()
    T[:3, 3] = [8.0, -5.0, 450.0]
    kin = CMKinematics()
    cp = torch.as_tensor(CP)
    view = camera.with_pose(T)  # maps CM coordinates to pixels
    landmarks = view.project(kin.landmarks_cm(cp).numpy())
    centerline = view.project(kin.centerline_cm(cp, n_points=200).numpy())
    return camera, T, landmarks, centerline, kin


def _polyline_distance_np(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Reference: distance of each point to a polyline, one segment at a time."""
    out = np.full(len(points), np.inf)
    for a, b in itertools.pairwise(poly):
        d = b - a
        t = np.clip(((points - a) @ d) / max(d @ d, 1e-12), 0.0, 1.0)
        out = np.minimum(out, np.linalg.norm(points - (a + t[:, None] * d), axis=1))
    return out


def _trimmed(d: np.ndarray, frac: float) -> float:
    keep = max(1, len(d) - math.floor(frac * len(d)))
    return float(np.sort(d)[:keep].mean())


def test_noise_free_recovers_pose() -> None:
    camera, T_true, landmarks, centerline, kin = _oblique_scene()
    res = centerline_initialize(camera, landmarks, centerline, CP)
    cp = torch.as_tensor(CP)
    view = camera.with_pose(res.camera_from_cm)
    # the landmarks are reprojected by construction
    assert np.abs(view.project(kin.landmarks_cm(cp).numpy()) - landmarks).max() < 0.5
    assert res.cost_px < 0.5
    # independent check of the centreline fit: dense model reprojection vs the given polyline
    dense = view.project(kin.centerline_cm(cp, n_points=300).numpy())
    assert _polyline_distance_np(dense, centerline).mean() < 0.5
    # a strongly bent CM is unambiguous without noise: depth and roll close to the truth
    assert abs(res.depth_mm - T_true[2, 3]) < 5.0
    chord = kin.landmarks_cm(cp).numpy()
    assert float(roll_about_axis_deg(res.camera_from_cm, T_true, chord[1] - chord[0])) < 5.0
    R = res.camera_from_cm[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert res.branch in ("near", "far") and 0.0 <= res.theta_deg < 360.0


def test_refinement_lowers_cost() -> None:
    camera, _, landmarks, centerline, _ = _oblique_scene()
    grid = centerline_initialize(
        camera, landmarks, centerline, CP, config=CenterlineInitConfig(refine=False, n_samples=300)
    )
    refined = centerline_initialize(
        camera, landmarks, centerline, CP, config=CenterlineInitConfig(refine=True, n_samples=300)
    )
    assert grid.cost_px == grid.grid_cost_px
    assert refined.grid_cost_px == pytest.approx(grid.cost_px)
    assert refined.cost_px < 0.5 * grid.cost_px
    assert refined.n_evaluated > grid.n_evaluated


def test_poses_from_depth_theta_geometry() -> None:
    camera, _, landmarks, _, kin = _oblique_scene()
    K = torch.as_tensor(camera.K)
    rays = (
        torch.cat([torch.as_tensor(landmarks), torch.ones(2, 1, dtype=torch.float64)], 1)
        @ torch.linalg.inv(K).T
    )
    lm_cm = kin.landmarks_cm(torch.as_tensor(CP))
    depth = torch.tensor([320.0, 380.0, 420.0, 440.0, 380.0, 380.0], dtype=torch.float64)
    theta = torch.tensor([0.0, 45.0, 200.0, 359.0, 45.0, 100.0], dtype=torch.float64)
    branch = torch.tensor([0, 1, 0, 1, 0, 1])
    T, ok = poses_from_depth_theta(rays[0], rays[1], lm_cm, depth, theta, branch)
    assert bool(ok.all())
    pts = lm_cm.numpy()
    for Ti, d in zip(T.numpy(), depth.numpy(), strict=True):
        view = camera.with_pose(Ti)
        np.testing.assert_allclose(view.project(pts), landmarks, atol=1e-8)
        assert (Ti[:3, :3] @ pts[0] + Ti[:3, 3])[2] == pytest.approx(d)
        assert np.linalg.det(Ti[:3, :3]) == pytest.approx(1.0)
    # the near and far roots at one depth put B at different depths; θ is a roll about the chord
    zb = [(Ti[:3, :3] @ pts[1] + Ti[:3, 3])[2] for Ti in T.numpy()[[1, 4]]]
    assert abs(zb[0] - zb[1]) > 1.0
    roll = roll_about_axis_deg(T[5].numpy(), T[1].numpy(), pts[1] - pts[0])
    assert float(roll) == pytest.approx(55.0, abs=1e-6)
    # beyond the feasible depth the chord cannot reach B's ray
    _, ok_far = poses_from_depth_theta(rays[0], rays[1], lm_cm, depth * 10, theta, branch)
    assert not bool(ok_far.any())


def test_roll_about_axis_ignores_swing() -> None:
    axis = np.array([0.0, 0.6, 0.8])
    twist = torch.as_tensor(axis) * math.radians(70.0)
    from fluoronav.geometry.rotations import rotvec_to_matrix

    T_true = np.eye(4)
    T_est = np.eye(4)
    T_est[:3, :3] = rotvec_to_matrix(twist).numpy()
    assert float(roll_about_axis_deg(T_est, T_true, axis)) == pytest.approx(70.0)
    T_est[:3, :3] = rotvec_to_matrix(-torch.as_tensor(axis) * math.radians(200.0)).numpy()
    assert float(roll_about_axis_deg(T_est, T_true, axis)) == pytest.approx(160.0)
    # a pure swing (axis perpendicular to the chord) has no twist
    T_est[:3, :3] = rotvec_to_matrix(torch.tensor([0.3, 0.0, 0.0], dtype=torch.float64)).numpy()
    assert float(roll_about_axis_deg(T_est, T_true, axis)) == pytest.approx(0.0, abs=1e-9)


def test_batched_cost_equals_loop_and_reference() -> None:
    camera, T_true, _, centerline, kin = _oblique_scene()
    rng = np.random.default_rng(3)
    K = torch.as_tensor(camera.K)
    T = np.repeat(T_true[None], 9, axis=0)
    T[1:, :3, 3] += rng.uniform(-5, 5, (8, 3))
    T[1:, :3, :3] = euler_to_matrix("xyz", torch.as_tensor(rng.uniform(-180, 180, (8, 3)))).numpy()
    T_t = torch.as_tensor(T)
    model = kin.centerline_cm(torch.as_tensor(CP), n_points=40)
    extracted = torch.as_tensor(centerline[::3])
    batched = centerline_cost(K, T_t, model, extracted, chunk_size=4)  # chunks of 4, 4, 1
    loop = torch.cat([centerline_cost(K, T_t[i : i + 1], model, extracted) for i in range(9)])
    # atol 1e-7 px: at the true pose (index 0) distances are ~0, and sqrt turns the ~1e-16 px² round-off
    # of a different summation order (it depends on the CPU's BLAS kernel) into ~1e-8 px
    torch.testing.assert_close(batched, loop, rtol=1e-12, atol=1e-7)
    for i in range(9):  # independent numpy reference of the symmetric trimmed-mean cost
        proj = camera.with_pose(T[i]).project(model.numpy())
        ref = 0.5 * (
            _trimmed(_polyline_distance_np(proj, extracted.numpy()), 0.1)
            + _trimmed(_polyline_distance_np(extracted.numpy(), proj), 0.1)
        )
        assert float(batched[i]) == pytest.approx(ref, rel=1e-9, abs=1e-5)  # expanded-form rounding
    assert float(batched[0]) < 0.1 < float(batched[1:].min())


def test_infeasible_landmarks_raise() -> None:
    camera = carm_camera(source_to_isocenter_mm=450.0)
    far_apart = np.array([[10.0, 10.0], [1500.0, 1500.0]])  # ~120 mm apart at 306 mm: chord ~27 mm
    line = np.linspace(far_apart[0], far_apart[1], 50)
    with pytest.raises(RegistrationFailure, match="too far apart"):
        centerline_initialize(camera, far_apart, line, CP)
    same = np.array([[700.0, 700.0], [700.0, 700.0]])
    with pytest.raises(RegistrationFailure, match="coincide"):
        centerline_initialize(camera, same, line, CP)


def test_input_errors() -> None:
    camera, _, landmarks, centerline, _ = _oblique_scene()
    with pytest.raises(InputError):
        centerline_initialize(camera, landmarks[:1], centerline, CP)
    with pytest.raises(InputError):
        centerline_initialize(camera, landmarks, centerline[:1], CP)
    with pytest.raises(InputError):
        centerline_initialize(camera, landmarks, centerline, CP[:3])
    with pytest.raises(InputError):
        centerline_initialize(camera, landmarks, centerline, CP, depth_range_mm=(500.0, 300.0))


def test_seeded_and_user_range() -> None:
    camera, _, landmarks, centerline, _ = _oblique_scene()
    kw = dict(config=CenterlineInitConfig(n_samples=200, refine=False, return_candidates=True))
    a = centerline_initialize(camera, landmarks, centerline, CP, seed=5, **kw)
    b = centerline_initialize(camera, landmarks, centerline, CP, seed=5, **kw)
    c = centerline_initialize(camera, landmarks, centerline, CP, seed=6, **kw)
    np.testing.assert_array_equal(a.camera_from_cm, b.camera_from_cm)
    assert not np.array_equal(a.candidate_depth_mm, c.candidate_depth_mm)
    assert a.candidate_costs is not None and a.candidate_costs.shape[-1] == 2
    assert a.n_evaluated == int(np.isfinite(a.candidate_costs).sum())
    # a user range is clipped to the feasible depths
    r = centerline_initialize(camera, landmarks, centerline, CP, depth_range_mm=(400.0, 2000.0), **kw)
    assert r.depth_range_mm[0] == 400.0 and r.depth_range_mm[1] < 2000.0
    assert 400.0 <= r.depth_mm <= r.depth_range_mm[1]
    w = r.world_from_cm(camera)
    np.testing.assert_allclose(camera.camera_from_world @ w, r.camera_from_cm, atol=1e-9)


def test_synthetic_scene_and_evaluation_smoke() -> None:
    sc = synthetic_centerline_scene(np.random.default_rng(0), fbg_noise_deg=0.0, landmark_noise_px=0.0)
    kin = CMKinematics()
    lm = sc.camera.with_pose(sc.camera_from_cm).project(
        kin.landmarks_cm(torch.as_tensor(sc.control_points_deg)).numpy()
    )
    np.testing.assert_allclose(sc.landmarks_px, lm, atol=1e-9)
    np.testing.assert_allclose(sc.centerline_px[[0, -1]], lm, atol=1e-6)
    out = evaluate_centerline_init(2, 0, config=CenterlineInitConfig(n_samples=100, refine=False))
    assert set(out) >= {"depth_error_mm_mean", "theta_error_deg_mean", "seconds_per_init"}
    assert 0.0 <= out["theta_error_deg_mean"] <= 180.0


def test_joint_refinement_reduces_depth_error_under_noise() -> None:
    # landmarks ±3 px and FBG ±0.5°: the grid's pinned landmarks slide the depth; the 11-DoF fit
    # (landmarks and control points as priors) recovers much of it (8 scenes, seed 3: 18.8 → 12.3 mm)
    kw = dict(fbg_noise_deg=0.5, landmark_noise_px=3.0, depth_window_mm=100.0)
    cfg = CenterlineInitConfig(n_samples=400)
    grid = evaluate_centerline_init(8, 3, config=cfg.with_(joint_refine=False), **kw)
    joint = evaluate_centerline_init(8, 3, config=cfg.with_(joint_refine=True), **kw)
    assert joint["depth_error_mm_mean"] < 0.75 * grid["depth_error_mm_mean"], (grid, joint)
    assert joint["cost_px_mean"] < grid["cost_px_mean"]


def test_depth_range_about_an_anchor() -> None:
    # isocentre at the world origin, 450 mm from the source: its depth is 450 mm
    cam = carm_camera(source_to_isocenter_mm=450.0)
    assert depth_range_about(cam, np.zeros(3), window_mm=100.0) == pytest.approx((350.0, 550.0))
    lo, hi = depth_range_about(cam, np.zeros(3), window_mm=500.0)
    assert lo == 1.0 and hi == pytest.approx(950.0)  # never behind the source
    with pytest.raises(InputError):
        depth_range_about(cam, cam.source_world - 200.0 * (np.zeros(3) - cam.source_world) / 450.0)


@pytest.mark.slow
def test_noisy_scenes_match_paper_accuracy() -> None:
    # paper (FBG U(±0.5°), detected landmarks): d_A 29.27 ± 21.02 mm, θ 30.78 ± 22.13°; AP view with
    # the bending plane nominally in the image plane (±30° perturbation); 20 scenes, so a margin
    out = evaluate_centerline_init(20, 0, scene_options={"roll_deg": 90.0})
    assert out["depth_error_mm_mean"] < 40.0
    assert out["theta_error_deg_mean"] < 35.0


def _multiview_scene(
    rng: np.random.Generator, *, cp_max_deg: float, rot_max_deg: float, orbits_deg: tuple[float, ...]
) -> tuple:
    """A random CM pose seen by an AP view and orbited views: ``(cams, cp, W, lms (V, 2, 2), cls)``."""
    from fluoronav.geometry import orbit_camera

    kin = CMKinematics()
    cp = rng.uniform(-cp_max_deg, cp_max_deg, 5)
    cpt = torch.as_tensor(cp)
    R = euler_to_matrix("xyz", torch.as_tensor(rng.uniform(-rot_max_deg, rot_max_deg, 3))).numpy()
    W = np.eye(4)
    W[:3, :3], W[:3, 3] = R, rng.uniform(-10, 10, 3)
    mid = (kin.centerline_cm(cpt).numpy() @ W[:3, :3].T + W[:3, 3]).mean(0)
    ap = carm_camera(source_to_isocenter_mm=450.0, isocenter_world=mid)
    cams = [ap, *(orbit_camera(ap, angle_deg=a, isocenter_world=mid) for a in orbits_deg)]
    pts = kin.centerline_cm(cpt, n_points=80).numpy() @ W[:3, :3].T + W[:3, 3]
    ab = kin.landmarks_cm(cpt).numpy() @ W[:3, :3].T + W[:3, 3]
    return cams, cp, W, np.stack([c.project(ab) for c in cams]), [c.project(pts) for c in cams]


def test_multiview_init_recovers_pose_and_resolves_the_mirror() -> None:
    from fluoronav.registration.centerline import centerline_initialize_multiview, mirror_about_chord

    rng = np.random.default_rng(4)
    kin = CMKinematics()
    worst = 0.0
    for _ in range(4):
        cams, cp, W, lms, cls = _multiview_scene(
            rng, cp_max_deg=7.9, rot_max_deg=60.0, orbits_deg=(20.0, -15.0)
        )
        cpt = torch.as_tensor(cp)
        res = centerline_initialize_multiview(cams, lms, cls, cp)
        tip_est = res.world_from_cm[:3, :3] @ kin.tip_cm(cpt).numpy() + res.world_from_cm[:3, 3]
        tip_true = W[:3, :3] @ kin.tip_cm(cpt).numpy() + W[:3, 3]
        worst = max(worst, float(np.linalg.norm(tip_est - tip_true)))
        assert res.cost_px < 0.5
        assert np.min(res.theta_costs_px) == pytest.approx(res.cost_px)
        # the mirror about the chord (what one view confuses) costs clearly more over three views
        mirror = mirror_about_chord(res.world_from_cm, cp)
        roll = np.degrees(
            np.arccos(np.clip(np.trace(mirror[:3, :3].T @ res.world_from_cm[:3, :3]) / 2 - 0.5, -1, 1))
        )
        assert roll > 170.0
        j = int(np.argmin(np.abs((res.theta_grid_deg - (res.theta_deg + 180.0)) % 360.0)))
        assert res.theta_costs_px[j] > res.cost_px + 1.0
        assert res.landmark_inliers.all()
        np.testing.assert_allclose(res.landmarks_px, lms)
        # B detected 80 px off in view 0 (its centreline drawn to the wrong B): that view's B is
        # left out of the triangulation and view 0 out of the roll score; the pose is unchanged
        bad = lms.copy()
        bad[0, 1] += [-60.0, -53.0]
        cls_bad = [np.concatenate([cls[0][: len(cls[0]) // 2], bad[0, 1][None]]), *cls[1:]]
        rob = centerline_initialize_multiview(cams, bad, cls_bad, cp)
        np.testing.assert_array_equal(rob.landmark_inliers, [[True, False], [True, True], [True, True]])
        np.testing.assert_allclose(rob.landmarks_px[0, 1], lms[0, 1], atol=0.5)
        tip_rob = rob.world_from_cm[:3, :3] @ kin.tip_cm(cpt).numpy() + rob.world_from_cm[:3, 3]
        worst = max(worst, float(np.linalg.norm(tip_rob - tip_true)))
    assert worst < 0.6  # 1° roll steps on a ~31 mm CM


@pytest.mark.parametrize("bad_view", [0, 1])
def test_multiview_init_two_views_trusts_the_confident_landmark(bad_view: int) -> None:
    """Two views, A of one detected on B (the 2-view case of a 20-trial study): no vote is possible;
    the more confident view's A at the model's chord length from B recovers the pose."""
    from fluoronav.registration.centerline import centerline_initialize_multiview

    kin = CMKinematics()
    cams, cp, W, lms, cls = _multiview_scene(
        np.random.default_rng(7), cp_max_deg=5.0, rot_max_deg=40.0, orbits_deg=(20.0,)
    )
    cpt = torch.as_tensor(cp)
    ab = kin.landmarks_cm(cpt).numpy() @ W[:3, :3].T + W[:3, 3]
    bad = lms.copy()
    bad[bad_view, 0] = lms[bad_view, 1] + [12.0, 3.0]  # A found next to B
    cls_bad = list(cls)
    cls_bad[bad_view] = np.linspace(bad[bad_view, 0], bad[bad_view, 1], 10)  # a stub between them
    conf = np.full((2, 2), 0.8)
    conf[bad_view] = 0.3
    tip_true = W[:3, :3] @ kin.tip_cm(cpt).numpy() + W[:3, 3]

    def tip_error(res: object) -> float:
        T = res.world_from_cm  # type: ignore[attr-defined]
        return float(np.linalg.norm(T[:3, :3] @ kin.tip_cm(cpt).numpy() + T[:3, 3] - tip_true))

    naive = centerline_initialize_multiview(cams, bad, cls_bad, cp)
    assert tip_error(naive) > 5.0  # the failure the confidence is for
    res = centerline_initialize_multiview(cams, bad, cls_bad, cp, landmark_confidence=conf)
    expected = np.ones((2, 2), bool)
    expected[bad_view, 0] = False
    np.testing.assert_array_equal(res.landmark_inliers, expected)
    np.testing.assert_allclose(res.landmarks_px[bad_view, 0], lms[bad_view, 0], atol=1.0)
    np.testing.assert_allclose(res.landmarks_world, ab, atol=0.5)
    assert tip_error(res) < 0.6
    # consistent views: the confidences change nothing
    same = centerline_initialize_multiview(cams, lms, cls, cp, landmark_confidence=conf)
    np.testing.assert_allclose(
        same.world_from_cm, centerline_initialize_multiview(cams, lms, cls, cp).world_from_cm
    )


def test_multiview_init_three_views_outvoted_by_unsure_detections_trust_the_sure_one() -> None:
    """Three views, A detected near B in two of them with low confidence (a verification whose CM
    base lay at the skin's edge): the two wrong views agree with each other and outvote the right
    one; with the confidences, A lies on the one confident view's ray at the model's chord length
    from B and the pose is recovered."""
    from fluoronav.registration.centerline import MultiViewInitConfig, centerline_initialize_multiview

    kin = CMKinematics()
    cams, cp, W, lms, cls = _multiview_scene(
        np.random.default_rng(11), cp_max_deg=5.0, rot_max_deg=40.0, orbits_deg=(20.0, -15.0)
    )
    cpt = torch.as_tensor(cp)
    tip_true = W[:3, :3] @ kin.tip_cm(cpt).numpy() + W[:3, 3]
    bad, cls_bad = lms.copy(), list(cls)
    for k in (0, 2):
        bad[k, 0] = lms[k, 1] + [10.0, 4.0]  # A found next to B
        cls_bad[k] = np.linspace(bad[k, 0], bad[k, 1], 10)
    conf = np.array([[0.3, 0.8], [0.85, 0.8], [0.4, 0.55]])

    def tip_error(res: object) -> float:
        T = res.world_from_cm  # type: ignore[attr-defined]
        return float(np.linalg.norm(T[:3, :3] @ kin.tip_cm(cpt).numpy() + T[:3, 3] - tip_true))

    unsure = centerline_initialize_multiview(
        cams,
        bad,
        cls_bad,
        cp,
        landmark_confidence=conf,
        init_config=MultiViewInitConfig(min_landmark_confidence=None),
    )
    assert tip_error(unsure) > 5.0  # the failure the confidence is for
    res = centerline_initialize_multiview(cams, bad, cls_bad, cp, landmark_confidence=conf)
    np.testing.assert_array_equal(res.landmark_inliers[:, 0], [False, True, False])
    np.testing.assert_allclose(res.landmarks_px[[0, 2], 0], lms[[0, 2], 0], atol=1.0)
    assert tip_error(res) < 0.6
    # consistent views: the confidences change nothing
    same = centerline_initialize_multiview(cams, lms, cls, cp, landmark_confidence=conf)
    np.testing.assert_array_equal(
        same.world_from_cm, centerline_initialize_multiview(cams, lms, cls, cp).world_from_cm
    )


def test_shaft_width_gives_the_depth_on_a_physics_image() -> None:
    """The shaft's apparent width (physics-simulated 384² image: polychromatic, scatter, noise) gives
    its depth within 15 mm, and the initialisation with the image lands within 15 mm in depth, where
    one view's centreline alone cannot tell depth from tilt (docs/registration.md)."""
    from fluoronav.manipulator.config import CMConfig
    from fluoronav.registration.centerline import measure_shaft_depth, shaft_depth_residual
    from fluoronav.simulation.cm_case import simulate_cm_case

    case = simulate_cm_case("single-view", seed=3, image_size=384, rotation_deg=5.0, translation_mm=5.0)
    view = case.views[0]
    T = view.camera.camera_from_world @ case.world_from_cm_true[0]
    cp = torch.as_tensor(case.control_points_true_deg)
    kin = CMKinematics()
    cl_cm = kin.centerline_cm(cp, n_points=40).numpy()
    centerline = view.camera.project(
        cl_cm @ case.world_from_cm_true[0][:3, :3].T + case.world_from_cm_true[0][:3, 3]
    )
    cue = measure_shaft_depth(
        view.camera,
        view.image,
        centerline,
        config=CMConfig(),
        shaft_length_mm=50.0,
        depth_range_mm=(300.0, 700.0),
    )
    assert cue is not None
    K = torch.as_tensor(view.camera.K)
    err_mm = float(shaft_depth_residual(cue, K, torch.as_tensor(T)[None])[0]) * cue.sigma_mm
    assert abs(err_mm) < 15.0, err_mm
    init = centerline_initialize(
        view.camera, view.landmarks_px, centerline, case.initial_control_points_deg, image=view.image, seed=0
    )
    assert init.shaft_depth_mm == pytest.approx(cue.depth_mm, abs=1.0)  # its own search range
    assert abs(init.depth_mm - T[2, 3]) < 15.0, (init.depth_mm, T[2, 3])


def test_turn_about_chord_keeps_the_landmarks_and_composes() -> None:
    from fluoronav.registration.centerline import mirror_about_chord, turn_about_chord

    W = np.eye(4)
    W[:3, :3] = euler_to_matrix("xyz", torch.tensor([10.0, -20.0, 30.0], dtype=torch.float64)).numpy()
    W[:3, 3] = [5.0, -3.0, 400.0]
    ab = CMKinematics().landmarks_cm(torch.as_tensor(CP)).numpy()
    for angle in (37.0, 180.0, 360.0):
        T = turn_about_chord(W, CP, angle)
        np.testing.assert_allclose(T[:3, :3] @ ab.T + T[:3, 3:4], W[:3, :3] @ ab.T + W[:3, 3:4], atol=1e-9)
        assert roll_about_axis_deg(T, W, ab[1] - ab[0]) == pytest.approx(
            min(angle % 360.0, 360.0 - angle % 360.0), abs=1e-6
        )
    np.testing.assert_allclose(turn_about_chord(turn_about_chord(W, CP, 50.0), CP, -50.0), W, atol=1e-12)
    np.testing.assert_allclose(mirror_about_chord(W, CP), turn_about_chord(W, CP, 180.0), atol=1e-12)


def test_multiview_init_prediction_keeps_two_wrong_views_from_outvoting_a_right_one() -> None:
    """Three views, A of two of them detected at one wrong 3D point 12 mm away (they agree with
    each other, so the vote keeps them): with the CM's expected landmarks (1.5 mm off, as after a
    move), those two are left out and A lies on the right view's ray nearest the prediction."""
    from fluoronav.registration.centerline import centerline_initialize_multiview

    kin = CMKinematics()
    cams, cp, W, lms, cls = _multiview_scene(
        np.random.default_rng(11), cp_max_deg=5.0, rot_max_deg=40.0, orbits_deg=(20.0, -15.0)
    )
    cpt = torch.as_tensor(cp)
    ab = kin.landmarks_cm(cpt).numpy() @ W[:3, :3].T + W[:3, 3]
    wrong_a = ab[0] + [6.0, 0.0, 10.0]
    bad = lms.copy()
    for k in (1, 2):
        bad[k, 0] = cams[k].project(wrong_a[None])[0]
    naive = centerline_initialize_multiview(cams, bad, cls, cp)
    assert np.linalg.norm(naive.landmarks_world[0] - ab[0]) > 5.0  # the failure the prediction is for
    expected = ab + np.array([[1.0, -0.8, 0.7], [0.9, 0.6, -0.9]])
    res = centerline_initialize_multiview(cams, bad, cls, cp, landmark_prior_world=expected)
    np.testing.assert_array_equal(res.landmark_inliers, [[True, True], [False, True], [False, True]])
    # B triangulated from the three views; A on view 0's ray: off the truth only along that ray
    np.testing.assert_allclose(res.landmarks_world[1], ab[1], atol=1e-6)
    ray = cams[0].world_from_camera[:3, :3] @ np.linalg.solve(cams[0].K, np.r_[lms[0, 0], 1.0])
    ray /= np.linalg.norm(ray)
    off = res.landmarks_world[0] - ab[0]
    assert np.linalg.norm(off - ray * (off @ ray)) < 1e-6 and abs(off @ ray) < 2.0
    # the replaced A's pixels: the prediction's depth error along view 0's ray, seen at ±20°
    np.testing.assert_allclose(res.landmarks_px[1:, 0], lms[1:, 0], atol=6.0)
    # detections that agree with the prediction: the same result as without it
    same = centerline_initialize_multiview(cams, lms, cls, cp, landmark_prior_world=expected)
    np.testing.assert_allclose(
        same.world_from_cm, centerline_initialize_multiview(cams, lms, cls, cp).world_from_cm
    )
