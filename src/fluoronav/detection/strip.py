"""Where along a path the CM begins: the strip stage, the detector's check of landmark A.

Where the mounting shaft is foreshortened to a stub and seen beside the CM, the projected shaft and
CM form a V with A at its apex. The fine stage can take the stub's far end for A (it is a tube end),
its mask then fills the V, and the centreline from that end to B cuts straight across it; no stage
that looks along that centreline sees the corner where the plain shaft meets the notched CM.

This stage resamples the image along a path (a polyline of input pixels) into a strip of ``shape``
(rows across × cols along, one strip pixel = ``step_px`` input pixels, the path's start at column 0)
and a small U-Net, its two output channels averaged across the strip, gives per column a logit for
"A lies here" and one whose mean over the path's columns is the logit of "A is not on this path".
A softmax over the path's columns and that class gives P(A at column k) and P(no A)
(:func:`strip_log_probs`). Trained on paths made from the true geometry (:func:`training_path`):
the true path from a point of the shaft through A to B, two straight legs through A, legs through a
wrong corner, and paths that start at A and bend on the CM.

The detector (:meth:`~fluoronav.detection.detector.Detector.off_apex`) asks it about two paths of an
unsure detection: its own centreline and the path through the V's apex (:func:`v_apex`); A moves to
the apex where the first path says that A is not at its start and the second that A is at the apex.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch
from scipy import ndimage

from fluoronav.detection.refine import photometric_change

__all__ = [
    "StripJitter",
    "a_column",
    "path_strips",
    "resample_path",
    "strip_log_probs",
    "strip_targets",
    "training_path",
    "training_strip",
    "v_apex",
    "window_probability",
]


def resample_path(path_px: np.ndarray, step_px: float, max_points: int) -> np.ndarray:
    """Points (n, 2) (u, v) every ``step_px`` of arc length along a polyline (N, 2) from its start,
    at most ``max_points`` of them (n = 1 for a path without length)."""
    pts = np.asarray(path_px, dtype=np.float64)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    s = np.arange(0.0, arc[-1] + 1e-9, step_px)[:max_points]
    return np.stack([np.interp(s, arc, pts[:, 0]), np.interp(s, arc, pts[:, 1])], axis=1)


def path_strips(
    image: np.ndarray,
    paths_px: list[np.ndarray],
    *,
    step_px: float,
    shape: tuple[int, int],
    smooth_px: float = 10.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Strips (P, rows, cols) float32 of ``image`` along each path (N, 2) (u, v) input px, and which
    columns lie on the path (P, cols) bool.

    Column k is the point at arc length k · ``step_px`` from the path's start, row j the point
    (j − (rows − 1)/2) · ``step_px`` along the normal there (the tangent averaged over ± ``smooth_px``
    strip pixels, so that a corner of the path does not fold the strip); bilinear, edges repeated.
    Each strip is normalised to zero mean and unit s.d. over its path's columns; the other columns
    are 0."""
    rows, cols = shape
    img = np.asarray(image, dtype=np.float32)
    out = np.zeros((len(paths_px), rows, cols), np.float32)
    valid = np.zeros((len(paths_px), cols), bool)
    off = (np.arange(rows, dtype=np.float64) - (rows - 1) / 2.0) * step_px
    for p, path in enumerate(paths_px):
        pts = resample_path(path, step_px, cols)
        n = len(pts)
        if n < 2:
            continue
        t = np.gradient(pts, axis=0)
        t = ndimage.uniform_filter1d(t, size=2 * int(smooth_px) + 1, axis=0, mode="nearest")
        t /= np.linalg.norm(t, axis=1, keepdims=True) + 1e-12
        normal = np.stack([-t[:, 1], t[:, 0]], axis=1)
        uv = pts[None] + off[:, None, None] * normal[None]
        v = cv2.remap(
            img,
            uv[..., 0].astype(np.float32),
            uv[..., 1].astype(np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        out[p, :, :n] = (v - v.mean()) / (v.std() + 1e-6)
        valid[p, :n] = True
    return out, valid


def strip_log_probs(logits: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Log-probabilities (P, cols + 1) of A at each column and (last) of no A on the path, from the
    strip network's output (P, 2, rows, cols) and the path's columns (P, cols) bool."""
    o = logits.float().mean(dim=2)
    a = o[:, 0].masked_fill(~valid, -1e4)
    w = valid.to(o.dtype)
    none = (o[:, 1] * w).sum(dim=1, keepdim=True) / w.sum(dim=1, keepdim=True).clamp_min(1.0)
    return torch.log_softmax(torch.cat([a, none], dim=1), dim=1)


def strip_targets(valid: torch.Tensor, a_col: torch.Tensor, *, sigma_px: float) -> torch.Tensor:
    """Target distributions (P, cols + 1): a Gaussian of σ ``sigma_px`` strip px around A's column
    ``a_col`` (P,) float on the path's columns, or all mass on "no A" where ``a_col`` < 0."""
    cols = valid.shape[1]
    pos = torch.arange(cols, dtype=torch.float32, device=valid.device)
    a = a_col.float()
    t = torch.exp(-0.5 * ((pos[None] - a[:, None]) / sigma_px) ** 2) * valid.float()
    none = a < 0
    t = torch.where(none[:, None], torch.zeros_like(t), t)
    t = torch.cat([t, none.float()[:, None]], dim=1)
    return t / t.sum(dim=1, keepdim=True).clamp_min(1e-12)


def window_probability(probs: np.ndarray, col: float, half_px: int) -> float:
    """P(A within ± ``half_px`` columns of ``col``) from one path's probabilities (cols + 1,)."""
    cols = len(probs) - 1
    k = round(col)
    lo, hi = max(k - half_px, 0), min(k + half_px + 1, cols)
    return float(np.sum(probs[lo:hi])) if lo < hi else 0.0


def v_apex(mask: np.ndarray, a_px: np.ndarray, b_px: np.ndarray) -> tuple[np.ndarray, float] | None:
    """The apex of a V-shaped mask (rows, cols) bool between its ends A and B (2,) (u, v): the mask
    pixel farthest from the segment A–B, moved towards the segment by the mask's largest half-width
    (so that it lies on a tube's axis, not its edge). Returns the apex (2,) and the farthest pixel's
    distance from the segment (px); None for an empty mask."""
    vv, uu = np.nonzero(mask)
    if len(uu) == 0:
        return None
    pts = np.stack([uu, vv], axis=1).astype(np.float64)
    a, b = np.asarray(a_px, dtype=np.float64), np.asarray(b_px, dtype=np.float64)
    ab = b - a
    t = np.clip((pts - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    foot = a + t[:, None] * ab
    d = np.linalg.norm(pts - foot, axis=1)
    k = int(np.argmax(d))
    if d[k] <= 0.0:
        return pts[k], 0.0
    half_width = float(ndimage.distance_transform_edt(mask).max())
    inwards = (foot[k] - pts[k]) / d[k]
    return pts[k] + min(half_width, float(d[k])) * inwards, float(d[k])


@dataclass(frozen=True)
class StripJitter:
    """How training paths are drawn (mm at the detector) and the strips changed.

    Attributes:
        near_a_prob: probability that a path starts within ``near_a_mm`` behind A on the shaft (a
            right A), else anywhere on the shaft's first ``max_back_mm`` inside the image.
        near_a_mm, max_back_mm: see ``near_a_prob``.
        start_sigma_px: σ of the path's start point's jitter (input px).
        end_sigma_mm: σ of the path's end point's jitter around B.
        corner_sigma_mm: σ of the corner's jitter around A on the two-leg paths through A.
        p_mirror: probability of mirroring the strip about the path.
        contrast: range of the factor on the normalised strip.
        max_noise: largest σ of Gaussian noise added to the normalised strip.
    """

    near_a_prob: float = 0.3
    near_a_mm: float = 1.5
    max_back_mm: float = 45.0
    start_sigma_px: float = 0.3
    end_sigma_mm: float = 0.5
    corner_sigma_mm: float = 0.4
    p_mirror: float = 0.5
    contrast: tuple[float, float] = (0.7, 1.3)
    max_noise: float = 0.3


def _polyline_at(pts: np.ndarray, arc: np.ndarray, s: float) -> np.ndarray:
    return np.array([np.interp(s, arc, pts[:, 0]), np.interp(s, arc, pts[:, 1])])


def _unit(rng: np.random.Generator) -> np.ndarray:
    d = rng.normal(size=2)
    return d / max(float(np.linalg.norm(d)), 1e-12)


def training_path(
    centerline_px: np.ndarray,
    rng: np.random.Generator,
    *,
    px_per_mm: float,
    shaft_inside_px: float,
    shaft_direction: np.ndarray | None,
    jitter: StripJitter,
) -> tuple[np.ndarray, str]:
    """A training path (N, 2) (u, v) px and its kind, from the true centreline (M, 2) from A to B and
    the projected mounting shaft (its unit direction (2,) from A away from the CM and the length of
    it inside the image, px; None / 0: no shaft).

    Kinds (each a quarter): ``"true"``, the true path from a point of the shaft (or A) through A to
    B; ``"legs"``, two straight legs from there through A (jittered) to B; ``"wrong"``, two legs
    through a wrong corner (beside the true path by 2–15 mm, or anywhere near the start);
    ``"bend"``, from A (jittered) through a corner on or beside the CM to B. The label (A's column)
    comes from where the path passes A (:func:`a_column`), not from the kind."""
    mm = px_per_mm
    cl = np.asarray(centerline_px, dtype=np.float64)
    a, b = cl[0], cl[-1]
    if shaft_direction is not None and shaft_inside_px > 0.0:
        if rng.random() < jitter.near_a_prob:
            back = rng.uniform(0.0, min(jitter.near_a_mm * mm, shaft_inside_px))
        else:
            back = rng.uniform(0.0, min(jitter.max_back_mm * mm, shaft_inside_px))
        shaft = np.stack([a + back * np.asarray(shaft_direction, dtype=np.float64), a])
        true = np.concatenate([shaft, cl[1:]]) if back > 0.0 else cl
    else:
        back, true = 0.0, cl
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(true, axis=0), axis=1))])
    arc_a = back  # A's arc length along the true path
    start = true[0] + rng.normal(0.0, jitter.start_sigma_px, 2)
    end = b + rng.normal(0.0, jitter.end_sigma_mm * mm, 2)
    kind = ("true", "legs", "wrong", "bend")[int(rng.integers(4))]
    if kind == "true":
        path = true.copy()
        path[0] = start
    elif kind == "legs":
        path = np.stack([start, a + rng.normal(0.0, jitter.corner_sigma_mm * mm, 2), end])
    elif kind == "bend":
        start = a + rng.normal(0.0, jitter.end_sigma_mm * mm, 2)
        lo, hi = arc_a + 4.0 * mm, max(arc[-1] - 4.0 * mm, arc_a + 4.0 * mm + 1e-3)
        corner = _polyline_at(true, arc, rng.uniform(lo, hi)) + _unit(rng) * rng.uniform(0.0, 6.0) * mm
        path = np.stack([start, corner, end])
    else:
        if rng.random() < 0.5:
            corner = _polyline_at(true, arc, rng.uniform(0.0, arc[-1]))
            corner = corner + _unit(rng) * rng.uniform(2.0, 15.0) * mm
        else:
            corner = start + rng.normal(size=2) * 12.0 * mm
        path = np.stack([start, corner, end])
    return path, kind


def a_column(path_px: np.ndarray, a_px: np.ndarray, *, step_px: float, cols: int, tol_px: float) -> int:
    """The strip column of a path (N, 2) nearest to A (2,), or −1 where the path passes A farther
    than ``tol_px`` or within 8 columns of the strip's end."""
    pts = resample_path(path_px, step_px, cols)
    d = np.linalg.norm(pts - np.asarray(a_px, dtype=np.float64), axis=1)
    k = int(np.argmin(d))
    return k if d[k] <= tol_px and k < cols - 8 else -1


def training_strip(
    image: np.ndarray,
    centerline_px: np.ndarray,
    rng: np.random.Generator,
    *,
    step_px: float,
    px_per_mm: float,
    shape: tuple[int, int],
    shaft_inside_px: float,
    shaft_direction: np.ndarray | None,
    jitter: StripJitter,
    photometric: bool,
    tol_mm: float = 1.5,
) -> tuple[np.ndarray, np.ndarray, int] | None:
    """A training strip (rows, cols) float32 along a :func:`training_path`, its path's columns
    (cols,) bool and A's column (−1: A not on the path); None for a path of under 3 px."""
    path, _ = training_path(
        centerline_px,
        rng,
        px_per_mm=px_per_mm,
        shaft_inside_px=shaft_inside_px,
        shaft_direction=shaft_direction,
        jitter=jitter,
    )
    if float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum()) < 3.0:
        return None
    strips, valid = path_strips(image, [path], step_px=step_px, shape=shape)
    strip, ok = strips[0], valid[0]
    if not ok.any():
        return None
    col = a_column(path, centerline_px[0], step_px=step_px, cols=shape[1], tol_px=tol_mm * px_per_mm)
    if rng.random() < jitter.p_mirror:  # mirrored about the path: the same problem
        strip = strip[::-1].copy()
    if photometric:
        strip = photometric_change(strip, rng, contrast=jitter.contrast, max_noise=jitter.max_noise)
    strip = np.where(ok[None, :], strip, 0.0).astype(np.float32)
    return strip, ok, col
