"""Numba CPU kernel of the patch gradient NCC cost (private; see
:class:`~fluoronav.registration.similarity.PatchGradNCC`).

The same cost as the torch path, fused per (candidate, view) image: Gaussian smoothing, 3×3 Sobel,
the mask, the patch sums and the weighted mean of ``1 − NCC`` in one pass over the image, without
the torch path's dozen full-size temporaries per image. Images run in parallel (``prange``);
filtering in the moving image's dtype as the torch path, patch sums in float64.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange, types

__all__ = ["PATCH_GRAD_NCC_ARGS", "patch_grad_ncc_cost"]

# reassociation (vectorised sums) without assuming finite values: the non-finite check must stand
_FASTMATH = {"nsz", "arcp", "contract", "reassoc"}


@njit(cache=True, fastmath=_FASTMATH)
def _pad_row(src: np.ndarray, rad: int, out: np.ndarray) -> None:  # pragma: no cover - jitted
    """``out`` (cols + 2·rad) = ``src`` (cols) with its end values repeated ``rad`` times each side."""
    cols = src.size
    for c in range(cols):
        out[rad + c] = src[c]
    for c in range(rad):
        out[c] = src[0]
        out[rad + cols + c] = src[cols - 1]


@njit(cache=True, fastmath=_FASTMATH)
def _smooth(x: np.ndarray, g: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - jitted
    """Separable correlation with ``g`` along rows then columns, replicate padding.

    Row by row, through a padded row buffer: the inner loops are over columns without clamping and
    vectorise (a clamped per-pixel tap loop does not).
    """
    rows, cols = x.shape
    rad = (g.size - 1) // 2
    acc = np.empty(cols, x.dtype)
    padded = np.empty(cols + 2 * rad, x.dtype)
    for r in range(rows):
        acc[:] = 0.0
        for k in range(g.size):
            src = x[min(max(r + k - rad, 0), rows - 1)]
            w = g[k]
            for c in range(cols):
                acc[c] += w * src[c]
        _pad_row(acc, rad, padded)
        o = out[r]
        o[:] = 0.0
        for k in range(g.size):
            w = g[k]
            for c in range(cols):
                o[c] += w * padded[c + k]


@njit(cache=True, fastmath=_FASTMATH)
def _sobel(s: np.ndarray, mask: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> None:  # pragma: no cover
    """Sobel derivatives (kernels / 8) along columns (gx) and rows (gy), replicate padding, masked."""
    rows, cols = s.shape
    a = np.empty(cols, s.dtype)
    d = np.empty(cols, s.dtype)
    ap = np.empty(cols + 2, s.dtype)
    dp = np.empty(cols + 2, s.dtype)
    for r in range(rows):
        up, mid, dn = s[max(r - 1, 0)], s[r], s[min(r + 1, rows - 1)]
        for c in range(cols):  # smoothed across rows, and differentiated across rows
            a[c] = 0.25 * up[c] + 0.5 * mid[c] + 0.25 * dn[c]
            d[c] = 0.5 * (dn[c] - up[c])
        _pad_row(a, 1, ap)
        _pad_row(d, 1, dp)
        m, ox, oy = mask[r], gx[r], gy[r]
        for c in range(cols):  # then differentiated, and smoothed, across columns
            ox[c] = 0.5 * (ap[c + 2] - ap[c]) * m[c]
            oy[c] = (0.25 * dp[c] + 0.5 * dp[c + 1] + 0.25 * dp[c + 2]) * m[c]


@njit(cache=True, fastmath=_FASTMATH)
def _add_rows(  # pragma: no cover - jitted
    gm: np.ndarray,
    gf: np.ndarray,
    r_lo: int,
    r_hi: int,
    sign: float,
    col_m: np.ndarray,
    col_fm: np.ndarray,
    col_mm: np.ndarray,
) -> None:
    """Add ``sign`` × rows r_lo … r_hi − 1 of gm, gm·gf and gm² to the column sums (float64)."""
    for r in range(r_lo, r_hi):
        for c in range(gm.shape[1]):
            m = float(gm[r, c])
            col_m[c] += sign * m
            col_fm[c] += sign * (m * float(gf[r, c]))
            col_mm[c] += sign * (m * m)


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _image_sum(x: np.ndarray) -> float:  # pragma: no cover - jitted
    """Sum of the (H, W) image ``x`` (non-finite where a pixel is)."""
    total = 0.0
    for r in range(x.shape[0]):
        for c in range(x.shape[1]):
            total += x[r, c]
    return total


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _patch_sums(  # pragma: no cover - jitted
    gm: np.ndarray,
    gf: np.ndarray,
    d: int,
    v: int,
    sum_f: np.ndarray,
    n: np.ndarray,
    stride: int,
    side: int,
    cov: np.ndarray,
    var: np.ndarray,
    energy: np.ndarray,
    col_m: np.ndarray,
    col_fm: np.ndarray,
    col_mm: np.ndarray,
) -> None:
    """Per patch of view ``v``, gradient direction ``d``: ``cov[d]`` of the moving gradient ``gm``
    with the fixed ``gf``, ``var[d]`` its centred sum of squares and ``energy[d]`` its sum of
    squares (float64; ``col_*`` (W,) are work buffers)."""
    Pr, Pc = cov.shape[1], cov.shape[2]
    for c in range(gm.shape[1]):
        col_m[c] = 0.0
        col_fm[c] = 0.0
        col_mm[c] = 0.0
    for pr in range(Pr):
        r0 = pr * stride
        # column sums over rows r0 … r0 + side − 1: slide the previous patch row's window
        # (float64, so the running sums stay exact to ~1e-15 of the patch energy)
        if pr == 0 or stride >= side:
            if pr > 0:
                col_m[:] = 0.0
                col_fm[:] = 0.0
                col_mm[:] = 0.0
            _add_rows(gm, gf, r0, r0 + side, 1.0, col_m, col_fm, col_mm)
        else:
            _add_rows(gm, gf, r0 - stride, r0, -1.0, col_m, col_fm, col_mm)
            _add_rows(gm, gf, r0 - stride + side, r0 + side, 1.0, col_m, col_fm, col_mm)
        sm = 0.0
        sfm = 0.0
        smm = 0.0
        for c in range(side):
            sm += col_m[c]
            sfm += col_fm[c]
            smm += col_mm[c]
        for pc in range(Pc):
            c0 = pc * stride
            if pc > 0:
                if stride >= side:
                    sm = 0.0
                    sfm = 0.0
                    smm = 0.0
                    for c in range(c0, c0 + side):
                        sm += col_m[c]
                        sfm += col_fm[c]
                        smm += col_mm[c]
                else:
                    for c in range(c0 - stride, c0):
                        sm -= col_m[c]
                        sfm -= col_fm[c]
                        smm -= col_mm[c]
                    for c in range(c0 - stride + side, c0 + side):
                        sm += col_m[c]
                        sfm += col_fm[c]
                        smm += col_mm[c]
            nn = max(n[v, pr, pc], 1.0)
            cov[d, pr, pc] = sfm - sum_f[v, d, pr, pc] * sm / nn
            energy[d, pr, pc] = smm
            var[d, pr, pc] = max(smm - sm * sm / nn, 0.0)


@njit(cache=True, fastmath=_FASTMATH, inline="always")
def _weighted_dissimilarity(  # pragma: no cover - jitted
    cov: np.ndarray,
    var: np.ndarray,
    energy: np.ndarray,
    v: int,
    weight: np.ndarray,
    std_f: np.ndarray,
    eps_rel: float,
    flat_rel: float,
) -> float:
    """``Σ w (1 − NCC)`` over view ``v``'s patches of both directions (NCC 0 on flat patches)."""
    Pr, Pc = cov.shape[1], cov.shape[2]
    acc = 0.0
    for d in range(2):
        vmax = 0.0
        for pr in range(Pr):
            for pc in range(Pc):
                vmax = max(vmax, var[d, pr, pc])
        for pr in range(Pr):
            for pc in range(Pc):
                w = weight[v, d, pr, pc]
                if w <= 0.0:
                    continue
                vm = var[d, pr, pc]
                ncc = 0.0
                if vmax > 0.0 and vm > eps_rel * vmax and vm > flat_rel * energy[d, pr, pc]:
                    ncc = min(max(cov[d, pr, pc] / (std_f[v, d, pr, pc] * math.sqrt(vm)), -1.0), 1.0)
                acc += w * (1.0 - ncc)
    return acc


@njit(parallel=True, cache=True, fastmath=_FASTMATH)
def patch_grad_ncc_cost(  # pragma: no cover - jitted
    moving: np.ndarray,
    mask: np.ndarray,
    grad_fixed: np.ndarray,
    sum_f: np.ndarray,
    std_f: np.ndarray,
    n: np.ndarray,
    weight: np.ndarray,
    weight_total: np.ndarray,
    gauss: np.ndarray,
    radius: int,
    stride: int,
    eps_rel: float,
    flat_rel: float,
) -> np.ndarray:
    """Patch gradient NCC cost of every moving image.

    Args:
        moving: (B, V, H, W) moving images (float32 or float64).
        mask: (V, H, W) mask of fixed pixels (0/1), moving's dtype.
        grad_fixed: (V, 2, H, W) the fixed images' masked gradients (x, y).
        sum_f, std_f, weight: (V, 2, Pr, Pc) float64 per-patch sums of the fixed gradients, the
            square roots of their centred sums of squares, and the patch weights.
        n: (V, Pr, Pc) float64 unmasked pixels per patch.
        weight_total: (V,) float64 sum of each view's weights.
        gauss: (k,) Gaussian taps (one tap of 1: no smoothing).
        radius, stride: patch half side and spacing of patch centres, pixels.
        eps_rel, flat_rel: the flat-patch thresholds of :class:`PatchGradNCC`.

    Returns:
        (B, V) float64 cost ``Σ w (1 − NCC) / Σ w`` (1 without informative patches, NaN for a moving
        image with a non-finite pixel).
    """
    B, V, H, W = moving.shape
    Pr, Pc = sum_f.shape[2], sum_f.shape[3]
    side = 2 * radius + 1
    out = np.empty((B, V), np.float64)
    for i in prange(B * V):
        b, v = i // V, i % V
        x = moving[b, v]
        if not math.isfinite(_image_sum(x)):
            out[b, v] = np.nan
            continue
        if weight_total[v] <= 0.0:
            out[b, v] = 1.0
            continue
        s = np.empty_like(x)
        if gauss.size > 1:
            _smooth(x, gauss, s)
        else:
            s[:, :] = x
        g = np.empty((2, H, W), x.dtype)
        _sobel(s, mask[v], g[0], g[1])
        cov = np.empty((2, Pr, Pc), np.float64)
        var = np.empty((2, Pr, Pc), np.float64)
        energy = np.empty((2, Pr, Pc), np.float64)
        col_m = np.empty(W, np.float64)
        col_fm = np.empty(W, np.float64)
        col_mm = np.empty(W, np.float64)
        for d in range(2):
            _patch_sums(
                g[d], grad_fixed[v, d], d, v, sum_f, n, stride, side, cov, var, energy, col_m, col_fm, col_mm
            )
        acc = _weighted_dissimilarity(cov, var, energy, v, weight, std_f, eps_rel, flat_rel)
        out[b, v] = acc / weight_total[v]
    return out


_F32 = types.float32
_F64 = types.float64

#: the argument types :class:`fluoronav.registration.similarity.PatchGradNCC` passes for float32
#: images (the registrations' renderers make float32 images)
PATCH_GRAD_NCC_ARGS = (
    (
        types.Array(_F32, 4, "C"),
        types.Array(_F32, 3, "C"),
        types.Array(_F32, 4, "C"),
        types.Array(_F64, 4, "C"),
        types.Array(_F64, 4, "C"),
        types.Array(_F64, 3, "C"),
        types.Array(_F64, 4, "C"),
        types.Array(_F64, 1, "C"),
        types.Array(_F32, 1, "C"),
        types.int64,
        types.int64,
        _F64,
        _F64,
    ),
)
