"""Where the instrument is in an X-ray: the CM and the straight shaft it is mounted on.

Bone registration compares the image with a DRR of bone only; the metal CM and its shaft are the
strongest edges in a fluoroscopic image, and patch NCC near them pulls the bone towards them
(docs/validation.md: a femur pulled off in depth). The mask is made from what detection gives: the
CM segmentation and the centreline from landmark A to B, plus the solid tip beyond B and the shaft
behind A to the image border (its direction the centreline's base, refined on the image when given:
the base is short and the shaft long).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np
from scipy import ndimage

from fluoronav.detection.centerline import end_direction, extract_centerline

__all__ = ["instrument_mask", "instrument_mask_from_landmarks", "instrument_masks", "shaft_direction"]

log = logging.getLogger(__name__)


def _band(
    shape: tuple[int, int], origin: np.ndarray, direction: np.ndarray, half_width: float, length: float
) -> np.ndarray:
    """Pixels within ``half_width`` of the ray ``origin + t·direction``, 0 ≤ t ≤ ``length``."""
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    du, dv = u - origin[0], v - origin[1]
    along = du * direction[0] + dv * direction[1]
    across = np.abs(-du * direction[1] + dv * direction[0])
    return (along >= 0.0) & (along <= length) & (across <= half_width)


def shaft_direction(
    image: np.ndarray,
    origin_px: np.ndarray,
    direction: np.ndarray,
    width_px: float,
    *,
    search_deg: float = 15.0,
    step_deg: float = 0.25,
    length_px: float | None = None,
) -> np.ndarray:
    """Refine the direction of the straight shaft behind landmark A on the image: the angle within
    ±``search_deg`` of ``direction`` whose line from ``origin_px`` is brightest against the two lines
    beside it (1.5 widths off), the shaft being a bright (attenuating) tube in a −ln image.

    Args:
        image: (H, W) −ln(I/I0) image (metal bright).
        origin_px: (2,) (u, v) start (landmark A).
        direction: (2,) unit (u, v) first guess (the centreline's base direction).
        width_px: apparent tube width.
        length_px: line length scored (default: 15 widths, at least 60 px).

    Returns:
        (2,) unit direction; ``direction`` itself when no line inside the image can be scored.
    """
    img = np.asarray(image, dtype=np.float64)
    length = float(length_px if length_px is not None else max(60.0, 15.0 * width_px))
    t = np.arange(0.5 * width_px, length, 1.0)
    base = math.atan2(direction[1], direction[0])
    angles = base + np.radians(np.arange(-search_deg, search_deg + 1e-9, step_deg))
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (A, 2)
    n = np.stack([-d[:, 1], d[:, 0]], axis=1)
    pts = origin_px[None, None] + t[None, :, None] * d[:, None]  # (A, T, 2)
    off = 1.5 * width_px * n[:, None]
    H, W = img.shape

    def sample(p: np.ndarray) -> np.ndarray:
        return ndimage.map_coordinates(img, [p[..., 1], p[..., 0]], order=1, mode="nearest")

    def inside(p: np.ndarray) -> np.ndarray:
        return (p[..., 0] >= 0) & (p[..., 0] <= W - 1) & (p[..., 1] >= 0) & (p[..., 1] <= H - 1)

    ok = inside(pts) & inside(pts + off) & inside(pts - off)
    if ok.sum(axis=1).min() < 10:
        return np.asarray(direction, dtype=np.float64)
    contrast = sample(pts) - 0.5 * (sample(pts + off) + sample(pts - off))
    score = np.where(ok, contrast, 0.0).sum(axis=1) / ok.sum(axis=1)
    return d[int(np.argmax(score))]


def instrument_mask(
    cm_mask: np.ndarray,
    centerline_px: np.ndarray,
    *,
    image: np.ndarray | None = None,
    margin_px: float = 6.0,
    shaft: bool = True,
    tip_widths: float = 1.5,
    direction_fraction: float = 0.125,
) -> np.ndarray:
    """Pixels covered by the CM, its tip and its shaft, with a margin.

    Args:
        cm_mask: (H, W) bool/uint8 segmentation of the CM (the notched part suffices), in the image's
            pixels.
        centerline_px: (P, 2) ordered (u, v) centreline from landmark A to landmark B, same pixels.
        image: the (H, W) −ln image; when given the shaft's direction is refined on it
            (:func:`shaft_direction`), else it continues the centreline's base.
        margin_px: added around the segmentation, the tip and the shaft band (blur, scatter halo,
            detection error), pixels.
        shaft: include the shaft band behind A (a straight tube to the image border, as wide as the
            widest cross-section of the segmentation).
        tip_widths: length of the solid tip beyond B (not part of a notched-region segmentation)
            covered, in tube widths (the paper's CM: a 4.15 mm tip on a 6 mm tube).
        direction_fraction: fraction of the centreline at each end whose chord gives the shaft's and
            the tip's direction.

    Returns:
        (H, W) bool, True on the instrument.

    Raises:
        ValueError: an empty mask or a centreline with fewer than two distinct points at its ends.
    """
    cm = np.asarray(cm_mask).astype(bool)
    if cm.ndim != 2 or not cm.any():
        raise ValueError("the CM mask is empty")
    cl = np.asarray(centerline_px, dtype=np.float64)
    if cl.ndim != 2 or cl.shape[1] != 2 or cl.shape[0] < 2:
        raise ValueError(f"centerline_px must have shape (P >= 2, 2), got {cl.shape}")
    # distance to the nearest CM pixel: dilation by a disc of radius margin_px
    out = ndimage.distance_transform_edt(~cm) <= margin_px
    width = 2.0 * float(ndimage.distance_transform_edt(cm).max())
    half = 0.5 * width + margin_px
    if tip_widths > 0:
        out |= _band(
            cm.shape, cl[-1], end_direction(cl, direction_fraction, at_start=False), half, tip_widths * width
        )
    if shaft:
        d = end_direction(cl, direction_fraction, at_start=True)
        if image is not None:
            d = shaft_direction(image, cl[0], d, width)
        out |= _band(cm.shape, cl[0], d, half, float(np.hypot(*cm.shape)))
    return out


def instrument_masks(
    cm_masks: Sequence[np.ndarray | None],
    centerlines_px: Sequence[np.ndarray | None],
    images: Sequence[np.ndarray | None] | None = None,
    *,
    margin_px: float = 6.0,
) -> list[np.ndarray | None]:
    """:func:`instrument_mask` per image (with the image when given); None where the CM was not
    detected (no mask or no centreline) or the mask cannot be made (logged)."""
    imgs = list(images) if images is not None else [None] * len(cm_masks)
    out: list[np.ndarray | None] = []
    for k, (m, cl, img) in enumerate(zip(cm_masks, centerlines_px, imgs, strict=True)):
        if m is None or cl is None:
            out.append(None)
            continue
        try:
            out.append(instrument_mask(m, cl, image=img, margin_px=margin_px))
        except ValueError as e:
            log.warning("image %d: no instrument mask (%s)", k, e)
            out.append(None)
    return out


def instrument_mask_from_landmarks(
    cm_mask: np.ndarray,
    landmarks_px: np.ndarray,
    *,
    image: np.ndarray | None = None,
    margin_px: float = 6.0,
) -> np.ndarray | None:
    """:func:`instrument_mask` with the centreline extracted from the segmentation and the two
    landmarks (2, 2) [[uA, vA], [uB, vB]]; None (logged) where that fails."""
    lm = np.asarray(landmarks_px, dtype=np.float64)
    try:
        cl = extract_centerline(np.asarray(cm_mask, bool), lm[0], lm[1])
        return instrument_mask(cm_mask, cl, image=image, margin_px=margin_px)
    except ValueError as e:
        log.warning("no instrument mask (%s)", e)
        return None
