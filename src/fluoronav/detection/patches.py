"""Tube-aligned patches: the sampler of the refinement, tube-mask, mask-end and shaft stages.

Patches are small, aligned with the tube and at a fixed scale at the detector (``step_mm`` per patch
pixel). With ``rows × cols`` patch pixels, ``s`` input pixels per patch pixel, unit tangent ``t``
along the tube and normal ``n = (−t_v, t_u)``, patch pixel (col k, row j) samples the input at

    c + s·((k − (cols − 1)/2)·t + (j − (rows − 1)/2)·n)

so the patch's centre ``c`` is the point of interest and flipping the rows mirrors it exactly about the tube's
axis (the mirror test-time augmentation). At a landmark ``t`` points into the CM, to the mean of the mask's
pixels in a ring around it (:func:`landmark_direction`); on a centreline, A to B (:func:`tube_frames`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

__all__ = [
    "DIRECTION_RING_PATCH_PX",
    "RefinePatch",
    "bilinear",
    "footprint",
    "inside_length_px",
    "landmark_direction",
    "patch_grid_px",
    "polyline_frame",
    "refine_patch",
    "sample_patches",
    "tube_frames",
]

#: ring around a landmark, in patch pixels, whose mask pixels give the tube's direction
DIRECTION_RING_PATCH_PX = (8.0, 32.0)


@dataclass(frozen=True)
class RefinePatch:
    """A tube-aligned patch's frame.

    Attributes:
        center_px: (2,) (u, v) input pixels of the patch centre.
        tangent: (2,) unit vector (input pixels), along the tube, into the CM.
        step_px: input pixels per patch pixel.
        shape: (rows, cols) of the patch.
    """

    center_px: np.ndarray
    tangent: np.ndarray
    step_px: float
    shape: tuple[int, int]

    @property
    def normal(self) -> np.ndarray:
        return np.array([-self.tangent[1], self.tangent[0]])

    def shifted(self, along_px: float) -> RefinePatch:
        """The same frame with its centre moved ``along_px`` patch pixels along the tube (into the
        CM where positive)."""
        center = self.center_px + float(along_px) * self.step_px * self.tangent
        return RefinePatch(center, self.tangent, self.step_px, self.shape)

    def _origin(self) -> np.ndarray:
        rows, cols = self.shape
        return np.array([(cols - 1) / 2.0, (rows - 1) / 2.0])

    def to_input(self, points_patch: np.ndarray) -> np.ndarray:
        """(..., 2) (col, row) patch pixels → (..., 2) (u, v) input pixels."""
        q = np.asarray(points_patch, dtype=np.float64) - self._origin()
        return self.center_px + self.step_px * (q[..., :1] * self.tangent + q[..., 1:] * self.normal)

    def from_input(self, points_px: np.ndarray) -> np.ndarray:
        """(..., 2) (u, v) input pixels → (..., 2) (col, row) patch pixels."""
        d = (np.asarray(points_px, dtype=np.float64) - self.center_px) / self.step_px
        return np.stack([d @ self.tangent, d @ self.normal], axis=-1) + self._origin()

    def sample(self, image: np.ndarray) -> np.ndarray:
        """The (rows, cols) float32 patch of ``image`` (bilinear, edges repeated), zero mean and unit
        standard deviation (the image's units cancel: −log images of any dose or scale)."""
        rows, cols = self.shape
        jj, kk = np.mgrid[0:rows, 0:cols].astype(np.float64)
        uv = self.to_input(np.stack([kk, jj], axis=-1))
        v = ndimage.map_coordinates(
            np.asarray(image, dtype=np.float32), [uv[..., 1], uv[..., 0]], order=1, mode="nearest"
        )
        return ((v - v.mean()) / (v.std() + 1e-6)).astype(np.float32)


def landmark_direction(
    mask: np.ndarray, point_px: np.ndarray, *, ring_px: tuple[float, float]
) -> np.ndarray | None:
    """Unit vector (u, v) from ``point_px`` to the mean of the ``mask`` pixels at distance
    ``ring_px[0]``–``ring_px[1]`` from it (the CM's direction at one end), or None where fewer than
    5 mask pixels are in the ring."""
    # only the window around the ring: a full-size mask of a 1536² image is 2.4 M pixels
    r1 = ring_px[1]
    v0, u0 = max(int(np.floor(point_px[1] - r1)), 0), max(int(np.floor(point_px[0] - r1)), 0)
    v1, u1 = int(np.ceil(point_px[1] + r1)) + 1, int(np.ceil(point_px[0] + r1)) + 1
    vv, uu = np.nonzero(mask[v0:v1, u0:u1])
    vv, uu = vv + v0, uu + u0
    d = np.hypot(uu - point_px[0], vv - point_px[1])
    ring = (d >= ring_px[0]) & (d <= ring_px[1])
    if int(ring.sum()) < 5:
        return None
    vec = np.array([uu[ring].mean() - point_px[0], vv[ring].mean() - point_px[1]])
    norm = float(np.linalg.norm(vec))
    return vec / norm if norm > 1e-6 else None


def refine_patch(
    mask: np.ndarray, point_px: np.ndarray, *, step_px: float, shape: tuple[int, int]
) -> RefinePatch | None:
    """The patch frame around a landmark (its direction from ``mask``), or None where the mask
    gives no direction (a CM seen end-on, or a mask that ends at the landmark)."""
    lo, hi = DIRECTION_RING_PATCH_PX
    t = landmark_direction(mask, point_px, ring_px=(lo * step_px, hi * step_px))
    if t is None:
        return None
    return RefinePatch(np.asarray(point_px, dtype=np.float64), t, float(step_px), shape)


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


def bilinear(values: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear values of a 2-D array at (u = column, v = row) coordinates of any 2-D shape, edges
    repeated. ``cv2.remap`` (faster than ``ndimage.map_coordinates`` here), its weights
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
    with :func:`bilinear`'s 1/32-pixel weights)."""
    img = np.asarray(image, dtype=np.float32)
    v = np.stack([bilinear(img, uv[..., 0], uv[..., 1]) for uv in map(patch_grid_px, frames)])
    mean = v.mean(axis=(1, 2), keepdims=True)
    return ((v - mean) / (v.std(axis=(1, 2), keepdims=True) + 1e-6)).astype(np.float32)


def footprint(
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


def polyline_frame(points: np.ndarray, arc_px: float, *, chord_px: float) -> tuple[np.ndarray, np.ndarray]:
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
    """Tube-aligned patch frames (as :class:`RefinePatch`, tangent from A
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
        c, t = polyline_frame(pts, arc, chord_px=chord)
        frames.append(RefinePatch(c, t, float(step_px), shape))
    return frames


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
