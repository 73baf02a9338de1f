"""Numba CPU kernel of the shaft's analytic chords (private; see :mod:`fluoronav.simulation.xray`).

Per stored pixel, the chords of its ``f × f`` sub-pixel rays through a hollow tube are computed and
averaged (the detector's area binning) in one pass, without the fine image in memory. The chord of
one ray is :func:`fluoronav.simulation.xray.tube_chord_mm`'s formula, term for term.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange, types

__all__ = ["BINNED_TUBE_CHORDS_ARGS", "binned_tube_chords"]


@njit(cache=True, inline="always")
def _chord(
    ox: float, oy: float, oz: float, dx: float, dy: float, dz: float, radius: float, z0: float, z1: float
) -> float:  # pragma: no cover - jitted
    """Length of the ray ``o + t·d`` (unit ``d``) inside x² + y² ≤ r², z0 ≤ z ≤ z1."""
    a = dx * dx + dy * dy
    b = 2.0 * (ox * dx + oy * dy)
    c = ox * ox + oy * oy - radius * radius
    disc = b * b - 4.0 * a * c
    if not (disc > 0.0 and a > 1e-15):
        return 0.0
    sq = math.sqrt(disc)
    t1 = (-b - sq) / (2.0 * a)
    t2 = (-b + sq) / (2.0 * a)
    dz_safe = dz if abs(dz) > 1e-15 else 1e-15
    s1 = (z0 - oz) / dz_safe
    s2 = (z1 - oz) / dz_safe
    lo = max(min(s1, s2), t1)
    hi = min(max(s1, s2), t2)
    return max(hi - lo, 0.0)


@njit(parallel=True, cache=True)
def binned_tube_chords(
    tube_from_pixel: np.ndarray,
    origin: np.ndarray,
    r_out: float,
    r_in: float,
    z0: float,
    z1: float,
    factor: int,
    out: np.ndarray,
) -> None:  # pragma: no cover - jitted
    """Mean hollow-tube chord (mm) over each stored pixel's ``factor²`` sub-pixel rays.

    Args:
        tube_from_pixel: (3, 3) maps a fine pixel (u, v, 1) to its ray direction in the tube frame
            (the tube's axis is z).
        origin: (3,) the source in the tube frame, mm.
        r_out, r_in: outer and inner radius, mm (``r_in`` 0: a solid rod).
        z0, z1: the tube's ends along z, mm.
        factor: sub-pixels per stored pixel and axis; fine pixel ``(r·f + a, c·f + b)`` lies in
            stored pixel ``(r, c)``.
        out: (rows, cols) float64, written in place.
    """
    rows, cols = out.shape
    M = tube_from_pixel
    ox = origin[0]
    oy = origin[1]
    oz = origin[2]
    inv_n = 1.0 / (factor * factor)
    for r in prange(rows):
        for c in range(cols):
            acc = 0.0
            for a in range(factor):
                vv = float(r * factor + a)
                for b in range(factor):
                    uu = float(c * factor + b)
                    dx = M[0, 0] * uu + M[0, 1] * vv + M[0, 2]
                    dy = M[1, 0] * uu + M[1, 1] * vv + M[1, 2]
                    dz = M[2, 0] * uu + M[2, 1] * vv + M[2, 2]
                    inv_len = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
                    dx *= inv_len
                    dy *= inv_len
                    dz *= inv_len
                    acc += _chord(ox, oy, oz, dx, dy, dz, r_out, z0, z1) - _chord(
                        ox, oy, oz, dx, dy, dz, r_in, z0, z1
                    )
            out[r, c] = acc * inv_n


_F64 = types.float64

#: the argument types :mod:`fluoronav.simulation.xray` passes to :func:`binned_tube_chords`
BINNED_TUBE_CHORDS_ARGS = (
    (
        types.Array(_F64, 2, "C"),
        types.Array(_F64, 1, "C"),
        _F64,
        _F64,
        _F64,
        _F64,
        types.int64,
        types.Array(_F64, 2, "C"),
    ),
)
