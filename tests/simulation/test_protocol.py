"""The simulation protocol: ranges, reproducibility, CM in view, ground-truth consistency."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.simulation.articulated import ArticulatedSimulator
from fluoronav.simulation.physics import XrayPhysics
from fluoronav.simulation.protocol import WORKFLOWS, ProtocolConfig, sample_trial, simulate_trial_images
from fluoronav.simulation.xray import SimulationConfig


@pytest.fixture(scope="module")
def volume():
    return hip_phantom(seed=0, spacing_mm=4.0)


def _angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(R).as_rotvec())))


def _h(p: np.ndarray) -> np.ndarray:
    return np.append(p, 1.0)


@pytest.mark.parametrize("workflow", WORKFLOWS)
def test_ranges_and_cm_in_view(volume, workflow):
    rng = np.random.default_rng(7)
    n_img = {"multi-view": 3, "multi-cm": 4, "hand-eye": 4}.get(workflow, 1)
    angles_p, angles_f = [], []
    for _ in range(50):
        tr = sample_trial(workflow, volume, rng)
        assert tr.n_images == n_img and tr.world_from_cm.shape == (n_img, 4, 4)
        # pelvis: rotation ≤ 10° about an axis through the pelvis centre, translation ≤ 10 mm
        Wp, Wf = tr.world_from_patient, tr.world_from_femur
        assert np.linalg.norm(tr.pelvis_center_world - tr.pelvis_center_ct) <= 10.0 + 1e-9
        angles_p.append(_angle_deg(Wp[:3, :3]))
        # femur: rotation ≤ 15° about the head on top of the pelvis motion
        rel = np.linalg.inv(Wp) @ Wf
        np.testing.assert_allclose((rel @ _h(tr.femoral_head_ct))[:3], tr.femoral_head_ct, atol=1e-9)
        angles_f.append(_angle_deg(rel[:3, :3]))
        # entry point moves with the femur
        np.testing.assert_allclose(tr.entry_world, (Wf @ _h(tr.entry_ct))[:3], atol=1e-9)
        assert np.linalg.norm(tr.entry_world - tr.femoral_head_world) == pytest.approx(
            np.linalg.norm(tr.entry_ct - tr.femoral_head_ct)
        )
        # shape, FBG and oracle noise
        assert np.all(np.abs(tr.control_points_deg) <= 5.0)
        assert np.all(np.abs(tr.initial_control_points_deg - tr.control_points_deg) <= 0.5)
        assert np.all(np.abs(tr.oracle_landmarks_px - tr.landmarks_px) <= 3.0)
        # initial CT pose: exactly 3° and 10 mm from the truth at the pelvis centre
        D = tr.initial_world_from_patient @ np.linalg.inv(Wp)
        assert _angle_deg(D[:3, :3]) == pytest.approx(3.0)
        c_init = (tr.initial_world_from_patient @ _h(tr.pelvis_center_ct))[:3]
        assert np.linalg.norm(c_init - tr.pelvis_center_world) == pytest.approx(10.0)
        # C-arm: full CIOS detector, source 400–500 mm from the isocentre near the head
        for cam in tr.cameras:
            assert (cam.rows, cam.cols) == (1536, 1536)
            depth = cam.to_camera(tr.femoral_head_world[None])[0, 2]
            assert 400.0 - 30.0 < depth < 500.0 + 30.0
        # CM: its landmarks project inside the detector in every image
        lm = tr.landmarks_px
        assert np.all(lm >= 0.0) and np.all(lm <= 1535.0)
    assert max(angles_p) <= 10.0 + 1e-9 and max(angles_p) > 5.0
    assert max(angles_f) <= 15.0 + 1e-9 and max(angles_f) > 8.0


def test_multi_view_orbit_angles(volume):
    rng = np.random.default_rng(3)
    for _ in range(30):
        tr = sample_trial("multi-view", volume, rng)
        z = [c.world_from_camera[:3, 2] for c in tr.cameras]
        for k, mean in ((1, 20.0), (2, -15.0)):
            # signed angle about the patient long axis (+z) between the beam directions
            a = np.degrees(np.arctan2(np.cross(z[0], z[k])[2], np.dot(z[0][:2], z[k][:2])))
            assert abs(a - mean) < 5 * 3.0
        np.testing.assert_allclose(tr.world_from_cm[0], tr.world_from_cm[1])


def test_multi_cm_poses_share_camera_and_shape(volume):
    tr = sample_trial("multi-cm", volume, np.random.default_rng(5))
    assert all(c is tr.cameras[0] for c in tr.cameras)
    rel = [np.linalg.inv(tr.world_from_cm[0]) @ T for T in tr.world_from_cm[1:]]
    assert max(_angle_deg(r[:3, :3]) for r in rel) > 1.0  # the poses differ
    assert all(_angle_deg(r[:3, :3]) <= 60.0 + 1e-9 for r in rel)  # each ≤ 30° from the base


def test_reproducible(volume):
    a = sample_trial("multi-view", volume, np.random.default_rng(11))
    b = sample_trial("multi-view", volume, np.random.default_rng(11))
    c = sample_trial("multi-view", volume, np.random.default_rng(12))
    for name in (
        "world_from_patient",
        "world_from_femur",
        "world_from_cm",
        "control_points_deg",
        "oracle_landmarks_px",
        "initial_world_from_patient",
    ):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(a.cameras[2].camera_from_world, b.cameras[2].camera_from_world)
    assert not np.allclose(a.world_from_patient, c.world_from_patient)


def test_unknown_workflow(volume):
    with pytest.raises(ValueError, match="unknown workflow"):
        sample_trial("stereo", volume, np.random.default_rng(0))


def test_simulated_images_match_the_trial(volume):
    cfg = SimulationConfig(physics=XrayPhysics(energy_bin_keV=3.0, photons_per_pixel=None))
    sim = ArticulatedSimulator(volume, config=cfg)
    tr = sample_trial("multi-view", volume, np.random.default_rng(2))
    images = simulate_trial_images(tr, sim, seed=0, image_size=64)
    assert len(images) == 3
    s = 64 / 1536
    for im, lm in zip(images, tr.landmarks_px, strict=True):
        assert im.image.shape == (64, 64) and np.isfinite(im.image).all()
        # stored-pixel landmarks = full-detector landmarks, resampled (pixel-area aligned)
        np.testing.assert_allclose(im.landmarks_px, (lm + 0.5) * s - 0.5, atol=1e-6)
        assert im.mask.sum() > 0


@pytest.mark.slow
def test_bone_registration_errors_on_a_trial():
    from fluoronav.studies.pipeline import bone_registration_errors

    vol = hip_phantom(seed=0, spacing_mm=2.0)
    sim = ArticulatedSimulator(vol, config=SimulationConfig())
    tr = sample_trial("single-view", vol, np.random.default_rng(1001))
    err = bone_registration_errors(tr, simulate_trial_images(tr, sim, seed=1, image_size=384), vol, seed=2)
    assert err["pelvis_mm"] < 2.0 and err["pelvis_deg"] < 1.0
    assert err["pelvis_depth_mm"] <= err["pelvis_mm"] + 1e-9
    assert err["femur_deg"] < 3.0 and err["entry_mm"] < 3.0


def test_image_counts_follow_the_config(volume):
    default = ProtocolConfig()
    assert [default.n_images(w) for w in WORKFLOWS] == [1, 1, 3, 4, 4, 1]
    cfg = ProtocolConfig(view_offsets_deg=((20.0, 3.0),), multi_cm_poses=2)
    assert cfg.n_images("multi-view") == 2 and cfg.n_images("hand-eye") == 2
    rng = np.random.default_rng(0)
    assert sample_trial("multi-view", volume, rng, config=cfg).n_images == 2
    assert sample_trial("multi-cm", volume, rng, config=cfg).world_from_cm.shape == (2, 4, 4)
