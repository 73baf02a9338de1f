"""Pelvis and femur 2D/3D registration against physics-simulated images (ArticulatedSimulator).

The fixed images are never made with the registration's renderer: they are polychromatic,
scatter-blurred images of the whole articulated CT (soft tissue, other bones), noise-free.
Tolerances are at the pelvis centre / femoral head: 1 mm and 0.5° for the pelvis, 1° for the femur.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.geometry.carm import carm_camera, orbit_camera
from fluoronav.registration.bone import (
    FEMUR_AUTHORS_PRESET,
    FEMUR_MULTI_VIEW_PRESET,
    FEMUR_ONE_VIEW_PRESET,
    PELVIS_AUTHORS_PRESET,
    PELVIS_PRESET,
    BoneLevel,
    BoneRegistrationConfig,
    BoneRegistrationResult,
    BoneView,
    bone_excess_mu,
    bone_footprints,
    femur_config,
    pelvis_config,
    register_femur,
    register_pelvis,
    register_pelvis_per_view,
    relative_view_poses,
    static_view_composite,
    views_from_images,
    views_in_ct_frame,
)
from fluoronav.registration.bone.levels import box_downsample
from fluoronav.registration.levels import LevelConfig
from fluoronav.registration.trace import RegistrationTrace
from fluoronav.rendering.ct import render_line_integrals
from fluoronav.simulation.articulated import ArticulatedSimulator
from fluoronav.simulation.physics import XrayPhysics
from fluoronav.simulation.protocol import sample_trial, simulate_trial_images
from fluoronav.simulation.xray import SimulationConfig

#: a lighter pelvis schedule for the unit tests (the defaults are exercised by the slow tests)
QUICK = BoneRegistrationConfig(
    levels=(
        BoneLevel(
            LevelConfig(sigma=(3, 3, 3, 6, 6, 12), popsize=12, max_iters=40), image_px=64, voxel_mm=4.0
        ),
        BoneLevel(
            LevelConfig(sigma=(1, 1, 1, 2, 2, 4), popsize=10, max_iters=30), image_px=128, voxel_mm=2.0
        ),
    )
)


@pytest.fixture(scope="module")
def volume():
    return hip_phantom(seed=0, spacing_mm=2.0)


@pytest.fixture(scope="module")
def simulator(volume):
    cfg = SimulationConfig(physics=XrayPhysics(energy_bin_keV=3.0, photons_per_pixel=None))
    return ArticulatedSimulator(volume, config=cfg)


def _h(p):
    return np.append(p, 1.0)


def _errors(W_est, W_true, center):
    """(translation mm at ``center``, rotation deg) between two poses."""
    dt = np.linalg.norm((W_est @ _h(center))[:3] - (W_true @ _h(center))[:3])
    dr = np.degrees(np.linalg.norm(Rotation.from_matrix(W_est[:3, :3] @ W_true[:3, :3].T).as_rotvec()))
    return float(dt), float(dr)


def _rotation_about(rotvec_deg, center):
    T = np.eye(4)
    R = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, :3] = R
    T[:3, 3] = center - R @ center
    return T


# ----- fast pieces ---------------------------------------------------------------------------------
def test_presets_are_data() -> None:
    assert pelvis_config() == PELVIS_PRESET and pelvis_config(authors=True) == PELVIS_AUTHORS_PRESET
    assert femur_config() == FEMUR_ONE_VIEW_PRESET and femur_config(views=3) == FEMUR_MULTI_VIEW_PRESET
    assert femur_config(authors=True, views=3) == FEMUR_AUTHORS_PRESET
    assert pelvis_config(device="cuda").device == "cuda" and PELVIS_PRESET.device == "cpu"
    # the one-view femur: the initial pose and a 3 x 3 grid of tilts about x and y, the best 3 kept
    starts = FEMUR_ONE_VIEW_PRESET.starts
    assert len(starts) == 8 and (0.0, 0.0, 0.0) not in starts and FEMUR_ONE_VIEW_PRESET.keep == 3


def test_bone_excess_volume_is_cropped_and_label_masked(volume):
    mu, w = bone_excess_mu(volume, ["pelvis"])
    assert mu.min() >= 0.0 and mu.max() > 0.02
    assert np.prod(mu.shape) < 0.5 * volume.data.size  # cropped to the pelvis
    # rendering the crop equals rendering the same field on the whole grid
    full = np.zeros(volume.data.shape, np.float32)
    lo = np.rint(np.linalg.inv(volume.world_from_index) @ w[:, 3]).astype(int)[:3]
    full[lo[2] : lo[2] + mu.shape[0], lo[1] : lo[1] + mu.shape[1], lo[0] : lo[0] + mu.shape[2]] = mu
    cam = carm_camera(isocenter_world=volume.landmarks_world["pelvis_center"]).downsample(32)
    a = render_line_integrals(
        torch.from_numpy(mu), w, cam.K, cam.camera_from_world, cam.rows, cam.cols, mipmap=False
    )
    b = render_line_integrals(
        torch.from_numpy(full),
        volume.world_from_index,
        cam.K,
        cam.camera_from_world,
        cam.rows,
        cam.cols,
        mipmap=False,
    )
    # (the two grids clip rays differently, so the midpoint samples differ slightly)
    np.testing.assert_allclose(a.numpy(), b.numpy(), atol=1e-2 * float(b.max()))
    with pytest.raises(ValueError, match="no label"):
        bone_excess_mu(volume, ["scapula"])


def test_box_downsample_keeps_the_integral_and_the_geometry():
    mu = torch.rand(9, 10, 11, dtype=torch.float64)
    w = np.diag([0.5, 0.7, 0.9, 1.0])
    w[:3, 3] = [3.0, -2.0, 1.0]
    small, w2 = box_downsample(mu, w, 2)
    assert small.shape == (5, 5, 6)
    assert float(small.sum()) * 8 == pytest.approx(float(mu.sum()))
    # the first coarse voxel centre is the centre of the first 2×2×2 block
    np.testing.assert_allclose(w2 @ [0, 0, 0, 1], w @ [0.5, 0.5, 0.5, 1])


def test_views_are_validated(volume):
    cam = carm_camera()
    with pytest.raises(ValueError, match="does not match"):
        BoneView(np.zeros((10, 10), np.float32), cam)
    a = BoneView(np.zeros((cam.rows // 8, cam.cols // 8), np.float32), cam.downsample(8))
    b = BoneView(np.zeros((cam.rows // 4, cam.cols // 4), np.float32), cam.downsample(4))
    with pytest.raises(ValueError, match="same image size"):
        register_pelvis([a, b], volume, initial_world_from_patient=np.eye(4), config=QUICK)


def test_relative_view_poses_from_per_view_estimates():
    rng = np.random.default_rng(0)
    world_from_patient = _rotation_about(rng.normal(size=3) * 5, np.zeros(3))
    cams = [orbit_camera(carm_camera(), angle_deg=a, isocenter_world=np.zeros(3)) for a in (0.0, 20.0, -15.0)]
    results = [
        BoneRegistrationResult(
            world_from_bone=world_from_patient,
            camera_from_bone=(c.camera_from_world @ world_from_patient)[None],
            params=np.zeros(6),
            cost=0.0,
            converged=True,
            reason="",
            trace=RegistrationTrace([]),
            seconds=0.0,
        )
        for c in cams
    ]
    rel = relative_view_poses(results)
    for c, r in zip(cams, rel, strict=True):
        np.testing.assert_allclose(r, c.camera_from_world @ cams[0].world_from_camera, atol=1e-9)
    # the CT frame: each view's camera placed by its pelvis estimate; a CT point projects where the
    # true camera sees it after the patient motion
    views = [BoneView(np.zeros((c.rows, c.cols), np.float32), c) for c in cams]
    ct_views = views_in_ct_frame(views, results)
    p_ct = np.array([12.0, -30.0, 45.0])
    p_world = world_from_patient[:3, :3] @ p_ct + world_from_patient[:3, 3]
    for v, c in zip(ct_views, cams, strict=True):
        np.testing.assert_allclose(v.camera.project(p_ct[None]), c.project(p_world[None]), atol=1e-9)


def _ball_volume(radius_mm: float, spacing_mm: float = 1.0) -> Volume:
    """A 1,000 HU ball labelled ``femur_left`` about the origin in soft tissue."""
    n = 64
    ax = (np.arange(n) - (n - 1) / 2) * spacing_mm
    z, y, x = np.meshgrid(ax, ax, ax, indexing="ij")
    ball = x**2 + y**2 + z**2 <= radius_mm**2
    return Volume(
        data=np.where(ball, 1000.0, 40.0).astype(np.float32),
        spacing_mm=(spacing_mm,) * 3,
        origin_mm=(float(ax[0]),) * 3,
        labels=ball.astype(np.int16),
        label_names={1: "femur_left"},
    )


def test_bone_footprints_are_the_projected_ball_widened_by_the_margin():
    radius, margin = 20.0, 3.0
    vol = _ball_volume(radius)
    cam = carm_camera().downsample(8)
    # the ball moved 15 mm along x and 10 mm along y of the CT: the footprint follows the pose
    moved = np.eye(4)
    moved[:3, 3] = [15.0, 10.0, 0.0]
    pose = cam.camera_from_world @ moved
    centre_cam = (pose @ _h(np.zeros(3)))[:3]
    f = float(cam.K[0, 0])
    c_px = cam.project((moved @ _h(np.zeros(3)))[None, :3])[0]
    rows, cols = np.mgrid[0 : cam.rows, 0 : cam.cols]
    r_px = np.hypot(cols - c_px[0], rows - c_px[1])
    # a sphere's outline: the tangent cone, radius f·R/√(d² − R²) on the image (here |c| ≈ depth)
    d = float(np.linalg.norm(centre_cam))
    ball_px = f * radius / np.sqrt(d**2 - radius**2)
    for m, extra in ((0.0, 0.0), (margin, margin * f / centre_cam[2])):
        fp = bone_footprints([cam], vol, "femur_left", pose[None], margin_mm=m, center_bone_mm=np.zeros(3))
        assert fp.shape == (1, cam.rows, cam.cols) and fp.dtype == bool
        # within 1.5 px of the analytic outline (the 2 % threshold and the voxelised ball)
        assert fp[0][r_px < ball_px + extra - 1.5].all()
        assert not fp[0][r_px > ball_px + extra + 1.5].any()


def test_per_view_pelvis_takes_one_start_per_view(volume):
    cam = carm_camera().downsample(32)
    views = [BoneView(np.zeros((cam.rows, cam.cols), np.float32), cam)] * 2
    with pytest.raises(ValueError, match=r"\(4, 4\) or \(2, 4, 4\)"):
        register_pelvis_per_view(views, volume, initial_world_from_patient=np.eye(4)[None].repeat(3, 0))


def test_instrument_masks_become_view_masks():
    cam = carm_camera().downsample(32)
    img = np.random.default_rng(0).random((cam.rows, cam.cols)).astype(np.float32)
    inst = np.zeros(img.shape, bool)
    inst[10:14, :] = True

    class Im:
        image, camera = img, cam

    a, b = views_from_images([Im(), Im()], [inst, None])
    assert b.mask is None and a.mask is not None
    np.testing.assert_array_equal(a.mask, ~inst)
    with pytest.raises(ValueError, match="2 images"):
        views_from_images([Im(), Im()], [inst])
    with pytest.raises(ValueError, match="mask shape"):
        BoneView(img, cam, np.ones((3, 3), bool))


def test_static_view_composite_fills_each_instrument_from_the_other_images():
    cam = carm_camera().downsample(32)
    rng = np.random.default_rng(1)
    anatomy = rng.random((cam.rows, cam.cols)).astype(np.float32)
    views = []
    for r0 in (5, 20, 35):  # the instrument moves between the images, the anatomy stays
        img = anatomy.copy()
        img[r0 : r0 + 4, 8:30] += 5.0
        use = np.ones(img.shape, bool)
        use[r0 - 1 : r0 + 5, 7:31] = False
        views.append(BoneView(img, cam, use))
    views.append(BoneView(anatomy + 9.0, cam))  # no mask: its instrument was not found; left out
    comp = static_view_composite(views)
    assert comp.mask is not None and comp.mask.all()
    np.testing.assert_allclose(comp.image, anatomy, atol=1e-6)
    # pixels no image can fill stay masked
    both = [BoneView(v.image, cam, np.where(np.arange(cam.cols) < 4, False, v.mask)) for v in views[:3]]
    comp2 = static_view_composite(both)
    assert comp2.mask is not None and not comp2.mask[:, :4].any() and comp2.mask[:, 4:].all()
    # without any mask: the first view; different cameras: an error
    assert static_view_composite(views[3:]) is views[3]
    with pytest.raises(ValueError, match="one camera"):
        static_view_composite(
            [views[0], BoneView(anatomy, carm_camera(source_to_isocenter_mm=500.0).downsample(32))]
        )


# ----- accuracy against physics images -------------------------------------------------------------
def test_pelvis_single_view_recovers_3deg_10mm(volume, simulator):
    trial = sample_trial("single-view", volume, np.random.default_rng(1))
    views = views_from_images(simulate_trial_images(trial, simulator, seed=0, image_size=256))
    c = trial.pelvis_center_ct
    assert _errors(trial.initial_world_from_patient, trial.world_from_patient, c) == pytest.approx(
        (10.0, 3.0)
    )
    res = register_pelvis(
        views, volume, initial_world_from_patient=trial.initial_world_from_patient, config=QUICK
    )
    dt, dr = _errors(res.world_from_bone, trial.world_from_patient, c)
    assert dt < 1.0 and dr < 0.5, (dt, dr)
    np.testing.assert_allclose(
        res.camera_from_bone[0], views[0].camera.camera_from_world @ res.world_from_bone
    )
    assert np.isfinite(res.cost) and len(res.trace.levels) == 2


def test_femur_single_view_recovers_10deg_about_the_head(volume, simulator):
    head = volume.landmarks_world["femoral_head_left"]
    entry = volume.landmarks_world["entry_left"]
    world_from_femur = _rotation_about(
        10.0 * np.array([0.48, -0.6, 0.64]) / np.linalg.norm([0.48, -0.6, 0.64]), head
    )
    cam = carm_camera(isocenter_world=head + np.array([0.0, 0.0, -10.0]), source_to_isocenter_mm=450.0)
    img = simulator.simulate(
        cam, world_from_patient=np.eye(4), world_from_femur=world_from_femur, seed=0, image_size=256
    )
    res = register_femur(views_from_images([img]), volume, side="left", world_from_patient=np.eye(4), seed=3)
    _, dr = _errors(res.world_from_bone, world_from_femur, head)
    entry_err, _ = _errors(res.world_from_bone, world_from_femur, entry)
    assert dr < 1.0, dr
    assert entry_err < 1.5, entry_err
    # the femur turns about its head only
    np.testing.assert_allclose((res.world_from_bone @ _h(head))[:3], head, atol=1e-6)


def test_masked_instrument_does_not_steer_the_femur(volume, simulator):
    """A bright metal-like bar across the femoral neck, masked out: the pixels under the mask have no
    influence at all (the same result with other values there) and the femur is recovered."""
    head = volume.landmarks_world["femoral_head_left"]
    world_from_femur = _rotation_about([4.0, -6.0, 5.0], head)
    cam = carm_camera(isocenter_world=head + np.array([0.0, 0.0, -10.0]), source_to_isocenter_mm=450.0)
    img = simulator.simulate(
        cam, world_from_patient=np.eye(4), world_from_femur=world_from_femur, seed=0, image_size=256
    )
    uv = img.camera.project(head[None])[0]
    v, u = np.mgrid[0 : img.camera.rows, 0 : img.camera.cols]
    across = np.abs((u - uv[0]) * 0.6 - (v - uv[1]) * 0.8)
    bar = across <= 4.0
    use = across > 4.0 + 10.0  # wider than the smoothing and Sobel support
    results = []
    for level in (3.0, 0.5):
        image = np.where(bar, img.image + level, img.image).astype(np.float32)
        res = register_femur(
            [BoneView(image, img.camera, use)], volume, side="left", world_from_patient=np.eye(4), seed=3
        )
        results.append(res)
    np.testing.assert_allclose(results[0].world_from_bone, results[1].world_from_bone, atol=1e-9)
    assert _errors(results[0].world_from_bone, world_from_femur, head)[1] < 1.0


@pytest.mark.slow
def test_pelvis_default_schedule_single_view(volume, simulator):
    trial = sample_trial("single-view", volume, np.random.default_rng(0))
    views = views_from_images(simulate_trial_images(trial, simulator, seed=0, image_size=384))
    res = register_pelvis(views, volume, initial_world_from_patient=trial.initial_world_from_patient)
    dt, dr = _errors(res.world_from_bone, trial.world_from_patient, trial.pelvis_center_ct)
    assert dt < 1.0 and dr < 0.5, (dt, dr)


@pytest.mark.slow
def test_multi_view_joint_pelvis_not_worse_in_depth(volume, simulator):
    trial = sample_trial("multi-view", volume, np.random.default_rng(0))
    views = views_from_images(simulate_trial_images(trial, simulator, seed=0, image_size=256))
    c = trial.pelvis_center_ct
    R0 = trial.cameras[0].camera_from_world[:3, :3]

    def depth_error(W):
        return abs((R0 @ ((W @ _h(c))[:3] - trial.pelvis_center_world))[2])

    init = trial.initial_world_from_patient
    single = register_pelvis(views[:1], volume, initial_world_from_patient=init, config=QUICK)
    joint = register_pelvis(views, volume, initial_world_from_patient=init, config=QUICK)
    assert depth_error(joint.world_from_bone) <= depth_error(single.world_from_bone) + 0.05
    dt, dr = _errors(joint.world_from_bone, trial.world_from_patient, c)
    assert dt < 1.0 and dr < 0.5, (dt, dr)
    # per-view registration gives each view's camera_from_patient, hence the view geometry
    per_view = register_pelvis_per_view(views, volume, initial_world_from_patient=init, config=QUICK)
    rel = relative_view_poses(per_view)
    truth = trial.cameras[1].camera_from_world @ trial.cameras[0].world_from_camera
    assert (
        _errors(rel[1], truth, (trial.cameras[0].camera_from_world @ _h(trial.pelvis_center_world))[:3])[1]
        < 1.0
    )


@pytest.mark.slow
def test_femur_multi_view_joint(volume, simulator):
    head = volume.landmarks_world["femoral_head_left"]
    world_from_femur = _rotation_about([6.0, -5.0, 6.0], head)
    cam = carm_camera(isocenter_world=head + np.array([0.0, 0.0, -10.0]), source_to_isocenter_mm=450.0)
    cams = [cam] + [orbit_camera(cam, angle_deg=a, isocenter_world=head) for a in (20.0, -15.0)]
    imgs = [
        simulator.simulate(
            c, world_from_patient=np.eye(4), world_from_femur=world_from_femur, seed=0, image_size=256
        )
        for c in cams
    ]
    res = register_femur(views_from_images(imgs), volume, side="left", world_from_patient=np.eye(4), seed=3)
    assert _errors(res.world_from_bone, world_from_femur, head)[1] < 1.0


def test_bone_volume_and_level_renderers_are_built_once_per_ct(volume):
    """The registrations of a navigation share each bone's excess-μ volume and level renderers."""
    from fluoronav.registration.bone.levels import BoneLevelData, shared_level_renderers
    from fluoronav.registration.bone.presets import PELVIS_LINEARIZED_PRESET
    from fluoronav.registration.bone.views import BoneView

    mu, w = bone_excess_mu(volume, ["pelvis"])
    mu2, w2 = bone_excess_mu(volume, ["pelvis"])
    assert mu2 is mu and np.array_equal(w2, w)
    w2[0, 3] += 1.0  # the pose is the caller's copy
    assert not np.array_equal(bone_excess_mu(volume, ["pelvis"])[1], w2)
    cam = carm_camera(isocenter_world=volume.landmarks_world["pelvis_center"]).downsample(8)
    view = BoneView(np.zeros((cam.rows, cam.cols), np.float32), cam, None)
    shared = shared_level_renderers(volume, ["pelvis"], "cpu")
    assert shared_level_renderers(volume, ["pelvis"], "cpu") is shared
    assert shared_level_renderers(volume, ["femur_left"], "cpu") is not shared
    levels = PELVIS_LINEARIZED_PRESET.levels
    a = BoneLevelData(
        [view], torch.from_numpy(mu), w, levels, "pelvis", torch.device("cpu"), renderers=shared
    )
    b = BoneLevelData(
        [view], torch.from_numpy(mu), w, levels, "pelvis", torch.device("cpu"), renderers=shared
    )
    assert all(a.renderers[k] is b.renderers[k] for k in a.renderers)
    # one renderer per voxel factor (levels of the same voxel size share theirs)
    spacing = float(np.linalg.norm(w[:3, :3], axis=0).min())
    factors = {max(1, int(np.floor(lv.voxel_mm / spacing + 1e-6))) for lv in levels}
    used = {id(r) for r in a.renderers.values()}
    # (earlier registrations of the same CT may have added renderers of other voxel sizes)
    assert len(used) == len(factors) and used <= {id(r) for r in shared.values()}
