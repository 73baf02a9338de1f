"""Domain randomisation: off changes nothing, seeded draws, records that replay, geometry of the image."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from fluoronav.errors import InputError
from fluoronav.geometry.camera import Camera
from fluoronav.simulation.materials import MATERIALS
from fluoronav.simulation.physics import XrayPhysics
from fluoronav.simulation.randomisation import (
    FILTER_MATERIAL,
    RANDOMISATION_OFF,
    RANDOMISATION_REALISTIC,
    RandomisationConfig,
    apply_image_record,
    beam_filter_densities,
    beam_filters_from_record,
    output_camera,
    physics_from_record,
    randomise_image,
    randomised_physics,
)

#: every source on, every event certain
ALWAYS = dataclasses.replace(
    RANDOMISATION_REALISTIC,
    p_collimation=1.0,
    p_wedge=1.0,
    p_linear_output=1.0,
    p_partial_fov=1.0,
    p_rotate_180=1.0,
    p_transpose=1.0,
)
LANDMARKS = np.array([[20.0, 30.0], [70.0, 40.0]])


def _sample(rows: int = 64, cols: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """A random log image and the mask of a straight CM from A to B (LANDMARKS)."""
    image = np.random.default_rng(0).uniform(0.0, 3.0, (rows, cols)).astype(np.float32)
    mask = np.zeros((rows, cols), np.uint8)
    for t in np.linspace(0.0, 1.0, 200):
        u, v = np.rint(LANDMARKS[0] + t * (LANDMARKS[1] - LANDMARKS[0])).astype(int)
        mask[v - 1 : v + 2, u] = 1
    return image, mask


def test_off_draws_nothing_and_changes_nothing() -> None:
    rng = np.random.default_rng(1)
    state = rng.bit_generator.state
    physics = XrayPhysics()
    same, record = randomised_physics(physics, RANDOMISATION_OFF, rng)
    assert same is physics and record == {}
    assert beam_filter_densities(32, 32, RANDOMISATION_OFF, rng) == ({}, {})
    image, mask = _sample()
    out_image, out_mask, out_lm, record = randomise_image(image, mask, LANDMARKS, RANDOMISATION_OFF, rng)
    assert out_image is image and out_mask is mask and out_lm is LANDMARKS and record == {}
    assert rng.bit_generator.state == state


def test_seeded_draws_are_deterministic() -> None:
    image, mask = _sample()
    runs = []
    for _ in range(2):
        rng = np.random.default_rng(7)
        physics, p_rec = randomised_physics(XrayPhysics(), ALWAYS, rng)
        filters, f_rec = beam_filter_densities(64, 96, ALWAYS, rng, keep_points_px=LANDMARKS)
        runs.append((physics, p_rec, filters, f_rec, *randomise_image(image, mask, LANDMARKS, ALWAYS, rng)))
    (p1, r1, f1, fr1, i1, m1, l1, ir1), (p2, r2, f2, fr2, i2, m2, l2, ir2) = runs
    assert p1 == p2 and r1 == r2 and fr1 == fr2 and ir1 == ir2
    assert torch.equal(f1[FILTER_MATERIAL], f2[FILTER_MATERIAL])
    assert l1 is not None and l2 is not None
    assert np.array_equal(i1, i2) and np.array_equal(m1, m2) and np.array_equal(l1, l2)
    other, _ = randomised_physics(XrayPhysics(), ALWAYS, np.random.default_rng(8))
    assert other != p1


def test_records_list_every_draw_and_replay_without_a_generator() -> None:
    base = XrayPhysics(extra_filtration_mm=(("aluminium", 1.0),))
    rng = np.random.default_rng(3)
    physics, record = randomised_physics(base, ALWAYS, rng)
    assert set(record) == {
        "kvp",
        "filtration",
        "added_al_mm",
        "added_cu_mm",
        "dose_factor",
        "electronic_noise_std",
        "blur_sigma_px",
        "glare_fraction",
        "scatter_to_primary",
        "scatter_sigma_px",
    }
    assert physics_from_record(base, record) == physics
    assert physics.photons_per_pixel == pytest.approx(5000.0 * record["dose_factor"])
    assert dict(physics.extra_filtration_mm)["aluminium"] == pytest.approx(1.0 + record["added_al_mm"])
    assert 60.0 <= physics.kvp <= 120.0 and physics.spectrum.kvp == physics.kvp  # the spectrum loads
    filters, f_rec = beam_filter_densities(64, 96, ALWAYS, rng, keep_points_px=LANDMARKS)
    assert {"collimation_angle_deg", "collimation_cu_mm", "wedge_angle_deg", "wedge_cu_mm"} <= set(f_rec)
    assert torch.equal(beam_filters_from_record(64, 96, f_rec)[FILTER_MATERIAL], filters[FILTER_MATERIAL])
    image, mask = _sample()
    out = randomise_image(image, mask, LANDMARKS, ALWAYS, rng)
    keys = {"output_gamma", "output_gain", "output_offset", "linear_output", "window_px", "rotate_180"}
    assert keys | {"transpose", "window_cut_landmark", "landmarks_in_image"} <= set(out[3])
    replay = apply_image_record(image, mask, LANDMARKS, out[3])
    assert replay[2] is not None and out[2] is not None
    assert np.array_equal(replay[0], out[0]) and np.array_equal(replay[1], out[1])
    assert np.array_equal(replay[2], out[2], equal_nan=True)


@pytest.mark.parametrize(("rotate", "transpose"), [(1.0, 0.0), (0.0, 1.0), (1.0, 1.0)])
def test_rotation_and_transpose_move_the_landmarks_with_the_image(rotate: float, transpose: float) -> None:
    image, mask = _sample()
    cfg = RandomisationConfig(p_rotate_180=rotate, p_transpose=transpose)
    out_image, out_mask, out_lm, record = randomise_image(
        image, mask, LANDMARKS, cfg, np.random.default_rng(0)
    )
    assert out_image.shape == (image.shape[::-1] if transpose else image.shape) and out_lm is not None
    affine = np.asarray(record["pixel_affine"])
    for (u, v), (u2, v2) in zip(LANDMARKS.astype(int), out_lm, strict=True):
        assert out_image[int(v2), int(u2)] == image[v, u]  # the landmark's pixel value follows it
        assert out_mask[int(v2), int(u2)] == mask[v, u] == 1
        assert np.allclose(affine @ [u, v, 1.0], [u2, v2, 1.0])
    assert np.array_equal(np.sort(out_image, axis=None), np.sort(image, axis=None))


def test_partial_field_of_view_leaves_one_landmark_out_and_flags_it() -> None:
    image, mask = _sample()
    for seed in range(12):
        cfg = RandomisationConfig(p_partial_fov=1.0)
        out_image, out_mask, lm, record = randomise_image(
            image, mask, LANDMARKS, cfg, np.random.default_rng(seed)
        )
        rows, cols = out_image.shape
        assert lm is not None
        inside = (lm[:, 0] >= -0.5) & (lm[:, 0] <= cols - 0.5) & (lm[:, 1] >= -0.5) & (lm[:, 1] <= rows - 0.5)
        cut = record["window_cut_landmark"]
        assert record["landmarks_in_image"] == list(inside) and not inside[cut] and inside[1 - cut]
        assert out_mask.any() and np.all(np.isfinite(lm))
        x0, y0, x1, y1 = record["window_px"]
        assert np.array_equal(out_image, image[y0:y1, x0:x1])
    nan_cfg = RandomisationConfig(p_partial_fov=1.0, out_of_view_landmarks="nan")
    _, _, lm, record = randomise_image(image, mask, LANDMARKS, nan_cfg, np.random.default_rng(0))
    assert lm is not None
    assert (
        np.isnan(lm[record["window_cut_landmark"]]).all()
        and np.isfinite(lm[1 - record["window_cut_landmark"]]).all()
    )
    # a negative gets a window of the same kind, anywhere, and stays a negative
    empty = np.zeros_like(mask)
    out_image, _, lm, record = randomise_image(image, empty, None, cfg, np.random.default_rng(0))
    assert lm is None and out_image.shape != image.shape and "landmarks_in_image" not in record


def test_output_camera_projects_as_the_pixel_affine_maps() -> None:
    image, mask = _sample()
    camera = Camera(64, 96, np.array([[1200.0, 0.0, 50.0], [0.0, 1200.0, 30.0], [0.0, 0.0, 1.0]]), np.eye(4))
    cfg = RandomisationConfig(p_partial_fov=1.0, p_rotate_180=1.0)
    _, _, _, record = randomise_image(image, mask, LANDMARKS, cfg, np.random.default_rng(4))
    out = output_camera(camera, record)
    points = np.array([[3.0, -4.0, 800.0], [-10.0, 6.0, 700.0]])
    uv = np.c_[camera.project(points), np.ones(2)] @ np.asarray(record["pixel_affine"]).T
    assert np.allclose(out.project(points), uv[:, :2])
    _, _, _, record = randomise_image(
        image, mask, LANDMARKS, RandomisationConfig(p_transpose=1.0), np.random.default_rng(0)
    )
    with pytest.raises(InputError):
        output_camera(camera, record)


def test_beam_filters_keep_the_cm_in_the_field_and_ramp_the_wedge() -> None:
    rho = MATERIALS[FILTER_MATERIAL].density_g_cm3 / 10.0
    blades = RandomisationConfig(p_collimation=1.0, collimation_field_frac_range=(0.3, 0.3))
    for seed in range(5):
        dens, record = beam_filter_densities(
            64, 96, blades, np.random.default_rng(seed), keep_points_px=LANDMARKS
        )
        d = dens[FILTER_MATERIAL]
        for u, v in LANDMARKS.astype(int):
            assert d[v, u] == 0.0  # open field at the CM
        assert float(d.max()) >= record["collimation_cu_mm"] * rho * (1 - 1e-6)  # blades at the edge
    wedge = RandomisationConfig(p_wedge=1.0)
    dens, record = beam_filter_densities(64, 96, wedge, np.random.default_rng(0))
    d = dens[FILTER_MATERIAL]
    assert float(d.min()) == 0.0 and float(d.max()) <= record["wedge_cu_mm"] * rho * (1 + 1e-6)
    assert float(d.max()) > 0.8 * record["wedge_cu_mm"] * rho


def test_randomised_physics_images() -> None:
    physics, _ = randomised_physics(XrayPhysics(energy_bin_keV=3.0), ALWAYS, np.random.default_rng(2))
    dens = {"soft_tissue": torch.full((32, 32), 15.0), "stainless_steel": torch.zeros(32, 32)}
    filters, _ = beam_filter_densities(32, 32, ALWAYS, np.random.default_rng(2))
    image = physics.apply({**dens, **filters}, seed=0)
    assert image.shape == (32, 32) and torch.isfinite(image).all()


def test_config_checks_its_ranges() -> None:
    with pytest.raises(ValueError):
        RandomisationConfig(kvp_range=(50.0, 90.0))
    with pytest.raises(ValueError):
        RandomisationConfig(p_wedge=1.5)
    with pytest.raises(ValueError):
        RandomisationConfig(gain_range=(2.0, 1.0))
