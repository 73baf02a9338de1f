"""Numba CPU kernel of the analytic CM renderer (private; see :mod:`fluoronav.rendering.cm`).

For each (candidate, view) image and each link, the rays of the pixels inside the link's projected
bounding box are intersected in closed form with the link's straight solid: the annulus between two
infinite cylinders, clipped to the link's axial slab, minus the notch slabs intersected with their
half-space. Every piece is convex along a ray, so each is one parameter interval and the chord
length is a sum of interval overlaps.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange, types

__all__ = ["RENDER_LINKS_ARGS", "render_links"]

_BIG = 1e30


@njit(cache=True, fastmath=True, inline="always")
def _overlap(a0: float, a1: float, b0: float, b1: float) -> float:  # pragma: no cover - jitted
    lo = a0 if a0 > b0 else b0
    hi = a1 if a1 < b1 else b1
    return hi - lo if hi > lo else 0.0


@njit(cache=True, fastmath=True, inline="always")
def _slab(o: float, d: float, lo: float, hi: float) -> tuple[float, float]:  # pragma: no cover - jitted
    """Parameter interval where ``lo ≤ o + t·d ≤ hi`` (empty as (1, 0))."""
    if abs(d) < 1e-12:
        if lo <= o <= hi:
            return -_BIG, _BIG
        return 1.0, 0.0
    t0 = (lo - o) / d
    t1 = (hi - o) / d
    if t0 > t1:
        return t1, t0
    return t0, t1


@njit(cache=True, fastmath=True)
def chord_link(  # pragma: no cover - jitted
    ox: float,
    oy: float,
    oz: float,
    dx: float,
    dy: float,
    dz: float,
    z0: float,
    z1: float,
    notches: np.ndarray,
    r_in: float,
    r_out: float,
    cut: float,
) -> float:
    """Parameter length (in units of |d|) of the ray o + t·d inside one straight link's solid."""
    a2 = dx * dx + dy * dy
    if a2 < 1e-24:
        rr = ox * ox + oy * oy
        if rr > r_out * r_out:
            return 0.0
        o0, o1 = -_BIG, _BIG
        if rr < r_in * r_in:
            i0, i1 = -_BIG, _BIG
        else:
            i0, i1 = 1.0, 0.0
    else:
        # closest approach to the axis first: stable where the ray grazes a cylinder
        tc = -(ox * dx + oy * dy) / a2
        px = ox + tc * dx
        py = oy + tc * dy
        dist2 = px * px + py * py
        if dist2 >= r_out * r_out:
            return 0.0
        h = math.sqrt((r_out * r_out - dist2) / a2)
        o0, o1 = tc - h, tc + h
        if dist2 < r_in * r_in:
            hi_ = math.sqrt((r_in * r_in - dist2) / a2)
            i0, i1 = tc - hi_, tc + hi_
        else:
            i0, i1 = 1.0, 0.0
    s0, s1 = _slab(oz, dz, z0, z1)
    s0 = s0 if s0 > 0.0 else 0.0  # the ray starts at the source
    if s1 <= s0:
        return 0.0
    total = _overlap(o0, o1, s0, s1) - _overlap(i0, i1, s0, s1)
    for m in range(notches.shape[0]):
        na = notches[m, 0] if notches[m, 0] > z0 else z0
        nb = notches[m, 1] if notches[m, 1] < z1 else z1
        if nb <= na:
            continue
        n0, n1 = _slab(oz, dz, na, nb)
        n0 = n0 if n0 > s0 else s0
        if n1 <= n0:
            continue
        side = notches[m, 2]
        sd = side * dy
        so = side * oy
        if abs(sd) < 1e-12:
            if so <= cut:
                continue
        elif sd > 0.0:
            th = (cut - so) / sd
            n0 = th if th > n0 else n0
        else:
            th = (cut - so) / sd
            n1 = th if th < n1 else n1
        if n1 <= n0:
            continue
        total -= _overlap(o0, o1, n0, n1) - _overlap(i0, i1, n0, n1)
    return total if total > 0.0 else 0.0


#: the 12 edges of a link's box, as pairs of corner indices (corners differ in one of the x, y, z bits)
_BOX_EDGES = np.array([(a, a | bit) for bit in (1, 2, 4) for a in range(8) if not a & bit], dtype=np.int64)


@njit(cache=True, fastmath=True, inline="always")
def _row_span(uv: np.ndarray, v: float, edges: np.ndarray) -> tuple[float, float]:  # pragma: no cover
    """Columns [lo, hi] where the row at ``v`` meets the convex hull of the projected corners ``uv``
    (8, 2): the hull's outline is made of projected box edges, and the others lie inside it, so the
    span is that of the row's crossings of all 12 (empty as lo > hi)."""
    lo, hi = _BIG, -_BIG
    for e in range(edges.shape[0]):
        ua, va = uv[edges[e, 0], 0], uv[edges[e, 0], 1]
        ub, vb = uv[edges[e, 1], 0], uv[edges[e, 1], 1]
        if (va - v) * (vb - v) > 0.0:
            continue
        if va == vb:
            lo, hi = min(lo, ua, ub), max(hi, ua, ub)
        else:
            u = ua + (v - va) * (ub - ua) / (vb - va)
            lo, hi = min(lo, u), max(hi, u)
    return lo, hi


@njit(parallel=True, fastmath=True, cache=True)
def render_links(  # pragma: no cover - jitted
    out: np.ndarray,
    link_from_camera: np.ndarray,
    bbox: np.ndarray,
    corners_uv: np.ndarray,
    clip: np.ndarray,
    Kinv: np.ndarray,
    n_views: int,
    z_range: np.ndarray,
    notches: np.ndarray,
    r_in: float,
    r_out: float,
    cut: float,
    scale: float,
) -> None:
    """Accumulate ``scale ×`` chord lengths (mm) into ``out``.

    Args:
        out: (BV, rows, cols) float32 output, zero-initialised by the caller.
        link_from_camera: (BV, L, 4, 4) float64 rigid transforms.
        bbox: (BV, L, 4) int64 pixel boxes ``(row0, row1, col0, col1)``, half-open; empty when
            row1 ≤ row0.
        corners_uv: (BV, L, 8, 2) float64 projected corners of each link's box.
        clip: (BV, L) bool: evaluate each row of the box only across the corners' hull (False: the
            whole box row, e.g. for a link reaching behind the source).
        Kinv: (V, 3, 3) float64 inverse intrinsics; image ``i`` uses view ``i % n_views``.
        z_range: (L, 2) axial slab of each link (already clipped to the rendered region).
        notches: (L, 2, 3) half-notches ``(z_lo, z_hi, side)`` per link.
    """
    BV = out.shape[0]
    L = z_range.shape[0]
    edges = _BOX_EDGES
    for i in prange(BV):
        Ki = Kinv[i % n_views]
        img = out[i]
        for k in range(L):
            r0, r1, c0, c1 = bbox[i, k, 0], bbox[i, k, 1], bbox[i, k, 2], bbox[i, k, 3]
            if r1 <= r0 or c1 <= c0 or z_range[k, 1] <= z_range[k, 0]:
                continue
            T = link_from_camera[i, k]
            ox, oy, oz = T[0, 3], T[1, 3], T[2, 3]
            # pixel (u, v, 1) → ray direction in the link frame in one 3×3 product (the camera-frame
            # direction, for the chord's length in mm, only where the ray hits)
            M = np.empty((3, 3))
            for a in range(3):
                for b in range(3):
                    M[a, b] = T[a, 0] * Ki[0, b] + T[a, 1] * Ki[1, b] + T[a, 2] * Ki[2, b]
            nk = notches[k]
            z0, z1 = z_range[k, 0], z_range[k, 1]
            for r in range(r0, r1):
                ca, cb = c0, c1
                if clip[i, k]:
                    lo, hi = _row_span(corners_uv[i, k], float(r), edges)
                    if lo > hi:
                        continue
                    ca = max(c0, int(math.floor(lo)))  # noqa: RUF046 (numba)
                    cb = min(c1, int(math.ceil(hi)) + 1)  # noqa: RUF046
                rx = M[0, 1] * r + M[0, 2]
                ry = M[1, 1] * r + M[1, 2]
                rz = M[2, 1] * r + M[2, 2]
                for c in range(ca, cb):
                    dx = M[0, 0] * c + rx
                    dy = M[1, 0] * c + ry
                    dz = M[2, 0] * c + rz
                    t_len = chord_link(ox, oy, oz, dx, dy, dz, z0, z1, nk, r_in, r_out, cut)
                    if t_len > 0.0:
                        # the rotation keeps lengths: |d| is the camera-frame direction's length
                        img[r, c] += scale * t_len * math.sqrt(dx * dx + dy * dy + dz * dz)


_F64 = types.float64

#: the argument types :mod:`fluoronav.rendering.cm` passes to :func:`render_links`
RENDER_LINKS_ARGS = (
    (
        types.Array(types.float32, 3, "C"),
        types.Array(_F64, 4, "C"),
        types.Array(types.int64, 3, "C"),
        types.Array(_F64, 4, "C"),
        types.Array(types.boolean, 2, "C"),
        types.Array(_F64, 3, "C"),
        types.int64,
        types.Array(_F64, 2, "C"),
        types.Array(_F64, 3, "C"),
        _F64,
        _F64,
        _F64,
        _F64,
    ),
)
