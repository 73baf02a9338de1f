"""The case's CT from a finer patient: partial volume, HU scale and noise, label boundaries."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.simulation.clinical_ct import clinical_ct, partial_volume
from fluoronav.simulation.world import IDEAL, CTWorld


def _ball(shape: tuple[int, int, int] = (48, 56, 64), spacing: float = 0.5, hu: float = 1000.0) -> Volume:
    """A textured ball on a zero background, with origin and a landmark off the grid's symmetry."""
    rng = np.random.default_rng(0)
    nz, ny, nx = shape
    z, y, x = np.mgrid[:nz, :ny, :nx]
    r = np.sqrt((x - 30.3) ** 2 + (y - 27.1) ** 2 + (z - 22.6) ** 2) * spacing
    data = np.where(r < 8.0, hu + 100.0 * rng.standard_normal(shape), 0.0).astype(np.float32)
    return Volume(
        data=data,
        spacing_mm=(spacing, spacing, spacing),
        origin_mm=(-3.0, 7.0, 11.0),
        labels=(r < 8.0).astype(np.uint8),
        label_names={1: "ball"},
        landmarks_world={
            "centre": np.array([-3.0 + 30.3 * spacing, 7.0 + 27.1 * spacing, 11.0 + 22.6 * spacing])
        },
        name="ball",
    )


def _centre_of_mass_world(v: Volume) -> np.ndarray:
    com_zyx = np.asarray(ndimage.center_of_mass(v.data.astype(np.float64)))
    return (v.world_from_index @ np.append(com_zyx[::-1], 1.0))[:3]


def test_partial_volume_preserves_hu_times_volume_and_position() -> None:
    patient = _ball()
    ct = partial_volume(patient, (0.8, 0.8, 1.5), np.array([0.31, 0.77, 0.52]))
    assert ct.spacing_mm == (0.8, 0.8, 1.5)
    integral_patient = patient.data.astype(np.float64).sum() * 0.5**3
    integral_ct = ct.data.astype(np.float64).sum() * 0.8 * 0.8 * 1.5
    assert integral_ct == pytest.approx(integral_patient, rel=1e-5)
    np.testing.assert_allclose(_centre_of_mass_world(ct), _centre_of_mass_world(patient), atol=1e-3)
    # partial volume: the boundary voxels mix ball and background
    assert np.any((ct.data > 50.0) & (ct.data < 700.0))
    # the CT lies inside the patient's field of view
    lo, hi = patient.corners_world().min(axis=0), patient.corners_world().max(axis=0)
    assert np.all(ct.corners_world() >= lo - 1e-9) and np.all(ct.corners_world() <= hi + 1e-9)


def test_partial_volume_grid_offset_moves_the_origin() -> None:
    patient = _ball()
    a = partial_volume(patient, (0.8, 0.8, 1.5), np.zeros(3))
    b = partial_volume(patient, (0.8, 0.8, 1.5), np.array([0.5, 0.25, 0.0]))
    np.testing.assert_allclose(np.subtract(b.origin_mm, a.origin_mm), [0.4, 0.2, 0.0], atol=1e-12)
    corner = np.asarray(patient.origin_mm) - 0.25  # outer corner of the patient grid
    np.testing.assert_allclose(np.subtract(a.origin_mm, corner), [0.4, 0.4, 0.75], atol=1e-12)


def test_hu_scale_and_noise_recovered() -> None:
    patient = Volume(data=np.full((40, 48, 56), 500.0, dtype=np.float32), spacing_mm=(1.0, 1.0, 1.0))
    for seed in range(4):
        ct = clinical_ct(patient, CTWorld(hu_noise_sd=15.0, hu_scale_error=0.03), np.random.default_rng(seed))
        scale = float(ct.data.mean()) / 500.0
        assert abs(abs(scale - 1.0) - 0.03) < 0.001
        assert float(ct.data.std()) == pytest.approx(15.0, rel=0.03)
        # a little spatial correlation between neighbours, as a reconstruction kernel gives
        d = ct.data - ct.data.mean()
        corr = float(np.mean(d[:, :, 1:] * d[:, :, :-1]) / d.var())
        assert 0.2 < corr < 0.8
    assert patient.data.max() == 500.0  # the patient is not modified


def _mean_boundary_shift_mm(before: np.ndarray, after: np.ndarray, spacing: float) -> float:
    """Mean distance of the new boundary voxels from the old boundary, mm."""
    edt_out = ndimage.distance_transform_edt(~before) * spacing
    edt_in = ndimage.distance_transform_edt(before) * spacing
    surface = after & ~ndimage.binary_erosion(after)
    d = np.where(before, edt_in - 0.5 * spacing, edt_out - 0.5 * spacing)
    return float(np.abs(d[surface]).mean())


def test_label_boundary_moved_by_about_the_configured_voxels() -> None:
    shape = (64, 64, 96)
    z, y, x = np.mgrid[: shape[0], : shape[1], : shape[2]]
    left = np.sqrt((x - 28) ** 2 + (y - 32) ** 2 + (z - 32) ** 2) < 20
    right = np.sqrt((x - 69) ** 2 + (y - 32) ** 2 + (z - 32) ** 2) < 20  # one voxel gap from left
    labels = (left * 1 + right * 2).astype(np.uint8)
    # landmarks on the boundary voxels of the left ball, in and out (x, y, z = world = index here)
    marks = {"gap": np.array([48.0, 32.0, 32.0])}  # where the balls nearly touch
    for n, (dx, dy, dz) in enumerate([(-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]):
        for r in (19.0, 20.0):
            marks[f"m{n}_{r}"] = np.array([28.0 + r * dx, 32.0 + r * dy, 32.0 + r * dz])
    patient = Volume(
        data=np.zeros(shape, np.float32),
        spacing_mm=(1.0, 1.0, 1.0),
        labels=labels,
        label_names={1: "left", 2: "right"},
        landmarks_world=marks,
    )
    cfg = CTWorld(label_boundary_voxels=1.5, label_smoothness_mm=8.0)
    shifts = []
    for seed in range(3):
        out = clinical_ct(patient, cfg, np.random.default_rng(seed)).labels
        assert out is not None and out.dtype == labels.dtype
        assert set(np.unique(out)) == {0, 1, 2}  # one value per voxel: disjoint
        # deep inside stays, far outside stays background
        assert np.all(out[_depth(left) > 6] == 1)
        assert out[0, 0, 0] == 0
        # the landmarks' labels are kept
        for p in marks.values():
            i, j, k = p.astype(int)
            assert out[k, j, i] == labels[k, j, i]
        for value, mask in ((1, left), (2, right)):
            shifts.append(_mean_boundary_shift_mm(mask, out == value, 1.0))
            assert not np.array_equal(out == value, mask)
    # |N(0, σ)| has mean 0.8 σ; voxelisation adds about a quarter voxel
    assert 0.8 * 1.5 - 0.35 < np.mean(shifts) < 0.8 * 1.5 + 0.45


def _depth(mask: np.ndarray) -> np.ndarray:
    return ndimage.distance_transform_edt(mask)


def test_phantom_ct_keeps_frame_and_landmark_labels() -> None:
    patient = hip_phantom(seed=0, spacing_mm=4.0)
    cfg = CTWorld(ct_spacing_mm=(5.0, 5.0, 6.0), label_boundary_voxels=1.0, label_smoothness_mm=20.0)
    offset = np.random.default_rng(7).uniform(0.0, 1.0, 3)
    grid = partial_volume(patient, cfg.ct_spacing_mm, offset)  # type: ignore[arg-type]
    ct = clinical_ct(patient, cfg, np.random.default_rng(7))
    assert ct.origin_mm == grid.origin_mm and np.array_equal(ct.direction, patient.direction)
    assert ct.label_names == patient.label_names and ct.name == patient.name
    assert ct.labels is not None and grid.labels is not None
    assert not np.array_equal(ct.labels, grid.labels)
    for name, p in patient.landmarks_world.items():
        np.testing.assert_array_equal(ct.landmarks_world[name], p)
        i, j, k = np.round((ct.index_from_world @ np.append(p, 1.0))[:3]).astype(int)
        if 0 <= i < ct.shape_xyz[0] and 0 <= j < ct.shape_xyz[1] and 0 <= k < ct.shape_xyz[2]:
            assert ct.labels[k, j, i] == grid.labels[k, j, i], name


def test_ideal_ct_is_the_patient_and_draws_nothing() -> None:
    patient = hip_phantom(seed=0, spacing_mm=8.0)
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    assert clinical_ct(patient, IDEAL.ct, rng) is patient
    assert rng.bit_generator.state == state
    assert not IDEAL.ct.enabled and CTWorld(hu_noise_sd=1.0).enabled
