"""2D centreline of the CM from its segmentation mask and two landmarks (Gao et al., IEEE TBME 69(1),
2022, sec. II-C).

The mask is dilated (closing small gaps and making landmarks on its border reachable), the distance of
every pixel from the region's edge is computed, and the cheapest 8-connected path from landmark A to
landmark B is found with a cost that falls with the distance from the edge, so the path runs along the
medial axis. The pixel path is smoothed along its length, each point is moved to the middle of the mask's
cross-section normal to the path (sub-pixel, from the 0.5 crossings of the interpolated mask), and
the result is resampled uniformly by arc length.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np
from scipy import ndimage
from skimage.graph import route_through_array

logger = logging.getLogger(__name__)


def resample_polyline(points: np.ndarray, n_points: int) -> np.ndarray:
    """Resample a polyline (N, 2) to ``n_points`` points equally spaced by arc length."""
    pts = np.asarray(points, dtype=np.float64)
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0.0:
        return np.repeat(pts[:1], n_points, axis=0)
    keep = np.concatenate([[True], seg > 0])
    s, pts = s[keep], pts[keep]
    t = np.linspace(0.0, s[-1], n_points)
    return np.stack([np.interp(t, s, pts[:, 0]), np.interp(t, s, pts[:, 1])], axis=1)


def end_direction(points: np.ndarray, fraction: float, *, at_start: bool) -> np.ndarray:
    """Unit (u, v) direction out of a polyline (N, 2) at its start (backwards from the first point)
    or its end, from the chord over ``fraction`` of its points (at least one step).

    Raises:
        ValueError: that chord has no length.
    """
    pts = np.asarray(points, dtype=np.float64)
    k = max(1, round(fraction * (len(pts) - 1)))
    d = pts[0] - pts[k] if at_start else pts[-1] - pts[-1 - k]
    nd = float(np.linalg.norm(d))
    if nd <= 0.0:
        raise ValueError("the centreline has no length at its " + ("start" if at_start else "end"))
    return d / nd


def extract_centerline(
    mask: np.ndarray,
    landmark_a_px: np.ndarray,
    landmark_b_px: np.ndarray,
    *,
    n_points: int = 100,
    dilation_px: int = 2,
    smooth_px: float = 2.0,
    cost_power: float = 3.0,
    path_grid_px: int = 160,
) -> np.ndarray:
    """Ordered centreline from landmark A to landmark B through a binary mask.

    Args:
        mask: (rows, cols) bool/0-1 segmentation of the CM.
        landmark_a_px: (2,) landmark A (u, v) in pixels; the polyline starts exactly here.
        landmark_b_px: (2,) landmark B (u, v) in pixels; the polyline ends exactly here.
        n_points: number of output points, equally spaced by arc length.
        dilation_px: radius of the dilation applied to the mask before the distance map.
        smooth_px: standard deviation (pixels of arc length) of the smoothing along the path.
        cost_power: step cost is 1 / (1 + distance-from-edge)^cost_power inside the region.
        path_grid_px: the path search runs on the region max-pooled to about this many pixels per side
            (the sub-pixel centring always uses the full-resolution mask).

    Returns:
        (n_points, 2) float64 (u, v) in the mask's pixels, ordered A → B.
    """
    m = np.asarray(mask).astype(bool)
    if m.ndim != 2:
        raise ValueError(f"mask must be 2-D, got shape {m.shape}")
    a = np.asarray(landmark_a_px, dtype=np.float64).reshape(2)
    b = np.asarray(landmark_b_px, dtype=np.float64).reshape(2)
    rows, cols = m.shape
    # work on the bounding box of the mask and the landmarks only
    pad = dilation_px + 3
    pts = [a, b]
    if m.any():
        x, y, w, h = cv2.boundingRect(m.view(np.uint8))
        pts += [np.array([x, y]), np.array([x + w - 1, y + h - 1])]
    stack = np.stack(pts)
    u0 = int(max(np.floor(stack[:, 0].min()) - pad, 0))
    v0 = int(max(np.floor(stack[:, 1].min()) - pad, 0))
    u1 = int(min(np.ceil(stack[:, 0].max()) + pad + 1, cols))
    v1 = int(min(np.ceil(stack[:, 1].max()) + pad + 1, rows))
    sub: np.ndarray = m[v0:v1, u0:u1].astype(np.uint8)
    if dilation_px > 0:
        k = 2 * dilation_px + 1
        sub = cv2.dilate(sub, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    path_uv, radius_px = _grid_path(sub, a, b, u0, v0, path_grid_px, cost_power)
    path_uv = _centred_path(m[v0:v1, u0:u1], path_uv, a, b, u0, v0, radius_px, smooth_px)
    return resample_polyline(path_uv, n_points)


def _grid_path(
    sub: np.ndarray, a: np.ndarray, b: np.ndarray, u0: int, v0: int, path_grid_px: int, cost_power: float
) -> tuple[np.ndarray, float]:
    """The cheapest path from A to B through the cropped (dilated) mask ``sub`` whose corner is pixel
    (u0, v0): ``(path (N, 2) (u, v) input pixels from A to B, tube radius + dilation in input pixels)``."""
    # the path only has to lie inside the tube: search it on a grid of at most ~path_grid_px per
    # side (max-pooled region); the centring works on the full-resolution mask
    f = max(1, int(np.ceil(max(sub.shape) / path_grid_px)))
    if f > 1:
        h, w = sub.shape
        pooled = np.zeros((-(-h // f) * f, -(-w // f) * f), np.uint8)
        pooled[:h, :w] = sub
        sub = pooled.reshape(pooled.shape[0] // f, f, pooled.shape[1] // f, f).max(axis=(1, 3))
    region = sub.astype(bool)
    dist = ndimage.distance_transform_edt(region)  # distance from the region's edge (grid pixels)
    cost = np.where(region, 1.0 / (1.0 + dist) ** cost_power, 1e3)  # finite outside: a path always exists
    radius_px = max(float(dist.max()) * f, 2.0)  # tube radius + dilation, input pixels

    def cell(p: np.ndarray) -> tuple[int, int]:
        q = (p - np.array([u0, v0]) + 0.5) / f - 0.5
        r = int(np.clip(np.round(q[1]), 0, region.shape[0] - 1))
        c = int(np.clip(np.round(q[0]), 0, region.shape[1] - 1))
        return r, c

    path, _ = route_through_array(cost, cell(a), cell(b), fully_connected=True, geometric=True)
    path_uv = (
        (np.asarray(path, dtype=np.float64)[:, ::-1] + 0.5) * f - 0.5 + np.array([u0, v0], dtype=np.float64)
    )
    path_uv = np.concatenate([a[None], path_uv[1:-1], b[None]]) if len(path_uv) > 2 else np.stack([a, b])
    return path_uv, radius_px


def _centred_path(
    sub_m: np.ndarray,
    path_uv: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    u0: int,
    v0: int,
    radius_px: float,
    smooth_px: float,
) -> np.ndarray:
    """The grid path (N, 2) from A to B smoothed and centred in the cropped mask ``sub_m`` (corner at
    pixel (u0, v0)), input pixels; unchanged where it is too short to smooth."""
    # smooth the staircase of the pixel path, then move each point to the middle of the mask's
    # cross-section normal to the path: the grid path is ambiguous by ~1 px (equal-cost staircases,
    # flat distance map near the end caps), the cross-section midpoint is not
    length = float(np.sum(np.linalg.norm(np.diff(path_uv, axis=0), axis=1)))
    if length > 4 * max(smooth_px, 1.0):
        spacing = max(1.0, radius_px / 8)  # samples along the path, input pixels
        dense = resample_polyline(path_uv, max(int(np.ceil(length / spacing)) + 1, 3))
        if smooth_px > 0:
            dense = _smooth_keep_ends(dense, smooth_px / spacing)
        half = 1.5 * radius_px + 2.0
        sub_mask = sub_m.astype(np.float32)
        centred = dense - [u0, v0]
        for _ in range(2):  # the second pass uses the normals of the centred path
            centred = _cross_section_midpoints(sub_mask, centred, half, tangent_sigma=radius_px / spacing)
        centred = centred + np.array([u0, v0], dtype=np.float64)
        # within about a tube radius of an end the cross-sections are cut by the end cap: join the
        # landmark straight to the first point beyond (the chord's sagitta is small there)
        r_end = radius_px
        far = (np.linalg.norm(centred - a, axis=1) > r_end) & (np.linalg.norm(centred - b, axis=1) > r_end)
        if far.sum() >= 3:
            centred = np.concatenate(
                [a[None], _smooth_keep_ends(centred[far], max(smooth_px / 2 / spacing, 0.5)), b[None]]
            )
        path_uv = centred
        path_uv[0], path_uv[-1] = a, b
    return path_uv


def _smooth_keep_ends(points: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing along a densely sampled path, blended back to the exact end points."""
    smooth = ndimage.gaussian_filter1d(points, sigma, axis=0, mode="nearest")
    n = len(points)
    w = np.clip(np.minimum(np.arange(n), np.arange(n)[::-1]) / (2 * sigma), 0.0, 1.0)[:, None]
    return w * smooth + (1 - w) * points


def _cross_section_midpoints(
    mask: np.ndarray,
    points: np.ndarray,
    half_px: float,
    *,
    tangent_sigma: float,
    step: float = 0.25,
) -> np.ndarray:
    """Move each interior point (N, 2) to the midpoint of the mask run through it along the path normal.

    Normals come from the path smoothed with ``tangent_sigma`` (points); edges are the 0.5 crossings of
    the bilinearly interpolated mask; points outside the mask are kept.
    """
    n = len(points)
    # extrapolate linearly past the ends so that the end normals are not bent by the filter's edges
    ext = int(np.ceil(3 * tangent_sigma))
    d0, d1 = points[min(ext, n - 1)] - points[0], points[-1] - points[max(n - 1 - ext, 0)]
    steps = np.arange(1, ext + 1)[:, None] / max(ext, 1)
    padded = np.concatenate([points[0] - steps[::-1] * d0, points, points[-1] + steps * d1])
    smooth = ndimage.gaussian_filter1d(padded, tangent_sigma, axis=0, mode="nearest")[ext : ext + n]
    tangent = np.gradient(smooth, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-12)
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)
    k = np.arange(-half_px, half_px + step / 2, step)
    K = len(k)
    c0 = int(np.argmin(np.abs(k)))
    coords = points[:, None, :] + k[None, :, None] * normal[:, None, :]  # (N, K, 2) (u, v)
    vals = cv2.remap(
        mask,
        coords[..., 0].astype(np.float32),
        coords[..., 1].astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0.0,
    ).astype(np.float64)
    outside = vals < 0.5
    il = np.where(outside[:, :c0], np.arange(c0), -1).max(axis=1)  # last outside sample left of the point
    ir = c0 + np.where(outside[:, c0:], np.arange(K - c0), K).min(axis=1)  # first outside on the right
    # skip points on or outside an edge (e.g. at an end cap) and runs reaching the search limit
    found = (vals[:, c0] >= 0.99) & (il >= 0) & (ir < K)
    found[[0, -1]] = False
    rows = np.arange(n)
    il, ir = np.clip(il, 0, K - 2), np.clip(ir, 1, K - 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        # linear 0.5 crossings between the last outside and first inside samples on each side
        kl = k[il] + step * (0.5 - vals[rows, il]) / (vals[rows, il + 1] - vals[rows, il])
        kr = k[ir - 1] + step * (vals[rows, ir - 1] - 0.5) / (vals[rows, ir - 1] - vals[rows, ir])
        mids = np.where(found, 0.5 * (kl + kr), np.nan)
        widths = np.where(found, kr - kl, np.nan)
    # cross-sections much narrower than the tube are cut by an end cap or a gap: those points take the
    # offset interpolated from their neighbours (held constant towards the ends)
    ok = np.isfinite(mids)
    if not ok.any():
        return points.copy()
    ok &= widths >= 0.7 * np.nanmedian(widths)
    idx = np.arange(n)
    offset = np.interp(idx, idx[ok], mids[ok]) if ok.any() else np.zeros(n)
    # a running median rejects sections biased by a partial cut (gaps, notches) over a few points
    offset = ndimage.median_filter(offset, size=2 * int(np.ceil(tangent_sigma)) + 1, mode="nearest")
    return points + offset[:, None] * normal
