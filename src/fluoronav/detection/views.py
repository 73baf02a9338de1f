"""The view sampler of the coarse and fine stages: square resampled windows ("views") of a detector
image and robust per-view intensity normalisation.

A :class:`View` maps its own pixel grid (``size`` × ``size``) onto a square window of ``side`` input
pixels whose top-left pixel *edge* is at ``(x0, y0)``. With the pixel-centre convention (origin at the
centre of the top-left pixel) a point maps as ``u_in = x0 + (u_view + 0.5)·s − 0.5`` with
``s = side / size``. Resampling uses area averaging when shrinking and bilinear interpolation when
enlarging (both follow that convention in OpenCV); samples outside the image repeat the edge.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class View:
    """A square window of ``side`` input pixels at edge corner ``(x0, y0)``, resampled to ``size``²."""

    x0: int
    y0: int
    side: int
    size: int

    @property
    def scale(self) -> float:
        """Input pixels per view pixel."""
        return self.side / self.size

    def to_input(self, uv: np.ndarray) -> np.ndarray:
        """View pixel coordinates (..., 2) (u, v) → input pixel coordinates (..., 2)."""
        uv = np.asarray(uv, dtype=np.float64)
        return np.array([self.x0, self.y0], dtype=np.float64) + (uv + 0.5) * self.scale - 0.5

    def from_input(self, uv: np.ndarray) -> np.ndarray:
        """Input pixel coordinates (..., 2) (u, v) → view pixel coordinates (..., 2)."""
        uv = np.asarray(uv, dtype=np.float64)
        return (uv - np.array([self.x0, self.y0], dtype=np.float64) + 0.5) / self.scale - 0.5


def full_view(shape: tuple[int, int], size: int, *, min_side_px: float = 0.0) -> View:
    """The view of a whole (rows, cols) image: isotropic, padded at the right/bottom to a square.

    With ``min_side_px`` above the longer side the window is that wide instead (rounded), centred on the
    image (a small field of view shown at the scale of a larger one; outside the image the edge
    pixels repeat, see :func:`resample`).
    """
    rows, cols = int(shape[0]), int(shape[1])
    side = max(rows, cols)
    wide = round(min_side_px)
    if wide > side:
        return View((cols - wide) // 2, (rows - wide) // 2, wide, int(size))
    return View(0, 0, side, int(size))


def roi_view(
    points_uv: np.ndarray,
    size: int,
    *,
    margin_frac: float = 0.25,
    min_side_px: float = 16.0,
    scale_factor: float = 1.0,
    shift_frac: tuple[float, float] = (0.0, 0.0),
) -> View:
    """A square view around the bounding box of ``points_uv`` (N, 2) in input pixels.

    Args:
        points_uv: points (N, 2) (u, v) the window must contain (mask pixels, landmarks).
        size: view size in pixels.
        margin_frac: margin added on each side, as a fraction of the box's longer extent.
        min_side_px: smallest window side in input pixels.
        scale_factor: multiplies the side (training jitter).
        shift_frac: shift of the centre as a fraction of the side (training jitter).
    """
    pts = np.asarray(points_uv, dtype=np.float64).reshape(-1, 2)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    extent = float(np.max(hi - lo)) + 1.0
    side = max(extent * (1.0 + 2.0 * margin_frac), min_side_px) * scale_factor
    side_i = max(round(side), 2)
    centre = (lo + hi) / 2.0 + np.asarray(shift_frac) * side_i
    x0, y0 = np.round(centre + 0.5 - side_i / 2.0).astype(int)
    return View(int(x0), int(y0), side_i, int(size))


def resample(image: np.ndarray, view: View) -> np.ndarray:
    """Resample a (rows, cols) array onto the view grid → (size, size) float32."""
    img: np.ndarray = np.asarray(image, dtype=np.float32)
    rows, cols = img.shape
    x1, y1 = view.x0 + view.side, view.y0 + view.side
    crop: np.ndarray
    if view.x0 >= 0 and view.y0 >= 0 and x1 <= cols and y1 <= rows:
        crop = img[view.y0 : y1, view.x0 : x1]
    else:  # outside the image: repeat the edge pixels
        r = np.clip(np.arange(view.y0, y1), 0, rows - 1)
        c = np.clip(np.arange(view.x0, x1), 0, cols - 1)
        crop = img[np.ix_(r, c)]
    if view.side == view.size:
        return np.ascontiguousarray(crop, dtype=np.float32)
    interp = cv2.INTER_AREA if view.side > view.size else cv2.INTER_LINEAR
    return cv2.resize(crop, (view.size, view.size), interpolation=interp)


def paste(
    values: np.ndarray,
    view: View,
    shape: tuple[int, int],
    *,
    fill: float = 0.0,
    box: tuple[int, int, int, int] | None = None,
) -> np.ndarray:
    """Inverse of :func:`resample`: bilinear map of view values (size, size) onto a (rows, cols) grid.

    Pixels outside the window get ``fill``. With ``box`` = (x0, y0, x1, y1) (input pixels, end
    exclusive, inside the grid) only that part of the grid is returned, (y1 − y0, x1 − x0).
    """
    rows, cols = shape
    bx0, by0, bx1, by1 = (0, 0, cols, rows) if box is None else box
    out = np.full((by1 - by0, bx1 - bx0), fill, dtype=np.float32)
    cx0, cy0 = max(view.x0, bx0), max(view.y0, by0)
    cx1, cy1 = min(view.x0 + view.side, bx1), min(view.y0 + view.side, by1)
    if cx1 <= cx0 or cy1 <= cy0:
        return out
    vals: np.ndarray = np.asarray(values, dtype=np.float32)
    if view.side != view.size:
        vals = cv2.resize(vals, (view.side, view.side), interpolation=cv2.INTER_LINEAR)
    out[cy0 - by0 : cy1 - by0, cx0 - bx0 : cx1 - bx0] = vals[
        cy0 - view.y0 : cy1 - view.y0, cx0 - view.x0 : cx1 - view.x0
    ]
    return out


def normalize_intensity(image: np.ndarray, *, low_pct: float = 1.0, high_pct: float = 99.0) -> np.ndarray:
    """Robust per-image normalisation: the ``low_pct``/``high_pct`` percentiles map to 0/1.

    Values are not clipped (bright metal may exceed 1); a flat image maps to zeros.
    """
    img = np.asarray(image, dtype=np.float32)
    lo, hi = np.percentile(img, [low_pct, high_pct])
    span = float(hi - lo)
    if not np.isfinite(span) or span <= 1e-12:
        return np.zeros_like(img)
    return (img - np.float32(lo)) / np.float32(span)


def scaled_view(view: View, factor: float) -> View:
    """The view with its side × ``factor`` about the same centre (same output size)."""
    side = max(round(view.side * factor), 2)
    return View(
        round(view.x0 + (view.side - side) / 2.0), round(view.y0 + (view.side - side) / 2.0), side, view.size
    )


def view_input(image: np.ndarray, view: View, *, low_pct: float, high_pct: float) -> np.ndarray:
    """The network input (size, size) float32 of ``view`` on an image (rows, cols):
    :func:`resample`, then :func:`normalize_intensity`."""
    return normalize_intensity(resample(image, view), low_pct=low_pct, high_pct=high_pct)
