"""Where the instrument is in an X-ray: the CM and the straight shaft it is mounted on.

Bone registration compares the image with a DRR of bone only; the metal CM and its shaft are the
strongest edges in a fluoroscopic image, and patch NCC near them pulls the bone towards them (a
femur 10 mm off in depth on one multiple-CM trial; 0.8 mm with the instrument masked out). The mask
is made from what detection gives: the CM segmentation and the centreline from landmark A to B. The
shaft continues the centreline's straight base behind A to the image border.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from scipy import ndimage

__all__ = ["instrument_mask", "instrument_mask_from_landmarks", "instrument_masks"]

log = logging.getLogger(__name__)


def instrument_mask(
    cm_mask: np.ndarray,
    centerline_px: np.ndarray,
    *,
    margin_px: float = 6.0,
    shaft: bool = True,
    direction_fraction: float = 0.125,
) -> np.ndarray:
    """Pixels covered by the CM and its shaft, with a margin.

    Args:
        cm_mask: (H, W) bool/uint8 segmentation of the CM (the notched part suffices), in the image's
            pixels.
        centerline_px: (P, 2) ordered (u, v) centreline from landmark A to landmark B, same pixels.
        margin_px: added around the segmentation and the shaft band (blur, scatter halo, detection
            error), pixels.
        shaft: include the shaft band behind A (a straight tube to the image border, as wide as the
            widest cross-section of the segmentation).
        direction_fraction: fraction of the centreline (from A) whose chord gives the shaft direction.

    Returns:
        (H, W) bool, True on the instrument.

    Raises:
        ValueError: an empty mask or a centreline with fewer than two distinct points.
    """
    cm = np.asarray(cm_mask).astype(bool)
    if cm.ndim != 2 or not cm.any():
        raise ValueError("the CM mask is empty")
    cl = np.asarray(centerline_px, dtype=np.float64)
    if cl.ndim != 2 or cl.shape[1] != 2 or cl.shape[0] < 2:
        raise ValueError(f"centerline_px must have shape (P >= 2, 2), got {cl.shape}")
    # distance to the nearest CM pixel: dilation by a disc of radius margin_px
    out = ndimage.distance_transform_edt(~cm) <= margin_px
    if shaft:
        k = max(1, round(direction_fraction * (len(cl) - 1)))
        d = cl[0] - cl[k]
        nd = float(np.linalg.norm(d))
        if nd <= 0.0:
            raise ValueError("the centreline has no length at its start")
        d /= nd
        half_width = float(ndimage.distance_transform_edt(cm).max()) + margin_px
        v, u = np.mgrid[0 : cm.shape[0], 0 : cm.shape[1]].astype(np.float64)
        du, dv = u - cl[0, 0], v - cl[0, 1]
        along = du * d[0] + dv * d[1]
        across = np.abs(-du * d[1] + dv * d[0])
        out |= (along >= 0.0) & (across <= half_width)
    return out


def instrument_masks(
    cm_masks: Sequence[np.ndarray | None],
    centerlines_px: Sequence[np.ndarray | None],
    *,
    margin_px: float = 6.0,
) -> list[np.ndarray | None]:
    """:func:`instrument_mask` per image; None where the CM was not detected (no mask or no
    centreline) or the mask cannot be made (logged)."""
    out: list[np.ndarray | None] = []
    for k, (m, cl) in enumerate(zip(cm_masks, centerlines_px, strict=True)):
        if m is None or cl is None:
            out.append(None)
            continue
        try:
            out.append(instrument_mask(m, cl, margin_px=margin_px))
        except ValueError as e:
            log.warning("image %d: no instrument mask (%s)", k, e)
            out.append(None)
    return out


def instrument_mask_from_landmarks(
    cm_mask: np.ndarray, landmarks_px: np.ndarray, *, margin_px: float = 6.0
) -> np.ndarray | None:
    """:func:`instrument_mask` with the centreline extracted from the segmentation and the two
    landmarks (2, 2) [[uA, vA], [uB, vB]]; None (logged) where that fails."""
    from fluoronav.detection.centerline import extract_centerline

    lm = np.asarray(landmarks_px, dtype=np.float64)
    try:
        cl = extract_centerline(np.asarray(cm_mask, bool), lm[0], lm[1])
        return instrument_mask(cm_mask, cl, margin_px=margin_px)
    except ValueError as e:
        log.warning("no instrument mask (%s)", e)
        return None
