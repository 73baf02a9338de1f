"""Overlays of a CM registration: edges of the final CM DRR on the ROI image (as the paper's Fig. 12)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from fluoronav.registration.cm.result import CMRegistrationResult

__all__ = ["EDGE_FRACTION", "edge_mask", "save_overlays", "to_uint8"]

#: a DRR pixel is an edge where its Sobel magnitude exceeds this fraction of the maximum
EDGE_FRACTION = 0.2


def edge_mask(img: np.ndarray) -> np.ndarray:
    """Edge mask of a DRR: Sobel magnitude above ``EDGE_FRACTION`` of its maximum."""
    g = np.hypot(ndimage.sobel(img, axis=0), ndimage.sobel(img, axis=1))
    top = float(g.max())
    return g > EDGE_FRACTION * top if top > 0 else np.zeros(img.shape, bool)


def to_uint8(img: np.ndarray) -> np.ndarray:
    """An image scaled to 8 bits between its 1st and 99th percentiles (clipped)."""
    lo, hi = np.percentile(img, [1, 99])
    return (np.clip((img - lo) / max(hi - lo, 1e-12), 0, 1) * 255).astype(np.uint8)


def save_overlays(result: CMRegistrationResult, out_dir: str | Path, *, scale: int = 4) -> list[Path]:
    """Write ``overlay_<view>.png`` per view: edges of the final CM DRR (green) on the ROI image
    (as the paper's Fig. 12), upscaled ``scale``× (nearest). Returns the written paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, img, drr in zip(result.view_names, result.roi_images, result.roi_drrs, strict=True):
        gray = to_uint8(img)
        rgb = np.repeat(gray[..., None], 3, axis=-1)
        edge = edge_mask(drr)
        rgb[edge] = (0, 255, 0)
        rgb = np.kron(rgb, np.ones((scale, scale, 1), np.uint8))
        p = out / f"overlay_{name}.png"
        cv2.imwrite(str(p), rgb[..., ::-1])
        paths.append(p)
    return paths
