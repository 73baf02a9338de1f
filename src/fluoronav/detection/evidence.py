"""Image evidence for a detection: whether the image has an edge where the mask has its boundary.

The CM is a metal tube: its projection is bounded by a step in intensity far stronger than the
gradients of the anatomy around it, which the fine stage's mask follows to about a pixel; a false
alarm (a bone's rim, the hip joint) is a blob whose boundary lies on no such edge.
:func:`mask_edge_ratio` measures this: the mean image gradient on the mask's boundary over the
median gradient in a ring around it, at one smoothing scale, so it depends neither on the image's
scaling, dose nor pixel size. :func:`end_continuation` asks whether a tube goes on beyond one end of
a detection: it does at landmark A, where the CM meets its mounting shaft, and not at a free end
(the CM's tip, or the far end of a short shaft stub that the fine stage can take for A).
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage as ndi
from torch.nn import functional as tnf

__all__ = ["area_downsample", "end_continuation", "local_tube_width_px", "mask_edge_ratio"]


def area_downsample(images: torch.Tensor, factor: int) -> torch.Tensor:
    """Bin images (..., H, W) by area averaging over ``factor`` × ``factor`` blocks → (..., H // factor,
    W // factor); trailing rows and columns that do not fill a block are dropped."""
    if factor < 1 or int(factor) != factor:
        raise ValueError(f"downsampling factor must be a positive integer, got {factor}")
    if factor == 1:
        return images
    shape = images.shape
    x = images.reshape(-1, 1, shape[-2], shape[-1])
    out = tnf.avg_pool2d(x, kernel_size=int(factor), stride=int(factor))
    return out.reshape(*shape[:-2], out.shape[-2], out.shape[-1])


def mask_edge_ratio(
    image: np.ndarray,
    mask: np.ndarray,
    *,
    pixel_spacing_mm: float,
    sigma_mm: float = 1.164,
    ring_mm: tuple[float, float] = (1.75, 5.82),
) -> float:
    """Mean gradient magnitude on a mask's boundary over its median in a ring around the mask.

    Args:
        image: (H, W) image (any intensity scale; a log image as the detector's input).
        mask: (H, W) bool mask of one object.
        pixel_spacing_mm: image pixel size at the detector, mm.
        sigma_mm: σ of the Gaussian derivative, mm at the detector (the default: 2 pixels of the
            512² training images, 0.582 mm, where their noise still hides a 1-pixel gradient).
        ring_mm: (inner, outer) distance from the mask of the reference ring, mm at the detector.

    Returns:
        The ratio (≥ 0; about 1 for a boundary drawn at random on the image's texture, 4–30 for
        a CM's tube). ``inf`` where the ring has no pixel or no gradient (the mask fills the
        image, or a constant background); 0 for an empty mask.
    """
    img = np.asarray(image)
    m = np.asarray(mask, dtype=bool)
    if img.shape != m.shape or img.ndim != 2:
        raise ValueError(f"image and mask must be 2-D of one shape, got {img.shape} and {m.shape}")
    if not pixel_spacing_mm > 0.0:
        raise ValueError(f"pixel_spacing_mm must be positive, got {pixel_spacing_mm}")
    rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
    if rows.size == 0:
        return 0.0
    sigma_px = sigma_mm / pixel_spacing_mm
    inner_px, outer_px = (r / pixel_spacing_mm for r in ring_mm)
    # only the neighbourhood of the mask is needed: crop so a 1536² image costs what a 512² one does
    pad = int(np.ceil(outer_px + 4.0 * sigma_px)) + 1
    r0, r1 = max(rows[0] - pad, 0), min(rows[-1] + pad + 1, m.shape[0])
    c0, c1 = max(cols[0] - pad, 0), min(cols[-1] + pad + 1, m.shape[1])
    img, m = img[r0:r1, c0:c1].astype(np.float64), m[r0:r1, c0:c1]
    # finer images are binned to about σ/2 per pixel first: the same measure at a ninth of the cost
    # for the 0.194 mm pixels of a full-resolution detector image
    factor = int(sigma_mm / 2.0 / pixel_spacing_mm + 0.25)
    if factor >= 2:
        img, m = _bin_image_and_mask(img, m, factor)
        sigma_px, inner_px, outer_px = sigma_px / factor, inner_px / factor, outer_px / factor
        if not m.any():
            return 0.0
    grad = ndi.gaussian_gradient_magnitude(img, sigma_px)
    boundary = m & ~ndi.binary_erosion(m)
    dist_out = ndi.distance_transform_edt(~m)
    ring = (dist_out > inner_px) & (dist_out <= outer_px)
    if not ring.any():
        return float("inf")
    ref = float(np.median(grad[ring]))
    if ref <= 0.0:
        return float("inf")
    return float(grad[boundary].mean()) / ref


def _bin_image_and_mask(img: np.ndarray, mask: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """An image (float64) and its bool mask binned by ``factor`` (area mean; the mask where at least
    half a bin is in it)."""
    both = np.stack([np.asarray(img, dtype=np.float64), mask.astype(np.float64)])
    binned = area_downsample(torch.from_numpy(both), factor).numpy()
    return binned[0], binned[1] >= 0.5


def local_tube_width_px(mask: np.ndarray, point_px: np.ndarray) -> float | None:
    """Width of a tube's mask near a point, pixels: twice the largest inscribed radius (distance
    transform) among the mask pixels within 3 typical radii (its 95th percentile) of ``point_px``
    (u, v); None for an empty mask."""
    m = np.asarray(mask, dtype=bool)
    p = np.asarray(point_px, dtype=np.float64).reshape(2)
    rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
    if rows.size == 0:
        return None
    # the mask's bounding box only: a 1536² image costs what a 512² one does
    box = m[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
    dt = ndi.distance_transform_edt(np.pad(box, 1))[1:-1, 1:-1]
    radius = float(np.percentile(dt[box], 95))
    vv, uu = np.nonzero(box)
    near = np.hypot(uu + cols[0] - p[0], vv + rows[0] - p[1]) <= 3.0 * radius
    return 2.0 * float(dt[vv[near], uu[near]].max() if near.any() else radius)


def end_continuation(
    image: np.ndarray,
    mask: np.ndarray,
    point_px: np.ndarray,
    *,
    pixel_spacing_mm: float | None = None,
    radius_frac: float = 1.3,
    n_angles: int = 72,
) -> float | None:
    """How much tube there is around a mask's end point outside the mask, as a fraction of the tube.

    The tube's width ``w`` is twice the mask's largest inscribed radius near the point. On a circle of
    radius ``radius_frac`` · ``w`` around the point, the image 0.15 ``w`` or more outside the mask
    (just beside it, the tube's own blurred edge is half bright) is scaled so that the background
    around the mask (its median in a band 0.5–1.5 ``w`` outside the mask) is 0 and the tube (the
    median of the mask within ``w`` of the point) is 1; the result is the largest value on that
    circle after a running median over 5 angles. A junction with a shaft (landmark A) gives
    about 1 or more in the shaft's direction; a free end of a tube gives about 0.

    Args:
        image: (H, W) image, bright = attenuating (any scale).
        mask: (H, W) bool mask of the object.
        point_px: (2,) (u, v) the end point, input pixels.
        pixel_spacing_mm: image pixel size at the detector, mm, where known: images finer than
            about 0.58 mm are binned to about that first (the measure is in tube widths, so it does
            not change; a 1536² detector image then costs what a 512² one does).
        radius_frac: radius of the circle, in tube widths.
        n_angles: samples on the circle.

    Returns:
        The fraction, or None where it is undefined: an empty mask, a tube narrower than 3 pixels,
        no circle sample outside the mask, no background band, or a tube no brighter than its
        background.
    """
    img = np.asarray(image)
    m = np.asarray(mask, dtype=bool)
    if img.shape != m.shape or img.ndim != 2:
        raise ValueError(f"image and mask must be 2-D of one shape, got {img.shape} and {m.shape}")
    if pixel_spacing_mm is not None and not pixel_spacing_mm > 0.0:
        raise ValueError(f"pixel_spacing_mm must be positive, got {pixel_spacing_mm}")
    p = np.asarray(point_px, dtype=np.float64).reshape(2)
    factor = int(_BIN_MM / pixel_spacing_mm + 0.25) if pixel_spacing_mm else 1
    rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
    if factor >= 2 and rows.size:
        # the tube's width from the binned mask, then the window of 3 widths around the point that
        # the circle and the band need, binned
        box = m[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1].astype(np.float32)
        box_binned = area_downsample(torch.from_numpy(box), factor).numpy() >= 0.5
        p_box = (p - np.array([cols[0], rows[0]], dtype=np.float64) + 0.5) / factor - 0.5
        half = factor * int(np.ceil(3.0 * (local_tube_width_px(box_binned, p_box) or 1.0) + 2.0))
        r0, c0 = max(int(p[1]) - half, 0), max(int(p[0]) - half, 0)
        r1, c1 = min(int(p[1]) + half + 1, m.shape[0]), min(int(p[0]) + half + 1, m.shape[1])
        img, m = _bin_image_and_mask(img[r0:r1, c0:c1], m[r0:r1, c0:c1], factor)
        p = (p - np.array([c0, r0], dtype=np.float64) + 0.5) / factor - 0.5
    return _continuation(img, m, p, radius_frac=radius_frac, n_angles=n_angles)


#: pixel size (mm at the detector) that :func:`end_continuation` bins finer images to
_BIN_MM = 0.582


def _continuation(
    img: np.ndarray, m: np.ndarray, p: np.ndarray, *, radius_frac: float, n_angles: int
) -> float | None:
    """:func:`end_continuation` on an image at its working pixel size."""
    w = local_tube_width_px(m, p)
    if w is None or w < 3.0:
        return None
    half = int(np.ceil(3.0 * w))
    r0, c0 = max(int(p[1]) - half, 0), max(int(p[0]) - half, 0)
    r1, c1 = min(int(p[1]) + half + 1, m.shape[0]), min(int(p[0]) + half + 1, m.shape[1])
    if r1 <= r0 or c1 <= c0:
        return None
    sub, win = m[r0:r1, c0:c1], img[r0:r1, c0:c1].astype(np.float64)
    yy, xx = np.mgrid[r0:r1, c0:c1]
    dist = np.hypot(xx - p[0], yy - p[1])
    inside = sub & (dist <= w)
    dist_out = ndi.distance_transform_edt(~sub)
    band = ~sub & (dist_out >= 0.5 * w) & (dist_out <= 1.5 * w) & (dist <= 2.5 * w)
    if not inside.any() or int(band.sum()) < 10:
        return None
    tube, background = float(np.median(win[inside])), float(np.median(win[band]))
    if tube <= background:
        return None
    angles = np.linspace(0.0, 2.0 * np.pi, n_angles, endpoint=False)
    circle = p + radius_frac * w * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    # the circle lies in the window (radius 1.3 w < 3 w) or, where the window is cut by the image's
    # border, beyond the image, where "nearest" repeats the same border pixels
    coords = [circle[:, 1] - r0, circle[:, 0] - c0]
    # clear of the mask by 0.15 w: just beside it the tube's own edge (a pixel or two of blur or of
    # a mask drawn a pixel short) is half bright
    clear = ndi.map_coordinates(dist_out, coords, order=1, mode="nearest") >= 0.15 * w
    if not clear.any():
        return None
    values = (ndi.map_coordinates(win, coords, order=1, mode="nearest") - background) / (tube - background)
    # one bright pixel (noise, a bone edge) must not count: the tube spans several angles
    values = ndi.median_filter(values, size=5, mode="wrap")
    return float(values[clear].max())
