"""CM solid: membership in the straight and bent CM, and partial-volume voxelisation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fluoronav.manipulator import CMConfig, CMKinematics
from fluoronav.manipulator.geometry import inside_cm, inside_cm_straight, link_table, voxelize_cm

CONFIG = CMConfig()
BENT = np.array([5.0, -3.0, 4.0, 6.0, 2.0])


def _segment_area(R: float, c: float) -> float:
    """Area of the disc of radius R with y > c (|c| ≤ R)."""
    return R * R * math.acos(c / R) - c * math.sqrt(R * R - c * c)


def analytic_volume(c: CMConfig, *, notched_only: bool = False) -> float:
    """Exact solid volume: annulus × length minus every notch's annulus-segment × width."""
    ring = math.pi * (c.outer_radius_mm**2 - c.inner_radius_mm**2)
    cut = _segment_area(c.outer_radius_mm, c.notch_cut_level_mm) - _segment_area(
        c.inner_radius_mm, c.notch_cut_level_mm
    )
    length = c.distal_notch_plane_mm if notched_only else c.total_length_mm
    return ring * length - c.n_notches * c.notch_width_mm * cut


def test_inside_straight_known_points() -> None:
    c = CONFIG
    r_mid = 0.5 * (c.inner_radius_mm + c.outer_radius_mm)
    z_solid, z_notch0, z_notch1 = -2.0, c.notch_z_mm(0), c.notch_z_mm(1)
    pts = np.array(
        [
            [0.0, r_mid, z_solid],  # wall of the plain base
            [0.0, 0.0, z_solid],  # lumen
            [0.0, c.outer_radius_mm + 0.01, z_solid],  # outside
            [0.0, r_mid, z_notch0],  # notch 0 opens towards +y
            [0.0, -r_mid, z_notch0],  # its spine (y < cut level)
            [0.0, r_mid, z_notch1],  # notch 1 opens towards −y: +y is the spine
            [0.0, -r_mid, z_notch1],
            [r_mid, 0.0, z_notch0],  # side wall at y = 0 > cut level: removed
            [0.0, r_mid, c.tip_z_mm + 0.01],  # beyond the tip
            [0.0, r_mid, -c.base_length_mm - 0.01],  # below the base
        ]
    )
    expected = [True, False, False, False, True, True, False, False, False, False]
    assert inside_cm_straight(pts, c).tolist() == expected
    notched = inside_cm_straight(pts, c, region="notched")
    assert notched.tolist() == [False, False, False, False, True, True, False, False, False, False]


def test_inside_cm_straight_config_matches_straight_solid() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform([-3.2, -3.2, -4.5], [3.2, 3.2, 31.5], size=(20000, 3))
    np.testing.assert_array_equal(inside_cm(pts, np.zeros(5), CONFIG), inside_cm_straight(pts, CONFIG))


def test_inside_cm_bent_follows_the_links() -> None:
    """Points of the straight solid moved by their link's transform stay inside; the lumen stays out."""
    rng = np.random.default_rng(1)
    table = link_table(CONFIG)
    T = CMKinematics(CONFIG).link_transforms(torch.tensor(BENT)).numpy()
    pts = rng.uniform([-3.0, -3.0, -4.0], [3.0, 3.0, 31.0], size=(20000, 3))
    k = np.clip(np.searchsorted(table.z_range_mm[:, 1], pts[:, 2]), 0, len(T) - 1)
    # stay clear of the joint planes, where a bent link's neighbour may overlap or leave a gap
    z_lo, z_hi = table.z_range_mm[k, 0], table.z_range_mm[k, 1]
    clear = (pts[:, 2] > z_lo + 0.05) & (pts[:, 2] < z_hi - 0.05)
    pts, k = pts[clear], k[clear]
    bent = np.einsum("pij,pj->pi", T[k, :3, :3], pts) + T[k, :3, 3]
    straight_inside = inside_cm_straight(pts, CONFIG)
    lumen = (pts[:, 0] ** 2 + pts[:, 1] ** 2) < (CONFIG.inner_radius_mm - 0.05) ** 2
    got = inside_cm(bent, BENT, CONFIG)
    assert straight_inside.sum() > 3000
    assert got[straight_inside].all()
    assert not got[lumen].any()


def test_voxelized_volume_matches_analytic_solid() -> None:
    vox = voxelize_cm(CONFIG, np.zeros(5), spacing_mm=0.1, supersample=3)
    assert vox.occupancy.dtype == np.float32 and vox.occupancy.ndim == 3
    vol = float(vox.occupancy.sum()) * vox.spacing_mm**3
    assert vol == pytest.approx(analytic_volume(CONFIG), rel=5e-3)
    notched = voxelize_cm(CONFIG, np.zeros(5), spacing_mm=0.1, supersample=3, region="notched")
    vol_n = float(notched.occupancy.sum()) * notched.spacing_mm**3
    assert vol_n == pytest.approx(analytic_volume(CONFIG, notched_only=True), rel=5e-3)


def test_voxelized_bent_cm_matches_membership_at_voxel_centres() -> None:
    vox = voxelize_cm(CONFIG, BENT, spacing_mm=0.2, supersample=1)
    nz, ny, nx = vox.occupancy.shape
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    idx = np.stack([i.ravel(), j.ravel(), k.ravel(), np.ones(i.size)], axis=1)
    centres = (idx @ vox.world_from_index.T)[:, :3]
    expected = inside_cm(centres, BENT, CONFIG).reshape(nz, ny, nx)
    got = vox.occupancy > 0.5
    assert expected.sum() > 10000
    # only centres within rounding of a surface may disagree (float32 vs float64 transforms)
    assert (got != expected).mean() < 1e-4
    # every occupied voxel is inside the voxel grid's margin
    assert not vox.occupancy[0].any() and not vox.occupancy[-1].any()
