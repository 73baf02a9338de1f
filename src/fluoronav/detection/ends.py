"""The mask's ends on tube-aligned patches: the detector's fourth stage.

The label mask is the projection of the CM's envelope between the planes of A and B, so each of its
ends is half the ellipse that the tube's cross-section at that landmark projects to: it bulges beyond
the landmark by up to the tube's radius, by R·sin φ where φ is the tube's angle out of the image
plane. The fine stage places these ends from a 128² view of the whole CM, one stored pixel per ROI
pixel, and on validation 60 % of its typical mask error (Dice 0.965) lies within 14 px of A or B.
With the true bulge drawn at the refined landmarks the typical Dice would be 0.975.

This stage resamples a patch around each refined landmark, aligned with the tube (as the refinement
stage's, :class:`~fluoronav.detection.refine.RefinePatch`, at the same scale), and a small U-Net
segments the CM's envelope in it: where the tube is cut at the landmark and how far the cut bulges.
Its mask replaces the fine stage's in the patch's outer part (from ``inner_px`` patch pixels inside
the landmark outwards), where the fine stage was least sure.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from fluoronav.detection.refine import RefinePatch, moved_frame, photometric_change, refine_patch

__all__ = [
    "EndJitter",
    "end_zone_paste",
    "inside_length_px",
    "patch_grid_px",
    "sample_patches",
    "training_end_patch",
    "training_tube_patch",
    "tube_frames",
    "tube_paste",
]


def patch_grid_px(frame: RefinePatch) -> np.ndarray:
    """(rows, cols, 2) (u, v) input pixels of every patch pixel of ``frame`` (as
    :meth:`RefinePatch.to_input`, computed separably)."""
    rows, cols = frame.shape
    k = (np.arange(cols, dtype=np.float64) - (cols - 1) / 2.0) * frame.step_px
    j = (np.arange(rows, dtype=np.float64) - (rows - 1) / 2.0) * frame.step_px
    t, n = frame.tangent, frame.normal
    u = frame.center_px[0] + k[None, :] * t[0] + j[:, None] * n[0]
    v = frame.center_px[1] + k[None, :] * t[1] + j[:, None] * n[1]
    return np.stack([u, v], axis=-1)


def _bilinear(values: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear values of a 2-D array at (u = column, v = row) coordinates of any 2-D shape, edges
    repeated. ``cv2.remap``: ten times faster than ``ndimage.map_coordinates`` here, its weights
    fixed-point in 1/32 pixel."""
    return cv2.remap(
        np.asarray(values, dtype=np.float32),
        np.asarray(u, dtype=np.float32),
        np.asarray(v, dtype=np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )


def sample_patches(image: np.ndarray, frames: list[RefinePatch]) -> np.ndarray:
    """(P, rows, cols) float32 patches of ``image`` on ``frames`` of one shape, each as
    :meth:`RefinePatch.sample` gives it (bilinear, edges repeated, zero mean and unit s.d.; here
    with :func:`_bilinear`'s 1/32-pixel weights)."""
    img = np.asarray(image, dtype=np.float32)
    v = np.stack([_bilinear(img, uv[..., 0], uv[..., 1]) for uv in map(patch_grid_px, frames)])
    mean = v.mean(axis=(1, 2), keepdims=True)
    return ((v - mean) / (v.std(axis=(1, 2), keepdims=True) + 1e-6)).astype(np.float32)


@dataclass(frozen=True)
class EndJitter:
    """How far training patches start from the true landmark (patch pixels, degrees): the refined
    landmark's error (on validation a median of 0.3 input px, 0.6 patch px) and the direction's.

    Attributes:
        along_sigma_px: σ of the Gaussian shift along the tube.
        across_sigma_px: σ of the Gaussian shift across the tube.
        angle_sigma_deg: σ of the rotation of the patch's tangent.
        p_mirror: probability of mirroring the patch about the tube's axis.
        contrast: range of the factor on the normalised patch.
        max_noise: largest σ of Gaussian noise added to the normalised patch (uniform in [0, this]).
    """

    along_sigma_px: float = 1.0
    across_sigma_px: float = 0.6
    angle_sigma_deg: float = 5.0
    p_mirror: float = 0.5
    contrast: tuple[float, float] = (0.7, 1.3)
    max_noise: float = 0.25


def training_end_patch(
    image: np.ndarray,
    mask: np.ndarray,
    landmark_px: np.ndarray,
    rng: np.random.Generator,
    *,
    step_px: float,
    shape: tuple[int, int],
    jitter: EndJitter,
    photometric: bool,
) -> tuple[np.ndarray, np.ndarray] | None:
    """A jittered training patch (rows, cols) float32 around a true landmark and the true mask on its
    pixels (rows, cols) float32 0/1 (the label of the input pixel each patch pixel falls in); None
    where the true mask gives no direction."""
    frame = refine_patch(mask, landmark_px, step_px=step_px, shape=shape)
    if frame is None:
        return None
    angle = rng.normal(0.0, jitter.angle_sigma_deg)
    along, across = rng.normal(0.0, jitter.along_sigma_px), rng.normal(0.0, jitter.across_sigma_px)
    frame = moved_frame(frame, landmark_px, angle_deg=angle, along_px=along, across_px=across)
    return _patch_and_label(image, mask, frame, rng, jitter=jitter, photometric=photometric)


def _patch_and_label(
    image: np.ndarray,
    mask: np.ndarray,
    frame: RefinePatch,
    rng: np.random.Generator,
    *,
    jitter: EndJitter,
    photometric: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """``frame``'s patch of ``image`` and the label of ``mask`` on it (float32 0/1), mirrored about
    the tube's axis with probability ``p_mirror``, with photometric changes where asked."""
    uv = patch_grid_px(frame)
    # nearest input pixel: the label is defined per input pixel (its centre inside the envelope)
    target = ndimage.map_coordinates(
        np.asarray(mask, dtype=np.float32), [uv[..., 1], uv[..., 0]], order=0, mode="constant"
    )
    patch = frame.sample(image)
    if rng.random() < jitter.p_mirror:  # exact mirror about the axis: rows j ↔ rows − 1 − j
        patch, target = patch[::-1].copy(), target[::-1].copy()
    if photometric:
        patch = photometric_change(patch, rng, contrast=jitter.contrast, max_noise=jitter.max_noise)
    return patch.astype(np.float32), target.astype(np.float32)


def _footprint(
    frame: RefinePatch, shape: tuple[int, int], cols: tuple[float, float] | None = None
) -> tuple[tuple[int, int, int, int], np.ndarray, np.ndarray] | None:
    """The input pixel box (u0, v0, u1, v1) that ``frame`` covers in an image of ``shape`` (only its
    patch columns ``cols`` = (first, last), None: all) and the patch coordinates (col k, row j) of
    each of its pixels; None where it covers none."""
    rows, n_cols = frame.shape
    k0, k1 = (0.0, n_cols - 1.0) if cols is None else (max(cols[0], 0.0), min(cols[1], n_cols - 1.0))
    last_row = rows - 1.0
    corners = frame.to_input(np.array([[k0, 0.0], [k1, 0.0], [k0, last_row], [k1, last_row]]))
    h, w = shape
    u0, v0 = np.maximum(np.floor(corners.min(axis=0)).astype(int), 0)
    u1, v1 = np.minimum(np.ceil(corners.max(axis=0)).astype(int) + 1, [w, h])
    if u1 <= u0 or v1 <= v0:
        return None
    # (col k, row j) = ((p − c)·t, (p − c)·n) / step + origin, separably in u and v
    du = (np.arange(u0, u1, dtype=np.float64) - frame.center_px[0]) / frame.step_px
    dv = (np.arange(v0, v1, dtype=np.float64) - frame.center_px[1]) / frame.step_px
    t, n = frame.tangent, frame.normal
    k = du[None, :] * t[0] + dv[:, None] * t[1] + (n_cols - 1) / 2.0
    j = du[None, :] * n[0] + dv[:, None] * n[1] + (rows - 1) / 2.0
    return (int(u0), int(v0), int(u1), int(v1)), k, j


def end_zone_paste(
    mask: np.ndarray, frame: RefinePatch, logits: np.ndarray, *, inner_px: float
) -> np.ndarray:
    """``mask`` (rows, cols) bool with its pixels in ``frame``'s outer part replaced by the patch
    segmentation ``logits`` (patch rows, patch cols; > 0: CM), read bilinearly at each input pixel's
    centre. The outer part: the patch pixels from ``inner_px`` patch pixels inside the landmark (the
    patch centre, towards the CM) outwards, across the whole patch."""
    rows, cols = frame.shape
    last = (cols - 1) / 2.0 + inner_px
    box = _footprint(frame, mask.shape, (0.0, last))
    if box is None:
        return mask
    (u0, v0, u1, v1), k, j = box
    zone = (k >= 0) & (k <= last) & (j >= 0) & (j <= rows - 1)
    out = np.array(mask, dtype=bool, copy=True)
    out[v0:v1, u0:u1][zone] = _bilinear(logits, k, j)[zone] > 0.0
    return out


def _polyline_frame(points: np.ndarray, arc_px: float, *, chord_px: float) -> tuple[np.ndarray, np.ndarray]:
    """The point at arc length ``arc_px`` along a polyline (N, 2) and the unit tangent there (from A
    towards B), from the chord over ± ``chord_px`` of arc length."""
    pts = np.asarray(points, dtype=np.float64)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])

    def at(x: float) -> np.ndarray:
        x = float(np.clip(x, 0.0, s[-1]))
        return np.array([np.interp(x, s, pts[:, 0]), np.interp(x, s, pts[:, 1])])

    d = at(arc_px + chord_px) - at(arc_px - chord_px)
    return at(arc_px), d / max(float(np.linalg.norm(d)), 1e-9)


def tube_frames(
    centerline_px: np.ndarray, *, step_px: float, shape: tuple[int, int], spacing_px: float
) -> list[RefinePatch]:
    """Tube-aligned patch frames (as :class:`~fluoronav.detection.refine.RefinePatch`, tangent from A
    towards B) centred every ``spacing_px`` input px of arc length along a centreline (N, 2) (u, v),
    from its start to its end (both included); none where it has no length."""
    pts = np.asarray(centerline_px, dtype=np.float64)
    length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()) if len(pts) > 1 else 0.0
    if length <= 0.0:
        return []
    n = max(int(np.ceil(length / spacing_px)), 1)
    chord = 0.25 * shape[1] * step_px  # a quarter of the patch's length either side
    frames = []
    for arc in np.linspace(0.0, length, n + 1):
        c, t = _polyline_frame(pts, arc, chord_px=chord)
        frames.append(RefinePatch(c, t, float(step_px), shape))
    return frames


def training_tube_patch(
    image: np.ndarray,
    mask: np.ndarray,
    centerline_px: np.ndarray,
    rng: np.random.Generator,
    *,
    step_px: float,
    shape: tuple[int, int],
    jitter: EndJitter,
    photometric: bool,
    shaft_px: np.ndarray | None = None,
    shaft_prob: float = 0.0,
) -> tuple[np.ndarray, np.ndarray] | None:
    """A training patch (rows, cols) float32 centred at a uniformly drawn point of the true
    centreline (N, 2), aligned with it (tangent jittered by ``angle_sigma_deg``, centre moved across
    by ``across_sigma_px`` patch px), and the true mask on its pixels (rows, cols) float32 0/1; None
    where the centreline has no length.

    With probability ``shaft_prob`` the point is drawn instead on the part inside the image of the
    projected mounting shaft ``shaft_px`` (2, 2) (A, then the shaft's far end; u, v), the patch
    aligned with the shaft: the true mask there is the CM's only, so the stage learns that a plain
    tube beyond A is not the CM (the fine stage sometimes takes a short shaft for part of it)."""
    pts = np.asarray(centerline_px, dtype=np.float64)
    length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()) if len(pts) > 1 else 0.0
    if length <= 0.0:
        return None
    chord = 0.25 * shape[1] * step_px
    inside = inside_length_px(shaft_px, image.shape) if shaft_px is not None and shaft_prob > 0.0 else 0.0
    if inside > 0.0 and rng.random() < shaft_prob:
        assert shaft_px is not None
        a, far = np.asarray(shaft_px, dtype=np.float64)
        direction = (far - a) / np.linalg.norm(far - a)
        c, t = a + rng.uniform(0.0, inside) * direction, -direction
    else:
        c, t = _polyline_frame(pts, rng.uniform(0.0, length), chord_px=chord)
    angle = rng.normal(0.0, jitter.angle_sigma_deg)
    if rng.random() < 0.5:  # either direction along the tube
        t = -t
    frame = moved_frame(
        RefinePatch(c, t, float(step_px), shape),
        c,
        angle_deg=angle,
        along_px=0.0,
        across_px=rng.normal(0.0, jitter.across_sigma_px),
    )
    return _patch_and_label(image, mask, frame, rng, jitter=jitter, photometric=photometric)


def inside_length_px(segment_px: np.ndarray, shape: tuple[int, ...]) -> float:
    """Length (px) of the part of a segment (2, 2) (u, v) from its first point that stays inside an
    image of ``shape`` (rows, cols); 0 where the first point is outside or the segment has no length."""
    a, b = np.asarray(segment_px, dtype=np.float64)
    length = float(np.linalg.norm(b - a))
    h, w = shape[:2]
    if length <= 0.0 or not (0.0 <= a[0] <= w - 1 and 0.0 <= a[1] <= h - 1):
        return 0.0
    d = (b - a) / length
    t_max = length
    for k, size in ((0, w), (1, h)):
        if d[k] > 0.0:
            t_max = min(t_max, (size - 1 - a[k]) / d[k])
        elif d[k] < 0.0:
            t_max = min(t_max, -a[k] / d[k])
    return max(t_max, 0.0)


def tube_paste(
    mask: np.ndarray, frames: list[RefinePatch], logits: np.ndarray, *, band_px: float
) -> np.ndarray:
    """``mask`` (rows, cols) bool where the patches' segmentations ``logits`` (P, patch rows, patch
    cols; > 0: CM) cover it replaced by their mean logit (> 0: CM), each patch covering the band of
    its pixels within ``band_px`` patch px of its centre along the tube, across the whole patch."""
    boxes = [
        _footprint(f, mask.shape, ((f.shape[1] - 1) / 2.0 - band_px, (f.shape[1] - 1) / 2.0 + band_px))
        for f in frames
    ]
    found = [b for b in boxes if b is not None]
    if not found:
        return mask
    # accumulate over the patches' common window only: a full-size 1536² image is 2.4 M pixels
    wu0, wv0 = min(b[0][0] for b in found), min(b[0][1] for b in found)
    wu1, wv1 = max(b[0][2] for b in found), max(b[0][3] for b in found)
    total = np.zeros((wv1 - wv0, wu1 - wu0), np.float32)
    count = np.zeros_like(total)
    for frame, logit, box in zip(frames, logits, boxes, strict=True):
        if box is None:
            continue
        rows, cols = frame.shape
        (u0, v0, u1, v1), k, j = box
        band = (np.abs(k - (cols - 1) / 2.0) <= band_px) & (j >= 0) & (j <= rows - 1)
        total[v0 - wv0 : v1 - wv0, u0 - wu0 : u1 - wu0][band] += _bilinear(logit, k, j)[band]
        count[v0 - wv0 : v1 - wv0, u0 - wu0 : u1 - wu0][band] += 1.0
    covered = count > 0
    out = np.array(mask, dtype=bool, copy=True)
    out[wv0:wv1, wu0:wu1][covered] = total[covered] > 0.0
    return out
