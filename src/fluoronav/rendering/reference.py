"""Independent float64 reference DRR: exact voxel traversal (Siddon 1985 / Jacobs 1998), for tests.

The volume is taken as piecewise constant: voxel ``(i, j, k)`` fills the cell
``[i ± ½] × [j ± ½] × [k ± ½]`` of index space with value ``mu[k, j, i]``. Each ray's exact
intersection lengths with every cell it crosses (in mm) are found from its crossings of the cell
planes, so the result is the exact ∫ μ dl of that nearest-neighbour volume. Pure numpy, one ray at
a time: slow, meant for small volumes and images only. It shares no code with
:mod:`fluoronav.rendering.ct`.
"""

from __future__ import annotations

import numpy as np

__all__ = ["siddon_line_integrals"]


def _ray_integral(mu: np.ndarray, s: np.ndarray, d: np.ndarray) -> float:
    """∫ of the cell-constant ``mu`` along ``s + t·d`` for t ≥ 0 (d in index units per mm)."""
    nz, ny, nx = mu.shape
    n = np.array([nx, ny, nz], dtype=np.float64)
    t_enter, t_exit = 0.0, np.inf
    for a in range(3):
        if abs(d[a]) < 1e-15:
            if not (-0.5 <= s[a] <= n[a] - 0.5):
                return 0.0
            continue
        ta, tb = (-0.5 - s[a]) / d[a], (n[a] - 0.5 - s[a]) / d[a]
        t_enter, t_exit = max(t_enter, min(ta, tb)), min(t_exit, max(ta, tb))
    if t_exit <= t_enter:
        return 0.0
    ts = [np.array([t_enter, t_exit])]
    for a in range(3):
        if abs(d[a]) < 1e-15:
            continue
        planes = np.arange(int(n[a]) + 1, dtype=np.float64) - 0.5
        t = (planes - s[a]) / d[a]
        ts.append(t[(t > t_enter) & (t < t_exit)])
    t_all = np.unique(np.concatenate(ts))
    lengths = np.diff(t_all)
    mid = 0.5 * (t_all[1:] + t_all[:-1])
    idx = np.floor(s[None, :] + mid[:, None] * d[None, :] + 0.5).astype(np.int64)
    idx = np.clip(idx, 0, (n - 1).astype(np.int64))  # midpoints lie inside; guards rounding only
    return float(np.sum(mu[idx[:, 2], idx[:, 1], idx[:, 0]] * lengths))


def siddon_line_integrals(
    mu: np.ndarray,
    world_from_index: np.ndarray,
    K: np.ndarray,
    camera_from_world: np.ndarray,
    rows: int,
    cols: int,
) -> np.ndarray:
    """Exact line integrals of a nearest-neighbour voxel volume for one pinhole camera.

    Args:
        mu: (nz, ny, nx) attenuation, 1/mm.
        world_from_index: (4, 4) index (i, j, k, 1) → world mm.
        K: (3, 3) intrinsics (pixels); camera_from_world: (4, 4), mm; the source is the camera origin.
        rows, cols: image size.

    Returns:
        (rows, cols) float64 ∫ μ dl through pixel centres.
    """
    mu = np.asarray(mu, dtype=np.float64)
    world_from_index = np.asarray(world_from_index, dtype=np.float64)
    camera_from_world = np.asarray(camera_from_world, dtype=np.float64)
    index_from_world = np.linalg.inv(world_from_index)
    world_from_camera = np.linalg.inv(camera_from_world)
    source_index = index_from_world[:3, :3] @ world_from_camera[:3, 3] + index_from_world[:3, 3]
    K_inv = np.linalg.inv(np.asarray(K, dtype=np.float64))
    out = np.zeros((rows, cols), dtype=np.float64)
    for v in range(rows):
        for u in range(cols):
            d_world = world_from_camera[:3, :3] @ (K_inv @ np.array([u, v, 1.0]))
            d_world /= np.linalg.norm(d_world)
            out[v, u] = _ray_integral(mu, source_index, index_from_world[:3, :3] @ d_world)
    return out
