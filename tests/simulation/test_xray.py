"""XraySimulator: consistency with the CT renderer, labels, CM contrast, negatives, speed-up accuracy."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy import ndimage

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.rendering.ct import CTRenderer
from fluoronav.simulation import noise
from fluoronav.simulation.materials import CT_MATERIALS, decompose_hu, mass_attenuation
from fluoronav.simulation.physics import XrayPhysics
from fluoronav.simulation.scene import Scene, sample_scene
from fluoronav.simulation.spectrum import Spectrum
from fluoronav.simulation.xray import SimulationConfig, XraySimulator

SIZE = 128


@pytest.fixture(scope="module")
def phantom() -> Volume:
    return hip_phantom(seed=0, spacing_mm=2.0)


@pytest.fixture(scope="module")
def sim(phantom: Volume) -> XraySimulator:
    return XraySimulator(phantom, config=SimulationConfig(image_size=SIZE))


def _scene(phantom: Volume, seed: int, **kw: object) -> Scene:
    return sample_scene(phantom, np.random.default_rng(seed), **kw)  # type: ignore[arg-type]


def _mono_noise_free(energy_keV: float) -> XrayPhysics:
    return XrayPhysics(
        custom_spectrum=Spectrum.monoenergetic(energy_keV),
        photons_per_pixel=None,
        scatter_to_primary=0.0,
        blur_sigma_px=0.0,
        glare_fraction=0.0,
    )


def test_monoenergetic_noise_free_equals_renderer_line_integral(phantom: Volume) -> None:
    """−ln(I/I0) of the whole simulator = ∫μ dl of the CT renderer on the μ(60 keV) volume, within 1 %."""
    energy = 60.0
    config = SimulationConfig(image_size=SIZE, physics=_mono_noise_free(energy))
    simulator = XraySimulator(phantom, config=config)
    scene = _scene(phantom, 3, with_cm=False)
    image = simulator.simulate(scene, seed=0).image
    # reference: one μ volume (1/mm) from the same decomposition, through the CT renderer
    parts = decompose_hu(phantom.data)
    mu = sum(parts[m] * float(mass_attenuation(m, np.array([energy]))[0]) for m in CT_MATERIALS if m != "air")
    renderer = CTRenderer(
        phantom.replace(data=(mu / 10.0).astype(np.float32), labels=None), device="cpu", mipmap=False
    )
    ref = renderer.render([simulator.stored_camera(scene)])[0].numpy()
    body = ref > 0.1
    assert body.mean() > 0.3  # the view sees the body
    rel = np.abs(image[body] - ref[body]) / ref[body]
    assert rel.max() < 0.01
    assert np.all(np.abs(image - ref) <= 0.01 * ref + 1e-4)  # everywhere, air included


def test_noise_free_cm_image_is_beer_lambert_of_areal_densities(phantom: Volume, sim: XraySimulator) -> None:
    """With a CM: mono noise-free image = Σ (μ/ρ)_m A_m of the simulator's own areal densities."""
    energy = 70.0
    simulator = XraySimulator(
        phantom, config=SimulationConfig(image_size=SIZE, physics=_mono_noise_free(energy))
    )
    scene = _scene(phantom, 5)
    dens = simulator.areal_densities(scene)
    assert "nitinol" in dens
    ref = sum(float(mass_attenuation(m, np.array([energy]))[0]) * a for m, a in dens.items())
    image = simulator.simulate(scene, seed=0).image
    np.testing.assert_allclose(image, ref.numpy(), rtol=1e-4, atol=1e-5)


def _mask_ends(mask: np.ndarray, lm: np.ndarray) -> tuple[float, float, float, float]:
    """Projections on the A→B direction of A, B and of the mask's extreme pixels."""
    d = (lm[1] - lm[0]) / np.linalg.norm(lm[1] - lm[0])
    rows, cols = np.nonzero(mask)
    s = np.stack([cols, rows], 1) @ d
    return float(lm[0] @ d), float(lm[1] @ d), float(s.min()), float(s.max())


def test_landmarks_lie_on_the_ends_of_the_mask(phantom: Volume, sim: XraySimulator) -> None:
    checked = 0
    for seed in range(30):
        scene = _scene(phantom, seed)
        camera = sim.stored_camera(scene)
        mask, lm = sim.labels(scene, camera)
        assert lm is not None and lm.shape == (2, 2)
        # the tube's end face (radius r) may protrude beyond A/B by at most its projected radius
        ends = scene.world_from_cm @ np.array([[0, 0, 0, 1.0], [0, 0, scene.cm_config.tip_z_mm, 1.0]]).T
        depth = (camera.camera_from_world @ ends)[2]
        radius_px = 0.5 * scene.cm_config.outer_diameter_mm * camera.K[0, 0] / depth.min()
        if np.linalg.norm(lm[1] - lm[0]) < 4 * (1.5 + radius_px):
            continue  # seen nearly end-on: the ends are not distinguishable at this size
        dist = ndimage.distance_transform_edt(mask == 0)
        for u, v in lm:  # on (or within 1.5 px of) the mask
            assert dist[round(float(v)), round(float(u))] <= 1.5
        sa, sb, smin, smax = _mask_ends(mask, lm)  # at its two extreme ends along the projected axis
        assert abs(smin - sa) <= 1.5 + radius_px
        assert abs(smax - sb) <= 1.5 + radius_px
        checked += 1
        if checked == 4:
            return
    pytest.fail(f"only {checked} scenes with a discernible CM axis")


def test_cm_over_bone_is_brighter_than_its_surroundings(phantom: Volume, sim: XraySimulator) -> None:
    scene = _scene(phantom, 11)
    # the CM's middle is inside the femur (a labelled voxel of femur_left/right)
    mid = scene.world_from_cm @ np.array([0.0, 0.0, 0.5 * scene.cm_config.tip_z_mm, 1.0])
    i, j, k = np.round((phantom.index_from_world @ mid)[:3]).astype(int)
    assert phantom.label_names[int(phantom.labels[k, j, i])].startswith("femur")
    noise_free = XraySimulator(
        phantom,
        config=SimulationConfig(
            image_size=SIZE, physics=dataclasses.replace(sim.config.physics, photons_per_pixel=None)
        ),
    )
    clean = noise_free.simulate(scene, seed=0)
    inside = clean.mask.astype(bool)
    ring = ndimage.binary_dilation(inside, iterations=6) & ~ndimage.binary_dilation(inside, iterations=2)
    assert clean.image[inside].mean() > clean.image[ring].mean() + 0.3
    # with quantum noise: still brighter, by more than 3 standard errors of the difference
    noisy = sim.simulate(scene, seed=4).image
    diff = noisy[inside].mean() - noisy[ring].mean()
    se = np.sqrt(noisy[inside].var() / inside.sum() + noisy[ring].var() / ring.sum())
    assert diff > 3 * se


def test_negatives_have_no_cm_labels_and_no_metal(phantom: Volume, sim: XraySimulator) -> None:
    pos = _scene(phantom, 2)
    neg = dataclasses.replace(pos, has_cm=False)
    out = sim.simulate(neg, seed=1)
    assert out.landmarks_px is None
    assert out.mask.dtype == np.uint8 and not out.mask.any()
    assert "nitinol" not in sim.areal_densities(neg)
    # same scene with the CM: brighter exactly where the CM is
    pos_out = sim.simulate(pos, seed=1)
    inside = pos_out.mask.astype(bool)
    assert (pos_out.image[inside] - out.image[inside]).mean() > 0.3


def test_same_seed_same_image(phantom: Volume, sim: XraySimulator) -> None:
    scene = _scene(phantom, 4)
    a, b, c = sim.simulate(scene, seed=9), sim.simulate(scene, seed=9), sim.simulate(scene, seed=10)
    np.testing.assert_array_equal(a.image, b.image)
    assert not np.array_equal(a.image, c.image)
    assert a.image.dtype == np.float32 and a.image.shape == (SIZE, SIZE)


def test_downsampled_scatter_matches_full_resolution() -> None:
    """The simulator's coarse scatter (4× binned, σ = 40/3 px at 512²) vs the full convolution."""
    rng = np.random.default_rng(0)
    line = torch.as_tensor(ndimage.gaussian_filter(rng.uniform(0, 6, (256, 256)), 6), dtype=torch.float32)
    primary = torch.exp(-line)
    kw = dict(scatter_to_primary=0.2, reference_line_integral=4.0, sigma_px=40.0 / 3)
    full = noise.scatter_estimate(primary, **kw)
    coarse = noise.scatter_estimate(primary, downsample=4, **kw)
    assert float((coarse - full).abs().max()) < 0.01 * float(full.max())
    flat = torch.full((64, 64), float(np.exp(-4.0)))
    spr = noise.scatter_estimate(flat, downsample=4, **kw) / flat
    np.testing.assert_allclose(spr.numpy(), 0.2, rtol=1e-5)


def test_drilled_path_sampling_reads_a_box_with_the_whole_ct_values() -> None:
    """``_sample_hu`` (a box of the CT) equals trilinear sampling of the whole CT, air outside,
    bit for bit: points inside, across the faces and all outside."""
    from scipy.ndimage import map_coordinates

    rng = np.random.default_rng(4)
    hu = rng.normal(0.0, 500.0, (12, 9, 15)).astype(np.float32)
    sim = XraySimulator.__new__(XraySimulator)  # only the sampler: no renderers needed
    sim._hu = hu
    shape = np.array(hu.shape, dtype=np.float64)[:, None]
    for lo, hi in ((2.0, 6.0), (-3.0, 4.0), (5.0, 20.0), (-30.0, -2.0), (-1.5, 40.0)):
        zyx = lo + (hi - lo) * rng.random((3, 200)) * (shape / shape.max())
        whole = map_coordinates(hu, zyx, order=1, mode="constant", cval=-1000.0)
        got = sim._sample_hu(zyx).astype(np.float32)
        assert np.array_equal(got, whole), (lo, hi)
