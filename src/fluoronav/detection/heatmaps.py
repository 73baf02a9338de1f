"""Landmark heatmap targets and sub-pixel decoding.

Heatmaps are unnormalised Gaussians with peak 1 at the landmark, so the decoded peak value doubles as
a confidence in [0, 1]. Pixel coordinates follow the package convention (u, v) = (col, row), origin
at the centre of the top-left pixel.
"""

from __future__ import annotations

import torch
from torch.nn import functional as tnf


def gaussian_heatmaps(
    points_uv: torch.Tensor,
    size: tuple[int, int],
    *,
    sigma_px: float,
    valid: torch.Tensor | None = None,
) -> torch.Tensor:
    """Gaussian targets exp(−r²/2σ²) at sub-pixel positions.

    Args:
        points_uv: (B, K, 2) landmark positions (u, v) in pixels; NaN rows are treated as absent.
        size: (rows, cols) of the heatmaps.
        sigma_px: Gaussian standard deviation in pixels.
        valid: optional (B, K) bool; False gives an all-zero heatmap (no landmark, e.g. negatives).

    Returns:
        (B, K, rows, cols) heatmaps with peak 1 at each valid landmark.
    """
    rows, cols = size
    pts = points_uv.to(torch.float32)
    ok = torch.isfinite(pts).all(dim=-1)
    if valid is not None:
        ok = ok & valid.to(torch.bool)
    pts = torch.where(ok[..., None], pts, torch.zeros_like(pts))
    u = torch.arange(cols, device=pts.device, dtype=pts.dtype)
    v = torch.arange(rows, device=pts.device, dtype=pts.dtype)
    gu = torch.exp(-((u[None, None, :] - pts[..., 0:1]) ** 2) / (2.0 * sigma_px**2))  # (B, K, cols)
    gv = torch.exp(-((v[None, None, :] - pts[..., 1:2]) ** 2) / (2.0 * sigma_px**2))  # (B, K, rows)
    return gv[..., :, None] * gu[..., None, :] * ok[..., None, None].to(pts.dtype)


def decode_heatmaps(
    heatmaps: torch.Tensor,
    *,
    method: str = "gaussian",
    window: int = 3,
    exclude: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sub-pixel peak positions and confidences of heatmaps.

    ``method="gaussian"`` fits a parabola to the log-heatmap through the argmax and its two neighbours
    along each axis (exact for a noise-free Gaussian); where the log profile is not concave it falls
    back to the integer argmax. ``method="softargmax"`` takes the centroid of the positive values in a
    (2·window+1)² window around the argmax.

    Args:
        heatmaps: (B, K, rows, cols).
        method: ``"gaussian"`` or ``"softargmax"``.
        window: half-width in pixels of the soft-argmax window.
        exclude: optional (B, K, rows, cols) bool: pixels that cannot be the peak (taken as 0).

    Returns:
        points (B, K, 2) (u, v) in pixels, and confidences (B, K): the peak value clipped to [0, 1].
    """
    if heatmaps.ndim != 4:
        raise ValueError(f"heatmaps must be (B, K, rows, cols), got {tuple(heatmaps.shape)}")
    B, K, rows, cols = heatmaps.shape
    if exclude is not None:
        heatmaps = heatmaps.masked_fill(exclude, 0.0)
    h = heatmaps.reshape(B * K, rows, cols).to(torch.float32)
    flat = h.reshape(B * K, -1)
    peak, idx = flat.max(dim=1)
    iv, iu = idx // cols, idx % cols
    if method == "gaussian":
        logh = torch.log(h.clamp_min(1e-8))
        rng = torch.arange(B * K, device=h.device)

        def at(dv: int, du: int) -> torch.Tensor:
            return logh[rng, (iv + dv).clamp(0, rows - 1), (iu + du).clamp(0, cols - 1)]

        c = at(0, 0)
        offsets = []
        for lo, hi, i, n in ((at(0, -1), at(0, 1), iu, cols), (at(-1, 0), at(1, 0), iv, rows)):
            den = lo - 2.0 * c + hi
            inside = (i > 0) & (i < n - 1) & (den < -1e-12)
            off = torch.where(
                inside,
                0.5 * (lo - hi) / torch.where(inside, den, -torch.ones_like(den)),
                torch.zeros_like(den),
            )
            offsets.append(off.clamp(-0.5, 0.5))
        pts = torch.stack([iu.to(torch.float32) + offsets[0], iv.to(torch.float32) + offsets[1]], dim=-1)
    elif method == "softargmax":
        padded = tnf.pad(h[:, None], (window, window, window, window), value=0.0)[:, 0]
        du = torch.arange(-window, window + 1, device=h.device)
        rows_idx = iv[:, None] + window + du[None, :]  # (N, k) in padded coordinates
        cols_idx = iu[:, None] + window + du[None, :]
        nk = torch.arange(B * K, device=h.device)[:, None, None]
        patch = padded[nk, rows_idx[:, :, None], cols_idx[:, None, :]].clamp_min(0.0)  # (N, k, k)
        w = patch / patch.sum(dim=(1, 2), keepdim=True).clamp_min(1e-12)
        off_u = (w.sum(dim=1) * du[None, :].to(w.dtype)).sum(dim=1)
        off_v = (w.sum(dim=2) * du[None, :].to(w.dtype)).sum(dim=1)
        pts = torch.stack([iu.to(torch.float32) + off_u, iv.to(torch.float32) + off_v], dim=-1)
    else:
        raise ValueError(f"unknown decoding method {method!r}")
    return pts.reshape(B, K, 2), peak.clamp(0.0, 1.0).reshape(B, K)


def heatmap_cross_entropy(
    logits: torch.Tensor, points_uv: torch.Tensor, *, sigma_px: float, min_inside: float = 0.5
) -> torch.Tensor:
    """Cross-entropy of spatial-softmax heatmaps against normalised Gaussian targets.

    Each heatmap's logits are a log-distribution over the pixels; the target is the Gaussian of
    :func:`gaussian_heatmaps` normalised to sum 1. Unlike the L2 regression of peak-1 Gaussians it
    cannot be lowered by predicting zeros everywhere, so it trains in a fraction of the steps.

    Args:
        logits: (B, K, rows, cols).
        points_uv: (B, K, 2) landmarks in pixels; NaN rows (negatives) are left out.
        sigma_px: target standard deviation in pixels.
        min_inside: a landmark whose Gaussian has less than this fraction of its mass inside the
            view (near or beyond the border) is left out.

    Returns:
        scalar mean over the landmarks that count (0 when none does).
    """
    B, K, rows, cols = logits.shape
    t = gaussian_heatmaps(points_uv, (rows, cols), sigma_px=sigma_px)
    mass = t.sum(dim=(-2, -1))
    ok = mass >= min_inside * 2.0 * torch.pi * sigma_px**2
    if not bool(ok.any()):
        return logits.sum() * 0.0
    logp = torch.log_softmax(logits.reshape(B, K, -1).float(), dim=-1)
    tn = t.reshape(B, K, -1) / mass.clamp_min(1e-12)[..., None]
    ce = -(tn * logp).sum(dim=-1)  # (B, K)
    return ce[ok].mean()


def decode_logit_heatmaps(
    logits: torch.Tensor,
    *,
    sigma_px: float,
    radius_sigmas: float = 2.0,
    exclude: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sub-pixel peaks and confidences of spatial-softmax heatmaps (see :func:`heatmap_cross_entropy`).

    The logits are the log-probabilities up to a constant, so the parabola fit of
    :func:`decode_heatmaps` on them is exact for a Gaussian distribution. The confidence is the
    probability mass within ``radius_sigmas`` · σ of the integer peak (≈ 0.86 for a prediction as
    sharp as the targets, → 0 for a diffuse one).

    Args:
        logits: (B, K, rows, cols).
        sigma_px: the training targets' σ in pixels.
        radius_sigmas: confidence radius in units of σ.
        exclude: optional (B, K, rows, cols) bool: pixels that cannot be the peak (the confidence is
            still the mass of the whole distribution around the peak found elsewhere).

    Returns:
        points (B, K, 2) (u, v) pixels, confidences (B, K) in [0, 1].
    """
    if logits.ndim != 4:
        raise ValueError(f"logits must be (B, K, rows, cols), got {tuple(logits.shape)}")
    B, K, rows, cols = logits.shape
    z = logits.float() - logits.float().amax(dim=(-2, -1), keepdim=True)
    p = torch.softmax(z.reshape(B, K, -1), dim=-1).reshape(B, K, rows, cols)
    if exclude is not None:
        z = z.masked_fill(exclude, _EXCLUDED_LOGIT)
        z = z - z.amax(dim=(-2, -1), keepdim=True)
    pts, _ = decode_heatmaps(torch.exp(z))
    idx = z.reshape(B, K, -1).argmax(dim=-1)
    iv, iu = (idx // cols).float(), (idx % cols).float()
    v = torch.arange(rows, device=z.device, dtype=z.dtype)
    u = torch.arange(cols, device=z.device, dtype=z.dtype)
    r2 = (v[None, None, :, None] - iv[..., None, None]) ** 2 + (
        u[None, None, None, :] - iu[..., None, None]
    ) ** 2
    conf = (p * (r2 <= (radius_sigmas * sigma_px) ** 2)).sum(dim=(-2, -1))
    return pts, conf.clamp(0.0, 1.0)


#: log-probability given to excluded pixels (exp underflows to 0 in float32)
_EXCLUDED_LOGIT = -1e4


def separation_exclusion(log_scores: torch.Tensor, *, min_separation_px: float) -> torch.Tensor:
    """Pixels to exclude so that the peaks of two landmark maps lie ``min_separation_px`` apart.

    A and B are distinct points of the CM, but where one end is unclear (a CM seen nearly end-on, or
    in heavy noise) both maps can peak on the same end. Where the two argmax pixels are closer than
    ``min_separation_px``, one map keeps its peak and the other is taken at its best pixel outside
    that disk around it: of the two choices, the one with the higher joint log-score
    ``log pA(a) + log pB(b)`` (the most probable pair that satisfies the constraint, up to the
    second-best peak of the map that moves).

    Args:
        log_scores: (B, 2, rows, cols) log-probabilities up to a constant per map (spatial-softmax
            logits, or the log of peak-1 heatmaps).
        min_separation_px: smallest A–B distance in pixels (0: no constraint).

    Returns:
        (B, 2, rows, cols) bool: the disk around the kept peak, in the map that moves; else False.
    """
    if log_scores.ndim != 4 or log_scores.shape[1] != 2:
        raise ValueError(f"log_scores must be (B, 2, rows, cols), got {tuple(log_scores.shape)}")
    B, _, rows, cols = log_scores.shape
    exclude = torch.zeros(log_scores.shape, dtype=torch.bool, device=log_scores.device)
    if min_separation_px <= 0.0:
        return exclude
    z = log_scores.float() - torch.logsumexp(log_scores.float().reshape(B, 2, -1), -1)[..., None, None]
    best, idx = z.reshape(B, 2, -1).max(dim=-1)  # (B, 2)
    iv, iu = (idx // cols).float(), (idx % cols).float()
    close = (iu[:, 0] - iu[:, 1]) ** 2 + (iv[:, 0] - iv[:, 1]) ** 2 < min_separation_px**2
    if not bool(close.any()):
        return exclude
    v = torch.arange(rows, device=z.device, dtype=z.dtype)[None, :, None]
    u = torch.arange(cols, device=z.device, dtype=z.dtype)[None, None, :]
    # disks[:, k]: the pixels within the separation of map k's peak
    disks = (v[:, None] - iv[..., None, None]) ** 2 + (u[:, None] - iu[..., None, None]) ** 2 < (
        min_separation_px**2
    )
    # the best of each map outside the other map's disk
    alt = z.masked_fill(disks.flip(1), -torch.inf).reshape(B, 2, -1).amax(dim=-1)  # (B, 2)
    move_b = best[:, 0] + alt[:, 1] >= alt[:, 0] + best[:, 1]
    exclude[:, 1] = disks[:, 0] & (close & move_b)[:, None, None]
    exclude[:, 0] = disks[:, 1] & (close & ~move_b)[:, None, None]
    return exclude


def decode_landmarks(
    heatmaps: torch.Tensor,
    *,
    mode: str,
    sigma_px: float,
    min_separation_px: float = 0.0,
    exclude: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Decode a stage's heatmap channels (B, K, rows, cols) by the model's ``heatmap`` mode; with two
    channels and ``min_separation_px`` > 0 their peaks are kept that far apart
    (:func:`separation_exclusion`). ``exclude``: optional (B, K, rows, cols) bool, pixels that cannot
    be a peak (the separation is then kept among the others)."""
    if mode not in ("softmax", "gaussian"):
        raise ValueError(f"unknown heatmap mode {mode!r}")
    if exclude is not None and exclude.shape != heatmaps.shape:
        raise ValueError(f"exclude must be {tuple(heatmaps.shape)}, got {tuple(exclude.shape)}")
    if min_separation_px > 0.0 and heatmaps.shape[1] == 2:
        scores = heatmaps if mode == "softmax" else torch.log(heatmaps.float().clamp_min(1e-8))
        if exclude is not None:
            scores = scores.float().masked_fill(exclude, _EXCLUDED_LOGIT)
        apart = separation_exclusion(scores, min_separation_px=min_separation_px)
        exclude = apart if exclude is None else exclude | apart
    if mode == "softmax":
        return decode_logit_heatmaps(heatmaps, sigma_px=sigma_px, exclude=exclude)
    return decode_heatmaps(heatmaps, exclude=exclude)
