"""The images of a CM registration (:class:`CMView`) and their regions of interest per level.

Per view the image is cropped to a square of ``roi_size_full_px`` *full-detector* pixels (authors: 500)
around the midpoint of the two landmarks and binned to the level's resolution (authors: 4×). Images
that are already binned (``CMView.binning``, e.g. 2 for a 768² image of the 1536² CIOS detector) are
cropped to ``500 / binning`` pixels and binned ``4 / binning`` times, so the working ROI is the same.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fluoronav.geometry.camera import Camera
from fluoronav.registration.roi import CropBox, crop_and_downsample_image

__all__ = ["BackgroundFn", "CMView", "ViewROI", "landmark_center", "view_roi"]

#: a static background rendered for a ROI camera: ``roi_camera -> (h, w)`` DRR
BackgroundFn = Callable[[Camera], np.ndarray]


@dataclass(frozen=True, eq=False)
class CMView:
    """One X-ray image for CM registration.

    Attributes:
        image: (H, W) −log intensity image (bone and metal bright), any resolution.
        camera: its camera (``camera_from_world`` in the workflow's world frame, K for this image).
        landmarks_px: (2, 2) detected landmarks A, B as (u, v) in this image's pixels; NaN rows are
            missing (then the ROI is centred on the initial pose's projection).
        background: optional static DRR of the anatomy: an (H, W) array aligned with ``image`` or a
            callable ``roi_camera -> (h, w)`` (rendered once per level); in the DRR's line-integral
            units (μ_water = 0.02/mm).
        binning: full-detector pixels per image pixel (2 for 768² of a 1536² detector); None infers
            it from ``camera.pixel_spacing_mm`` and ``full_pixel_spacing_mm`` (1 when unknown).
        full_pixel_spacing_mm: detector pixel pitch at full resolution (CIOS Fusion: 0.194 mm).
        name: label used in results and overlay file names.
    """

    image: np.ndarray
    camera: Camera
    landmarks_px: np.ndarray | None = None
    background: np.ndarray | BackgroundFn | None = None
    binning: int | None = None
    full_pixel_spacing_mm: float = 0.194
    name: str = ""

    @property
    def image_binning(self) -> int:
        if self.binning is not None:
            return int(self.binning)
        ps = self.camera.pixel_spacing_mm
        if ps is None:
            return 1
        return max(1, round(ps / self.full_pixel_spacing_mm))


@dataclass(frozen=True, eq=False)
class ViewROI:
    """A view's ROI at one level: crop box in image pixels, binning factor, camera and fixed image."""

    box: CropBox
    factor: int
    camera: Camera
    image: np.ndarray
    background: np.ndarray | None


def landmark_center(view: CMView, fallback_uv: np.ndarray) -> np.ndarray:
    """The midpoint of a view's landmarks (u, v), or ``fallback_uv`` (2,) when they are missing."""
    lm = None if view.landmarks_px is None else np.asarray(view.landmarks_px, dtype=np.float64)
    if lm is not None and lm.shape == (2, 2) and np.all(np.isfinite(lm)):
        return lm.mean(axis=0)
    return np.asarray(fallback_uv, dtype=np.float64)


def view_roi(
    view: CMView, center_uv: np.ndarray, *, downsample_full: int, roi_size_full_px: int = 500
) -> ViewROI:
    """Crop ``roi_size_full_px`` full-detector pixels around ``center_uv`` (image pixels), binned to
    ``downsample_full`` full-detector pixels per working pixel (e.g. 768² image: crop 250, bin 2).

    Raises:
        ValueError: when the image's binning does not divide ``downsample_full``.
    """
    b = view.image_binning
    if downsample_full % b:
        raise ValueError(f"image binning {b} does not divide the level's downsampling {downsample_full}")
    factor = downsample_full // b
    size = round(roi_size_full_px / b)
    size -= size % factor
    cropped, (row0, col0) = view.camera.crop_around(center_uv, size)
    box = CropBox(row0, col0, cropped.rows, cropped.cols)
    cam = cropped.downsample(factor)
    img = np.asarray(crop_and_downsample_image(np.asarray(view.image, dtype=np.float32), box, factor))
    bg: np.ndarray | None = None
    if view.background is not None:
        if callable(view.background):
            bg = np.asarray(view.background(cam), dtype=np.float32)
        else:
            bg = np.asarray(crop_and_downsample_image(np.asarray(view.background, np.float32), box, factor))
        if bg.shape != (cam.rows, cam.cols):
            raise ValueError(f"background of view {view.name!r} has shape {bg.shape}, expected ROI shape")
    return ViewROI(box=box, factor=factor, camera=cam, image=img.astype(np.float32), background=bg)
