"""Region of interest for CM registration: crop around the two landmarks, then bin.

The authors crop the image to 500 × 500 pixels around the two detected CM landmarks and downsample
it 4× (Gao et al., IEEE TBME 69(1), 2022; the authors' code). The crop is centred on the landmarks'
midpoint. The ROI camera comes from ``Camera.crop_around`` then ``Camera.downsample``, so a world point
projects through the ROI camera exactly where its full-image projection lands after the same crop and binning
(``u_roi = (u − col0 − (f − 1)/2) / f``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch.nn import functional as tnf

from fluoronav.geometry.camera import Camera

__all__ = [
    "CropBox",
    "area_downsample",
    "crop_and_downsample_image",
    "full_to_roi_px",
    "roi_camera_from_landmarks",
    "roi_to_full_px",
]


@dataclass(frozen=True)
class CropBox:
    """Crop ``[row0:row0+rows, col0:col0+cols]`` of the full image (may extend past its edges)."""

    row0: int
    col0: int
    rows: int
    cols: int


def roi_camera_from_landmarks(
    camera: Camera, landmarks_px: np.ndarray, *, size: int | tuple[int, int] = 500, downsample: int = 4
) -> tuple[Camera, CropBox]:
    """ROI camera around two landmarks.

    Args:
        camera: full-image camera.
        landmarks_px: (2, 2) landmarks A and B as (u, v) in full-image pixels.
        size: crop size (rows, cols) or a square side, full-image pixels.
        downsample: integer binning factor applied after cropping.

    Returns:
        (roi camera of size ``size // downsample``, crop box in full-image pixels).
    """
    lm = np.asarray(landmarks_px, dtype=np.float64)
    if lm.shape != (2, 2) or not np.all(np.isfinite(lm)):
        raise ValueError(f"landmarks_px must be a finite (2, 2) array, got shape {lm.shape}")
    cropped, (row0, col0) = camera.crop_around(lm.mean(axis=0), size)
    return cropped.downsample(downsample), CropBox(row0, col0, cropped.rows, cropped.cols)


def full_to_roi_px(uv: np.ndarray, box: CropBox, factor: int) -> np.ndarray:
    """Full-image pixels (..., 2) → ROI pixels after crop and ``factor`` binning."""
    uv = np.asarray(uv, dtype=np.float64)
    off = np.array([box.col0, box.row0], dtype=np.float64)
    return (uv - off - (factor - 1) / 2.0) / factor


def roi_to_full_px(uv: np.ndarray, box: CropBox, factor: int) -> np.ndarray:
    """Inverse of :func:`full_to_roi_px`."""
    uv = np.asarray(uv, dtype=np.float64)
    return uv * factor + (factor - 1) / 2.0 + np.array([box.col0, box.row0], dtype=np.float64)


def area_downsample(images: torch.Tensor, factor: int) -> torch.Tensor:
    """Bin images (..., H, W) by area averaging over ``factor`` × ``factor`` blocks.

    Trailing rows/columns that do not fill a block are dropped (as ``Camera.downsample``).
    """
    if factor < 1 or int(factor) != factor:
        raise ValueError(f"downsampling factor must be a positive integer, got {factor}")
    if factor == 1:
        return images
    shape = images.shape
    x = images.reshape(-1, 1, shape[-2], shape[-1])
    out = tnf.avg_pool2d(x, kernel_size=int(factor), stride=int(factor))
    return out.reshape(*shape[:-2], out.shape[-2], out.shape[-1])


def crop_and_downsample_image(
    image: np.ndarray | torch.Tensor, box: CropBox, factor: int
) -> np.ndarray | torch.Tensor:
    """Crop (..., H, W) to ``box`` and bin by ``factor``; the input type (numpy / torch) is kept.

    Parts of the box outside the image are filled with the nearest edge pixel (replicate), so that
    no artificial edge enters the gradient-based similarity.
    """
    is_np = isinstance(image, np.ndarray)
    t: torch.Tensor = torch.from_numpy(np.ascontiguousarray(image)) if is_np else torch.as_tensor(image)
    H, W = t.shape[-2:]
    pad = (
        max(0, -box.col0),
        max(0, box.col0 + box.cols - W),
        max(0, -box.row0),
        max(0, box.row0 + box.rows - H),
    )
    if any(pad):
        shape = t.shape
        x = t.reshape(-1, 1, H, W)
        x = tnf.pad(x if x.is_floating_point() else x.double(), pad, mode="replicate")
        t = x.reshape(*shape[:-2], x.shape[-2], x.shape[-1])
    r0, c0 = box.row0 + pad[2], box.col0 + pad[0]
    crop = t[..., r0 : r0 + box.rows, c0 : c0 + box.cols]
    if not crop.is_floating_point():
        crop = crop.double()
    out = area_downsample(crop, factor)
    return out.numpy() if is_np else out
