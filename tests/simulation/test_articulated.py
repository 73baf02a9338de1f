"""ArticulatedSimulator against XraySimulator (same physics, noise-free) and rigid-motion predictions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fluoronav.anatomy.volume import Volume
from fluoronav.geometry.carm import carm_camera
from fluoronav.rendering.ct import render_line_integrals
from fluoronav.simulation.articulated import ArticulatedSimulator
from fluoronav.simulation.materials import MM_PER_CM
from fluoronav.simulation.scene import Scene
from fluoronav.simulation.xray import SimulationConfig, XraySimulator


def _motion(rotvec_deg, center, t):
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    R = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    T[:3, :3] = R
    T[:3, 3] = center - R @ center + np.asarray(t, float)
    return T


def test_identity_matches_xray_simulator(setup):
    vol, cfg, camera, world_from_cm, cp = setup
    art = ArticulatedSimulator(vol, config=cfg)
    ref = XraySimulator(vol, config=cfg).simulate(
        Scene(camera=camera, world_from_cm=world_from_cm, control_points_deg=cp), seed=0
    )
    img = art.simulate(
        camera, world_from_patient=np.eye(4), world_from_femur=np.eye(4), cm=(world_from_cm, cp), seed=0
    )
    rel = np.abs(img.image - ref.image) / np.maximum(np.abs(ref.image), 0.05)
    assert rel.max() < 0.01
    np.testing.assert_array_equal(img.mask, ref.mask)
    np.testing.assert_allclose(img.landmarks_px, ref.landmarks_px, atol=1e-9)
    assert img.mask.sum() > 20  # the CM is in the image, so the comparison covers the drilling


def test_empty_space_skipping_keeps_the_bodies_integrals(setup):
    """Each body's material renderers skip their empty space; the moved bodies' line integrals are
    those of the plain march over the whole grid (no skipping), to float32 rounding."""
    vol, cfg, camera, _, _ = setup
    art = ArticulatedSimulator(vol, config=cfg)
    stored = art.stored_camera(camera)
    wp = _motion([2.0, -3.0, 1.0], vol.landmarks_world["pelvis_center"], [4.0, -2.0, 3.0])
    wf = wp @ _motion([6.0, 4.0, -5.0], vol.landmarks_world["femoral_head_left"], [0.0, 0.0, 0.0])
    got = art.areal_densities(camera, world_from_patient=wp, world_from_femur=wf, stored=stored)
    for m, dens in got.items():
        plain = np.zeros((stored.rows, stored.cols))
        for body, w_index, w_body in (
            (art._rest, art.rest_world_from_index, wp),
            (art._femur, art.femur_world_from_index, wf),
        ):
            if m in body:
                T = stored.camera_from_world @ w_body
                img = render_line_integrals(
                    body[m].mu, w_index, stored.K, T, stored.rows, stored.cols, mipmap=False
                )
                plain += img[0].numpy()
        expected = np.clip(plain, 0.0, None) / MM_PER_CM
        assert expected.max() > 0.5  # the view holds the body
        np.testing.assert_allclose(dens.numpy(), expected, rtol=1e-5, atol=1e-6 * expected.max())


def test_moving_everything_equals_moving_the_camera(setup):
    vol, cfg, camera, world_from_cm, cp = setup
    art = ArticulatedSimulator(vol, config=cfg)
    T = _motion([4.0, -3.0, 5.0], vol.landmarks_world["pelvis_center"], [6.0, -4.0, 3.0])
    moved = art.simulate(camera, world_from_patient=T, world_from_femur=T, cm=(T @ world_from_cm, cp), seed=0)
    ref = XraySimulator(vol, config=cfg).simulate(
        Scene(
            camera=camera.with_pose(camera.camera_from_world @ T),
            world_from_cm=world_from_cm,
            control_points_deg=cp,
        ),
        seed=0,
    )
    rel = np.abs(moved.image - ref.image) / np.maximum(np.abs(ref.image), 0.05)
    assert np.median(rel) < 1e-3 and rel.max() < 0.01


def _femur_bone(art, camera, world_from_femur):
    """Areal density of the femur's cortical bone (its image minus the image without it)."""
    away = np.eye(4)
    away[:3, 3] = [0.0, 0.0, 1.0e4]  # femur far outside every ray
    stored = art.stored_camera(camera)
    kw = {"world_from_patient": np.eye(4), "stored": stored}
    with_f = art.areal_densities(camera, world_from_femur=world_from_femur, **kw)["bone_cortical"]
    without = art.areal_densities(camera, world_from_femur=away, **kw)["bone_cortical"]
    return (with_f - without).numpy(), without.numpy(), stored


def _centroid(img):
    w = np.clip(img, 0.0, None)
    rows, cols = np.indices(w.shape)
    return np.array([(w * cols).sum(), (w * rows).sum()]) / w.sum()


def test_femur_translation_moves_its_projected_centroid(setup):
    vol, cfg, _, _, _ = setup
    art = ArticulatedSimulator(vol, config=cfg)
    # a view that holds the whole femur body (so no mass leaves the field of view)
    lo = art.femur_world_from_index @ np.array([0.0, 0.0, 0.0, 1.0])
    nz, ny, nx = art._femur["bone_cortical"].mu.shape
    hi = art.femur_world_from_index @ np.array([nx - 1.0, ny - 1.0, nz - 1.0, 1.0])
    camera = carm_camera(isocenter_world=(lo[:3] + hi[:3]) / 2.0, source_to_isocenter_mm=700.0)
    # a shift parallel to the detector, applied to the femur alone
    t_cam = np.array([12.0, -8.0, 0.0])
    t_world = camera.world_from_camera[:3, :3] @ t_cam
    T = np.eye(4)
    T[:3, 3] = t_world
    f0, rest0, stored = _femur_bone(art, camera, np.eye(4))
    f1, rest1, _ = _femur_bone(art, camera, T)
    assert f0.sum() > 0 and f1.sum() == pytest.approx(f0.sum(), rel=0.01)
    # predicted image shift: magnification at the femur's (bone-weighted) depth
    mask = art._femur["bone_cortical"].mu.cpu().numpy() > 0
    k, j, i = np.nonzero(mask)
    w = art._femur["bone_cortical"].mu.cpu().numpy()[mask]
    pts = np.stack([i, j, k, np.ones_like(i)], 1) @ art.femur_world_from_index.T
    centre = (w[:, None] * pts[:, :3]).sum(0) / w.sum()
    shift_pred = stored.project(centre + t_world) - stored.project(centre)
    shift = _centroid(f1) - _centroid(f0)
    assert np.linalg.norm(shift_pred) > 8.0
    np.testing.assert_allclose(shift, shift_pred, atol=0.5)
    np.testing.assert_array_equal(rest0, rest1)  # the rest of the anatomy does not move


def test_femur_rotation_about_head_keeps_the_head(setup):
    vol, cfg, camera, _, _ = setup
    art = ArticulatedSimulator(vol, config=cfg)
    head = vol.landmarks_world["femoral_head_left"]
    f0, _, stored = _femur_bone(art, camera, np.eye(4))
    f1, _, _ = _femur_bone(art, camera, _motion([0.0, 0.0, 12.0], head, [0.0, 0.0, 0.0]))
    uv = stored.project(head[None])[0]
    r = 10  # pixels (~1 cm at the isocentre): inside the head, whose projection is rotation invariant
    win = np.s_[int(uv[1]) - r : int(uv[1]) + r, int(uv[0]) - r : int(uv[0]) + r]
    # the head's projected mass stays (its cancellous texture turns with it, so not pixel by pixel)
    assert f1[win].sum() == pytest.approx(f0[win].sum(), rel=0.02)
    assert np.abs(f1[win] - f0[win]).mean() < 0.05 * f0[win].mean()
    assert np.abs(f1 - f0).max() > 0.5 * f0.max()  # while the shaft and trochanter moved


def test_drilling_bodies_read_the_filled_ct_without_copying_it() -> None:
    """The rest body reads the filler on the femur's voxels, the femur body the filler outside its
    mask, the filler body only filler: as the explicit arrays they replace."""
    from fluoronav.simulation.articulated import FILLER_HU, _XrayHelpers

    rng = np.random.default_rng(2)
    hu = rng.normal(0.0, 500.0, (6, 7, 8)).astype(np.float32)
    mask = rng.random(hu.shape) < 0.3
    box = (slice(1, 5), slice(0, 7), slice(2, 6))
    vol = Volume(data=hu, spacing_mm=(1.0, 1.0, 1.0))
    expected = {
        "rest": np.where(mask, np.float32(FILLER_HU), hu)[box],
        "femur": np.where(mask, hu, np.float32(FILLER_HU))[box],
        "filler": np.full_like(hu[box], FILLER_HU),
    }
    device = torch.device("cpu")
    cfg = SimulationConfig()
    helpers = {
        "rest": _XrayHelpers(vol, hu, cfg, device, filled=mask),
        "femur": _XrayHelpers(vol, hu, cfg, device, filled=~mask),
        "filler": _XrayHelpers(vol, hu, cfg, device, filled=True),
    }
    for name, helper in helpers.items():
        assert np.array_equal(helper._hu_box(box), expected[name]), name
