"""CM surface mesh: closed per link, outward, correct volume; binary STL round trip."""

from __future__ import annotations

import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from fluoronav.manipulator import CMConfig
from fluoronav.manipulator.mesh import cm_surface_mesh, link_meshes, mesh_volume, read_stl, write_stl

CONFIG = CMConfig()
BENT = np.array([5.0, -3.0, 4.0, 6.0, 2.0])


def analytic_volume(c: CMConfig) -> float:
    """Exact solid volume: annulus × length minus each notch's annulus segment (y beyond the cut) × width."""

    def segment(R: float, h: float) -> float:  # area of the disc of radius R with y > h
        return R * R * math.acos(h / R) - h * math.sqrt(R * R - h * h)

    ring = math.pi * (c.outer_radius_mm**2 - c.inner_radius_mm**2)
    cut = segment(c.outer_radius_mm, c.notch_cut_level_mm) - segment(c.inner_radius_mm, c.notch_cut_level_mm)
    return ring * c.total_length_mm - c.n_notches * c.notch_width_mm * cut


@pytest.mark.parametrize("cp", [np.zeros(5), BENT], ids=["straight", "bent"])
def test_each_link_mesh_is_closed_and_consistently_oriented(cp: np.ndarray) -> None:
    parts = link_meshes(CONFIG, cp)
    assert len(parts) == CONFIG.n_notches + 1
    for v, f in parts:
        directed = Counter(
            (int(a), int(b)) for tri in f for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0]))
        )
        # closed 2-manifold with consistent orientation: each directed edge once, its reverse once
        assert all(n == 1 and directed[(b, a)] == 1 for (a, b), n in directed.items())
        assert mesh_volume(v, f) > 0  # outward normals


@pytest.mark.parametrize("cp", [np.zeros(5), BENT], ids=["straight", "bent"])
def test_mesh_volume_matches_analytic_solid(cp: np.ndarray) -> None:
    v, f = cm_surface_mesh(CONFIG, cp, segments=48)
    assert mesh_volume(v, f) == pytest.approx(analytic_volume(CONFIG), rel=1e-2)


def test_mesh_volume_converges_with_segments() -> None:
    errors = [
        abs(mesh_volume(*cm_surface_mesh(CONFIG, np.zeros(5), segments=s)) / analytic_volume(CONFIG) - 1)
        for s in (24, 96)
    ]
    assert errors[1] < errors[0] / 3 and errors[1] < 1e-3


def test_stl_round_trip(tmp_path: Path) -> None:
    v, f = cm_surface_mesh(CONFIG, BENT, segments=32)
    path = tmp_path / "cm.stl"
    write_stl(path, v, f)
    assert path.stat().st_size == 84 + 50 * f.shape[0]
    tri, normals = read_stl(path)
    np.testing.assert_allclose(tri, v[f], atol=1e-4)  # float32 storage of ~30 mm coordinates
    expected_n = np.cross(v[f][:, 1] - v[f][:, 0], v[f][:, 2] - v[f][:, 0])
    expected_n /= np.linalg.norm(expected_n, axis=1, keepdims=True)
    np.testing.assert_allclose(normals, expected_n, atol=1e-5)
    assert mesh_volume(
        tri.reshape(-1, 3).astype(np.float64), np.arange(tri.shape[0] * 3).reshape(-1, 3)
    ) == pytest.approx(mesh_volume(v, f), rel=1e-5)
