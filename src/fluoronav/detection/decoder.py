"""The decoder: the rules that turn the stages' heatmaps and masks into landmarks and a mask.

View stages (coarse, fine): :func:`decode_views` reads the landmarks from the heatmaps of a batch of
views (:func:`~fluoronav.detection.heatmaps.decode_landmarks`), keeping a landmark on the CM's mask
(:func:`off_support_exclusion`); :func:`mask_at_input` maps the views' mask logits to the input grid
and keeps the CM's components (:func:`cm_components`). Patch stages: :func:`decode_refine_logits`
reads a refinement heatmap with a prior at the fine landmark; :func:`end_zone_paste` and
:func:`tube_paste` put patch masks back on the input grid; :func:`cm_start_index` finds where the
CM begins along the centreline. :func:`truncated_landmarks` and :func:`distances_to_mask` tell
whether a landmark is the CM's (not where the image border cuts it, not off its mask).
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
from scipy import ndimage as ndi

from fluoronav.detection.heatmaps import decode_landmarks, decode_logit_heatmaps
from fluoronav.detection.patches import RefinePatch, bilinear, footprint
from fluoronav.detection.views import View, paste

__all__ = [
    "OUTSIDE_LOGIT",
    "add_center_prior",
    "along_centerline",
    "cm_components",
    "cm_start_index",
    "component_at",
    "core_logits",
    "decode_refine_logits",
    "decode_views",
    "distances_to_mask",
    "end_zone_paste",
    "mask_at_input",
    "off_support_exclusion",
    "reaches_edge",
    "truncated_landmarks",
    "tube_paste",
]

#: logit given to input pixels outside a fine view when the views' logits are averaged
OUTSIDE_LOGIT = -20.0


def decode_views(
    outputs: torch.Tensor,
    *,
    heatmap: str,
    sigma_px: float,
    threshold_logit: float,
    min_separation_px: float = 0.0,
    support_px: float = 0.0,
    exclude: torch.Tensor | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A view stage's outputs (N, 3, S, S) → seg logits (N, S, S), landmarks (N, 2, 2) view px
    (float64) and confidences (N, 2).

    ``heatmap``, ``sigma_px``: see :func:`~fluoronav.detection.heatmaps.decode_landmarks`;
    ``min_separation_px``: see :func:`~fluoronav.detection.heatmaps.separation_exclusion`;
    ``support_px`` (> 0) with ``threshold_logit``: see :func:`off_support_exclusion`; ``exclude``:
    (N, 2, S, S) bool heatmap pixels that may not be a landmark besides.
    """
    out = outputs
    if exclude is not None:
        exclude = exclude.to(out.device)
    if support_px > 0.0:
        off = off_support_exclusion(
            out[:, 0], out[:, 1:], threshold_logit=threshold_logit, support_px=support_px
        )
        exclude = off if exclude is None else exclude | off
    pts, conf = decode_landmarks(
        out[:, 1:],
        mode=heatmap,
        sigma_px=sigma_px,
        min_separation_px=min_separation_px,
        exclude=exclude,
    )
    return out[:, 0].cpu().numpy(), pts.cpu().numpy().astype(np.float64), conf.cpu().numpy()


def off_support_exclusion(
    seg_logits: torch.Tensor, heatmaps: torch.Tensor, *, threshold_logit: float, support_px: float
) -> torch.Tensor:
    """Heatmap pixels a landmark may not take where its map peaks away from the CM's mask.

    A and B lie on the CM. The CM's region is the largest connected component of the view's
    thresholded mask grown by ``support_px``: pieces of one tube less than 2 · ``support_px`` apart
    (a thin part of the mask broken by noise) are one region, a blob farther away (noise, a bone
    edge) is not. A map whose argmax lies outside that region has every pixel outside it
    excluded, so the landmark is taken at its best peak on the CM, unless the other landmark lies in
    the region and the region runs towards this one (the median of its pixels' positions along the
    segment from the other landmark to this one is ≥ 0): then this is the far end of a tube the mask
    has cut in two, and it stays. Maps that peak in the region are left alone (no exclusion).

    Args:
        seg_logits: (N, S, S) segmentation logits.
        heatmaps: (N, K, S, S) landmark maps (only their argmax is read).
        threshold_logit: mask threshold on the logits.
        support_px: growth of the mask, view pixels (> 0).

    Returns:
        (N, K, S, S) bool, all False for a view without a mask.
    """
    n, k, _, cols = heatmaps.shape
    exclude = torch.zeros(heatmaps.shape, dtype=torch.bool)
    masks = (seg_logits > threshold_logit).cpu().numpy()
    idx = heatmaps.reshape(n, k, -1).argmax(dim=-1).cpu().numpy()
    for i in range(n):
        if not masks[i].any():
            continue
        grown = ndi.distance_transform_edt(~masks[i]) <= support_px
        _, labels, stats, _ = cv2.connectedComponentsWithStats(grown.astype(np.uint8), connectivity=8)
        largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        far = labels != largest
        off = far.reshape(-1)[idx[i]]  # (K,) maps peaking off the CM
        if k == 2 and off.sum() == 1:
            j = int(np.argmin(off))  # the landmark on the CM
            pj = np.array([idx[i, j] % cols, idx[i, j] // cols], dtype=np.float64)
            pk = np.array([idx[i, 1 - j] % cols, idx[i, 1 - j] // cols], dtype=np.float64)
            vv, uu = np.nonzero(~far)
            t = (np.stack([uu, vv], axis=1) - pj) @ (pk - pj)
            if float(np.median(t)) >= 0.0:
                off[:] = False
        if off.any():
            exclude[i, torch.from_numpy(off)] = torch.from_numpy(far)
    return exclude.to(heatmaps.device)


def component_at(mask: np.ndarray, seeds_uv: np.ndarray) -> np.ndarray:
    """The connected components of ``mask`` within 2 px of any seed (N, 2) (u, v); the largest if none."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:
        return mask.astype(bool)
    keep: set[int] = set()
    rows, cols = mask.shape
    for u, v in np.asarray(seeds_uv, dtype=np.float64).reshape(-1, 2):
        r0, r1 = int(max(round(v) - 2, 0)), int(min(round(v) + 3, rows))
        c0, c1 = int(max(round(u) - 2, 0)), int(min(round(u) + 3, cols))
        keep.update(int(x) for x in np.unique(labels[r0:r1, c0:c1]) if x > 0)
    if not keep:
        return labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return np.isin(labels, sorted(keep))


def cm_components(mask: np.ndarray, landmarks_px: np.ndarray, *, join_frac: float) -> np.ndarray:
    """The CM's part of a thresholded mask (rows, cols): its largest connected component and, with
    ``join_frac`` > 0, every other component that comes within max(3, ``join_frac`` · |AB|) pixels of
    the segment between the landmarks (2, 2) (u, v).

    Noise or a crossing bone can cut the mask of one tube into pieces; the pieces between its two
    ends belong to it, a blob elsewhere does not. The margin covers the bend of the CM away from the
    chord A–B (≲ 0.09 · |AB| at the sampled curvatures) and the tube's radius in end-on views.
    """
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:
        return mask.astype(bool)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    if join_frac <= 0.0:
        return labels == largest
    a, b = np.asarray(landmarks_px, dtype=np.float64).reshape(2, 2)
    ab = b - a
    margin = max(3.0, join_frac * float(np.hypot(*ab)))
    vv, uu = np.nonzero(labels)
    p = np.stack([uu, vv], axis=1).astype(np.float64)
    t = np.clip((p - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    near = np.hypot(*(p - (a + t[:, None] * ab)).T) <= margin
    keep = {largest, *np.unique(labels[vv[near], uu[near]]).tolist()}
    return np.isin(labels, sorted(keep))


def mask_at_input(
    logits: np.ndarray,
    views: list[View],
    shape: tuple[int, int],
    thr_logit: float,
    landmarks_px: np.ndarray,
    *,
    join_frac: float = 0.0,
) -> np.ndarray:
    """Threshold the mean of the views' logits (N, R, R) bilinearly mapped to the input grid; keep
    the largest component and, with ``join_frac`` > 0, the fragments along the landmarks (2, 2)
    (:func:`cm_components`). Outside a view its logits count as certain background."""
    rows, cols = shape
    out = np.zeros(shape, dtype=bool)
    # the union of the views, clipped to the image: the only place the mask can be
    cx0, cy0 = max(min(v.x0 for v in views), 0), max(min(v.y0 for v in views), 0)
    cx1 = min(max(v.x0 + v.side for v in views), cols)
    cy1 = min(max(v.y0 + v.side for v in views), rows)
    if cx1 <= cx0 or cy1 <= cy0:
        return out
    acc = np.zeros((cy1 - cy0, cx1 - cx0), np.float32)
    for logit, v in zip(logits, views, strict=True):
        acc += paste(logit, v, (rows, cols), fill=OUTSIDE_LOGIT, box=(cx0, cy0, cx1, cy1))
    sub = acc / len(views) > thr_logit
    if sub.any():
        local = np.asarray(landmarks_px, dtype=np.float64) - np.array([cx0, cy0], dtype=np.float64)
        out[cy0:cy1, cx0:cx1] = cm_components(sub, local, join_frac=join_frac)
    return out


def reaches_edge(view_mask: np.ndarray, view: View, shape: tuple[int, int], *, ring_px: int = 2) -> bool:
    """Whether a mask (S, S) in ``view`` pixels has pixels in the view's outer ring of ``ring_px``
    view pixels that lie inside the image ``shape`` (rows, cols) (not counting the image's own edge)."""
    ring = view_mask.copy()
    ring[ring_px:-ring_px, ring_px:-ring_px] = False
    vv, uu = np.nonzero(ring)
    if vv.size == 0:
        return False
    uv = view.to_input(np.stack([uu, vv], axis=1).astype(np.float64))
    rows, cols = shape
    inside = (uv[:, 0] >= 1.0) & (uv[:, 0] <= cols - 2.0) & (uv[:, 1] >= 1.0) & (uv[:, 1] <= rows - 2.0)
    return bool(inside.any())


def distances_to_mask(mask: np.ndarray, points_px: np.ndarray) -> np.ndarray:
    """(N,) distances (px) from points (N, 2) (u, v) to the nearest pixel of a mask (inf for an
    empty mask); the mask's pixels are listed once for all the points."""
    vv, uu = np.nonzero(mask)
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    if vv.size == 0:
        return np.full(len(pts), np.inf)
    pixels = np.stack([uu, vv], axis=1).astype(np.float64)
    return np.sqrt(((pixels[None] - pts[:, None]) ** 2).sum(axis=-1)).min(axis=1)


def truncated_landmarks(
    mask: np.ndarray, landmarks_px: np.ndarray, *, edge_px: float = 3.0, reach_px: float = 10.0
) -> np.ndarray:
    """Which landmarks (2, 2) (u, v) sit where a mask (rows, cols) is cut by the image border → (2,) bool.

    A landmark counts as truncated when it lies within ``edge_px`` of a border and the mask has pixels
    on that border within ``reach_px`` of it: the CM leaves the field there, and the detector, which
    only sees the image, puts the landmark at the cut.
    """
    rows, cols = mask.shape
    out = np.zeros(2, dtype=bool)
    for k, (u, v) in enumerate(np.asarray(landmarks_px, dtype=np.float64).reshape(2, 2)):
        # (distance to the border, the mask's border line, the landmark's position along it)
        borders = (
            (u, mask[:, 0], v),
            (cols - 1 - u, mask[:, -1], v),
            (v, mask[0, :], u),
            (rows - 1 - v, mask[-1, :], u),
        )
        for dist, line, along in borders:
            if dist > edge_px:
                continue
            idx = np.flatnonzero(line)
            if idx.size and float(np.min(np.abs(idx - along))) <= reach_px:
                out[k] = True
    return out


def add_center_prior(
    log_probs: torch.Tensor, *, sigma_px: float, center_px: torch.Tensor | None = None
) -> torch.Tensor:
    """(N, K, rows, cols) log-probabilities + log of an isotropic Gaussian of σ = ``sigma_px`` patch
    pixels (0: unchanged) at ``center_px`` (N, 2) (col, row) patch pixels, one per patch (None: the
    patch centre)."""
    if sigma_px <= 0:
        return log_probs
    rows, cols = log_probs.shape[-2:]
    dtype, device = log_probs.dtype, log_probs.device
    if center_px is None:
        center = torch.tensor([[(cols - 1) / 2.0, (rows - 1) / 2.0]], dtype=dtype, device=device)
    else:
        center = torch.as_tensor(center_px, dtype=dtype, device=device).reshape(-1, 2)
    v = torch.arange(rows, dtype=dtype, device=device)[None, :] - center[:, 1:]  # (N|1, rows)
    u = torch.arange(cols, dtype=dtype, device=device)[None, :] - center[:, :1]  # (N|1, cols)
    r2 = v[:, :, None] ** 2 + u[:, None, :] ** 2  # (N|1, rows, cols)
    return log_probs - r2[:, None] / (2.0 * sigma_px**2)


def decode_refine_logits(
    logits: torch.Tensor,
    *,
    sigma_px: float,
    prior_px: float,
    prior_center_px: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 1, rows, cols) refinement logits → sub-pixel peaks (N, 2) (col, row) and confidences (N,),
    after the prior (:func:`add_center_prior`; ``prior_center_px`` (N, 2), None: the patch centre)."""
    logp = torch.log_softmax(logits.flatten(-2).float(), dim=-1).reshape(logits.shape)
    prior = add_center_prior(logp, sigma_px=prior_px, center_px=prior_center_px)
    pts, conf = decode_logit_heatmaps(prior, sigma_px=sigma_px)
    return pts[:, 0], conf[:, 0]


def end_zone_paste(
    mask: np.ndarray, frame: RefinePatch, logits: np.ndarray, *, inner_px: float
) -> np.ndarray:
    """``mask`` (rows, cols) bool with its pixels in ``frame``'s outer part replaced by the patch
    segmentation ``logits`` (patch rows, patch cols; > 0: CM), read bilinearly at each input pixel's
    centre. The outer part: the patch pixels from ``inner_px`` patch pixels inside the landmark (the
    patch centre, towards the CM) outwards, across the whole patch."""
    rows, cols = frame.shape
    last = (cols - 1) / 2.0 + inner_px
    box = footprint(frame, mask.shape, (0.0, last))
    if box is None:
        return mask
    (u0, v0, u1, v1), k, j = box
    zone = (k >= 0) & (k <= last) & (j >= 0) & (j <= rows - 1)
    out = np.array(mask, dtype=bool, copy=True)
    out[v0:v1, u0:u1][zone] = bilinear(logits, k, j)[zone] > 0.0
    return out


def tube_paste(
    mask: np.ndarray, frames: list[RefinePatch], logits: np.ndarray, *, band_px: float
) -> np.ndarray:
    """``mask`` (rows, cols) bool where the patches' segmentations ``logits`` (P, patch rows, patch
    cols; > 0: CM) cover it replaced by their mean logit (> 0: CM), each patch covering the band of
    its pixels within ``band_px`` patch px of its centre along the tube, across the whole patch."""
    boxes = [
        footprint(f, mask.shape, ((f.shape[1] - 1) / 2.0 - band_px, (f.shape[1] - 1) / 2.0 + band_px))
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
        total[v0 - wv0 : v1 - wv0, u0 - wu0 : u1 - wu0][band] += bilinear(logit, k, j)[band]
        count[v0 - wv0 : v1 - wv0, u0 - wu0 : u1 - wu0][band] += 1.0
    covered = count > 0
    out = np.array(mask, dtype=bool, copy=True)
    out[wv0:wv1, wu0:wu1][covered] = total[covered] > 0.0
    return out


def core_logits(logits: np.ndarray, *, band_px: float, core_px: float = 8.0) -> np.ndarray:
    """(P,) mean logit of each tube-aligned patch's core: the pixels (P, rows, cols) within
    ``band_px`` patch px of its centre along the tube (cols) and ``core_px`` of its axis (rows)."""
    _, rows, cols = logits.shape
    along = np.abs(np.arange(cols) - (cols - 1) / 2.0) <= band_px
    across = np.abs(np.arange(rows) - (rows - 1) / 2.0) <= core_px
    return logits[:, across][:, :, along].mean(axis=(1, 2))


def along_centerline(centerline_px: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether each point of a centreline (N, 2) (u, v) px lies in ``mask`` (rows, cols) bool (nearest
    pixel; points outside the image count as outside), (N,) bool, and its arc length (N,) px."""
    line = np.asarray(centerline_px, dtype=np.float64).reshape(-1, 2)
    h, w = mask.shape
    iu, iv = np.rint(line[:, 0]).astype(int), np.rint(line[:, 1]).astype(int)
    ok = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
    inside = np.zeros(len(line), bool)
    inside[ok] = mask[iv[ok], iu[ok]]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    return inside, arc[: len(line)]


def cm_start_index(centerline_px: np.ndarray, mask: np.ndarray, *, run_px: float) -> int | None:
    """Index of the first point of a centreline (N, 2) (u, v) px from which it runs ``run_px`` px of
    arc length or more wholly inside ``mask`` (rows, cols) bool (:func:`along_centerline`); None
    where it never does."""
    inside, arc = along_centerline(centerline_px, mask)
    run_start: int | None = None
    for i, good in enumerate(inside):
        if not good:
            run_start = None
            continue
        run_start = i if run_start is None else run_start
        if arc[i] - arc[run_start] >= run_px:
            return run_start
    return None
