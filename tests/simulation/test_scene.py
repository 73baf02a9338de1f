"""Scene sampling: the paper's ranges, the CM in and around the femur, unlabelled CTs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.simulation.dataset import DatasetSpec
from fluoronav.simulation.scene import (
    BONE_HU,
    SceneSampling,
    angle_between_deg,
    projected_ab_mm,
    projected_shaft_angle_deg,
    projected_shaft_mm,
    sample_scene,
)


@pytest.fixture(scope="module")
def phantom() -> Volume:
    return hip_phantom(seed=0, spacing_mm=2.0)


def test_sampled_ranges_follow_the_paper(phantom: Volume) -> None:
    rng = np.random.default_rng(0)
    sampling = SceneSampling()
    scenes = [sample_scene(phantom, rng) for _ in range(60)]
    cp = np.array([s.control_points_deg for s in scenes])
    assert cp.min() >= -7.9 and cp.max() <= 7.9 and cp.max() - cp.min() > 12  # spans the range
    sid = np.array([s.source_to_isocenter_mm for s in scenes])
    assert sid.min() >= 400 and sid.max() <= 500
    alpha = np.array([s.lao_rao_deg for s in scenes])
    beta = np.array([s.cran_caud_deg for s in scenes])
    assert alpha.min() >= 0 and alpha.max() <= 360 and alpha.max() - alpha.min() > 250
    assert beta.min() >= 75 and beta.max() <= 105
    for s in scenes:
        # the camera's source sits at the sampled distance from the isocentre
        source = -s.camera.camera_from_world[:3, :3].T @ s.camera.camera_from_world[:3, 3]
        assert np.linalg.norm(source - s.isocenter_world) == pytest.approx(s.source_to_isocenter_mm, abs=1e-6)
        # the isocentre is the CM's middle shifted by at most the translation range per axis
        mid = (s.world_from_cm @ np.array([0, 0, 0.5 * s.cm_config.tip_z_mm, 1.0]))[:3]
        assert np.all(np.abs(mid - s.isocenter_world) <= sampling.translation_mm + 1e-9)
        assert s.side in ("left", "right")


def test_cm_overlaps_the_femur(phantom: Volume) -> None:
    rng = np.random.default_rng(1)
    femur = {k for k, v in phantom.label_names.items() if v.startswith("femur")}
    fractions = []
    for _ in range(20):
        s = sample_scene(phantom, rng)
        cp = torch.as_tensor(np.asarray(s.control_points_deg, np.float64))
        pts = CMKinematics(s.cm_config).centerline_cm(cp, n_points=30).numpy()
        world = np.c_[pts, np.ones(len(pts))] @ s.world_from_cm.T
        ijk = np.round(world @ phantom.index_from_world.T)[:, :3].astype(int)
        inside = np.all((ijk >= 0) & (ijk < phantom.data.shape[::-1]), axis=1)
        labels = np.zeros(len(pts), int)
        labels[inside] = phantom.labels[ijk[inside, 2], ijk[inside, 1], ijk[inside, 0]]
        fractions.append(np.isin(labels, list(femur)).mean())
    fractions = np.array(fractions)
    assert np.median(fractions) > 0.5  # mostly inside the femur ("in")
    assert fractions.min() > 0.2  # and never outside it ("around": the base may stick out)


def test_same_rng_state_same_scene(phantom: Volume) -> None:
    a = sample_scene(phantom, np.random.default_rng(5))
    b = sample_scene(phantom, np.random.default_rng(5))
    np.testing.assert_array_equal(a.camera.camera_from_world, b.camera.camera_from_world)
    np.testing.assert_array_equal(a.world_from_cm, b.world_from_cm)
    assert not sample_scene(phantom, np.random.default_rng(5), with_cm=False).has_cm


def test_unlabelled_ct_gets_the_cm_in_the_bone_nearest_the_centre() -> None:
    # a water cylinder with two bone rods; the one nearer the volume centre must be chosen
    shape = (40, 50, 60)
    hu = np.zeros(shape, np.float32)
    _, j, i = np.indices(shape)
    hu[(j - 25) ** 2 + (i - 35) ** 2 < 9] = 1200.0  # near the centre (i = 29.5)
    hu[(j - 25) ** 2 + (i - 8) ** 2 < 9] = 1200.0  # far
    vol = Volume(data=hu, spacing_mm=(1.5, 1.5, 2.0), origin_mm=(-40.0, 10.0, 5.0), name="ct")
    for seed in range(5):
        s = sample_scene(vol, np.random.default_rng(seed))
        assert s.side == ""
        a = (vol.index_from_world @ s.world_from_cm[:, 3])[:3]
        ii, jj, kk = np.round(a).astype(int)
        assert hu[kk, jj, ii] > BONE_HU
        assert abs(a[0] - 35) < 4


def test_projected_ab_matches_the_rendered_landmarks(phantom: Volume) -> None:
    # the rejection test's distance is the one the labels give: the simulator's landmarks (px) × pitch
    from fluoronav.simulation.xray import SimulationConfig, XraySimulator

    sim = XraySimulator(phantom, config=SimulationConfig(image_size=96))
    for seed in range(4):
        s = sample_scene(phantom, np.random.default_rng(seed))
        cam = sim.stored_camera(s)
        _, lm = sim.labels(s, cam)
        assert lm is not None and cam.pixel_spacing_mm is not None
        expected = float(np.linalg.norm(lm[1] - lm[0])) * cam.pixel_spacing_mm
        assert projected_ab_mm(s) == pytest.approx(expected, rel=1e-9)


def test_foreshortened_sampling_keeps_only_short_projections(phantom: Volume) -> None:
    plain = [projected_ab_mm(sample_scene(phantom, np.random.default_rng(k))) for k in range(40)]
    assert max(plain) > 45  # the paper's distribution is mostly CMs across the view
    short = SceneSampling(max_projected_ab_mm=25.0)
    kept = [
        projected_ab_mm(sample_scene(phantom, np.random.default_rng(k), sampling=short)) for k in range(20)
    ]
    assert max(kept) <= 25.0
    assert min(kept) < 15  # not only the threshold's edge: the tail below it is there too
    # reproducible for a seed, like every draw
    a = sample_scene(phantom, np.random.default_rng(3), sampling=short)
    b = sample_scene(phantom, np.random.default_rng(3), sampling=short)
    np.testing.assert_array_equal(a.camera.camera_from_world, b.camera.camera_from_world)
    with pytest.raises(ValueError, match=r"max_projected_ab_mm=0\.01"):
        sample_scene(
            phantom, np.random.default_rng(0), sampling=SceneSampling(max_projected_ab_mm=0.01, max_draws=50)
        )


def test_shaft_sampling_keeps_only_short_shafts(phantom: Volume) -> None:
    # a straight CM: its notched part A → B (26.85 mm along +z) and a shaft as long behind A
    # (−z) project alike, up to the perspective of a 27 mm depth change at ~450 mm
    for k in range(6):
        s = sample_scene(phantom, np.random.default_rng(k))
        straight = dataclasses.replace(s, control_points_deg=np.zeros(5))
        ab = projected_ab_mm(straight)
        assert projected_shaft_mm(straight, 26.85) == pytest.approx(ab, rel=0.15, abs=0.5)
        assert projected_shaft_mm(s, 50.0) == pytest.approx(2 * projected_shaft_mm(s, 25.0), rel=0.15)
    plain = [projected_shaft_mm(sample_scene(phantom, np.random.default_rng(k)), 50.0) for k in range(40)]
    assert np.median(plain) > 60  # the paper's distribution: mostly a shaft across the view
    short = SceneSampling(max_projected_shaft_mm=30.0, shaft_length_mm=50.0)
    kept = [sample_scene(phantom, np.random.default_rng(k), sampling=short) for k in range(12)]
    assert max(projected_shaft_mm(s, 50.0) for s in kept) <= 30.0
    both = SceneSampling(max_projected_shaft_mm=40.0, max_projected_ab_mm=30.0)
    s = sample_scene(phantom, np.random.default_rng(1), sampling=both)
    assert projected_shaft_mm(s, 50.0) <= 40.0 and projected_ab_mm(s) <= 30.0
    # the sampler checks its limits where it is made; a data set's spec makes it at once
    with pytest.raises(ValueError, match="needs a shaft"):
        SceneSampling(max_projected_shaft_mm=30.0, shaft_length_mm=0.0)
    with pytest.raises(ValueError, match="needs a shaft"):
        DatasetSpec(max_projected_shaft_mm=30.0, shaft_length_mm=0.0)
    with pytest.raises(ValueError, match="max_projected_shaft_mm must be positive"):
        SceneSampling(max_projected_shaft_mm=0.0)
    with pytest.raises(ValueError, match="max_projected_ab_mm must be positive"):
        SceneSampling(max_projected_ab_mm=-1.0)


def test_angle_between_deg_by_hand() -> None:
    assert angle_between_deg(np.array([1.0, 0.0]), np.array([0.0, 2.0])) == pytest.approx(90.0)
    assert angle_between_deg(np.array([1.0, 0.0]), np.array([-3.0, 0.0])) == pytest.approx(180.0)
    assert angle_between_deg(np.array([1.0, 1.0]), np.array([1.0, 0.0])) == pytest.approx(45.0)
    tilted = np.array([0.0, 1.0, np.sqrt(3.0)])
    assert angle_between_deg(np.array([0.0, 0.0, 1.0]), tilted) == pytest.approx(30.0)
    assert np.isnan(angle_between_deg(np.zeros(2), np.array([1.0, 0.0])))


def test_shaft_angle_sampling_keeps_only_v_views(phantom: Volume) -> None:
    # a straight CM goes on from A where its shaft ends: the two meet at ~180° in any view that
    # does not see them end-on (a 27 mm CM and a 50 mm shaft on one line)
    for k in range(4):
        s = sample_scene(phantom, np.random.default_rng(k))
        straight = dataclasses.replace(s, control_points_deg=np.zeros(5))
        if projected_ab_mm(straight) > 10.0:
            assert projected_shaft_angle_deg(straight, 50.0) == pytest.approx(180.0, abs=0.5)
    rngs = [np.random.default_rng(k) for k in range(60)]
    plain = [projected_shaft_angle_deg(sample_scene(phantom, rng), 50.0) for rng in rngs]
    assert np.median(plain) > 130  # the paper's distribution: mostly the shaft behind the CM
    v_views = SceneSampling(max_shaft_angle_deg=70.0)
    kept = [sample_scene(phantom, np.random.default_rng(k), sampling=v_views) for k in range(8)]
    angles = [projected_shaft_angle_deg(s, 50.0) for s in kept]
    assert max(angles) <= 70.0
    a = sample_scene(phantom, np.random.default_rng(5), sampling=v_views)
    b = sample_scene(phantom, np.random.default_rng(5), sampling=v_views)
    np.testing.assert_array_equal(a.world_from_cm, b.world_from_cm)
    with pytest.raises(ValueError, match="max_shaft_angle_deg needs a shaft"):
        SceneSampling(max_shaft_angle_deg=70.0, shaft_length_mm=0.0)
    with pytest.raises(ValueError, match=r"max_shaft_angle_deg must be in \(0, 180\]"):
        DatasetSpec(max_shaft_angle_deg=200.0)
    with pytest.raises(ValueError, match=r"max_shaft_angle_deg=0\.01"):
        sample_scene(
            phantom, np.random.default_rng(0), sampling=SceneSampling(max_shaft_angle_deg=0.01, max_draws=20)
        )
