"""Pinhole model of a C-arm (OpenCV convention) and camera files.

Conventions (see docs/conventions.md):

- Camera (C-arm) frame: origin at the X-ray source, +z from the source towards the detector,
  +x along increasing columns, +y along increasing rows. Units mm.
- Pixel coordinates (u, v) = (column, row), origin at the centre of the top-left pixel.
- ``K`` maps camera coordinates to homogeneous pixels: ``[u, v, 1]ᵀ ∝ K · [x, y, z]ᵀ``; for a flat
  panel at source-to-detector distance ``sdd_mm`` with square pixels of ``pixel_spacing_mm``,
  ``fx = fy = sdd_mm / pixel_spacing_mm``.
- ``camera_from_world`` (4×4, mm) maps world (the CT's LPS frame, or a scene frame) to camera coordinates.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fluoronav.errors import InputError

__all__ = [
    "CIOS_FUSION",
    "Camera",
    "DetectorSpec",
    "project_points",
    "stack_cameras",
    "triangulate_points",
    "triangulate_points_robust",
]


@dataclass(frozen=True)
class DetectorSpec:
    """A flat-panel C-arm's intrinsic geometry.

    Attributes:
        rows, cols: detector size in pixels.
        pixel_spacing_mm: isotropic pixel pitch at the detector, mm.
        sdd_mm: source-to-detector distance, mm.
        principal_point_px: (u, v) of the ray perpendicular to the panel; None = image centre.
    """

    rows: int
    cols: int
    pixel_spacing_mm: float
    sdd_mm: float
    principal_point_px: tuple[float, float] | None = None

    def K(self) -> np.ndarray:
        """3×3 intrinsic matrix in pixels."""
        f = self.sdd_mm / self.pixel_spacing_mm
        if self.principal_point_px is None:
            cx, cy = (self.cols - 1) / 2.0, (self.rows - 1) / 2.0
        else:
            cx, cy = self.principal_point_px
        return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


#: Siemens CIOS Fusion: 1536², 0.194 mm pixels, 1020 mm source-to-detector, centred principal point.
CIOS_FUSION = DetectorSpec(rows=1536, cols=1536, pixel_spacing_mm=0.194, sdd_mm=1020.0)


def _as_matrix(value: Any, shape: tuple[int, int], name: str, source: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(source, f"{name} is not a numeric matrix ({exc})") from None
    if arr.shape != shape:
        raise InputError(source, f"{name} must be {shape[0]}x{shape[1]}, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(source, f"{name} has non-finite entries")
    return arr


def _check_rigid(T: np.ndarray, name: str, source: str) -> None:
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0.99:
        raise InputError(source, f"{name} is not a rigid transform (rotation part not orthonormal)")
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9):
        raise InputError(source, f"{name} last row must be [0, 0, 0, 1]")


@dataclass(frozen=True, eq=False)
class Camera:
    """A projective camera: image size, intrinsics and pose.

    Attributes:
        rows, cols: image size in pixels.
        K: (3, 3) intrinsics in pixels (float64).
        camera_from_world: (4, 4) rigid transform, mm.
        pixel_spacing_mm: detector pixel pitch at this resolution (mm), if known; used to express
            image-plane errors in mm at the detector.
    """

    rows: int
    cols: int
    K: np.ndarray
    camera_from_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    pixel_spacing_mm: float | None = None

    def __post_init__(self) -> None:
        K = _as_matrix(self.K, (3, 3), "K", "camera")
        T = _as_matrix(self.camera_from_world, (4, 4), "camera_from_world", "camera")
        if int(self.rows) <= 0 or int(self.cols) <= 0:
            raise InputError("camera", f"image size must be positive, got {self.rows}x{self.cols}")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
            raise InputError("camera", "K must have positive focal lengths and last row [0, 0, 1]")
        _check_rigid(T, "camera_from_world", "camera")
        object.__setattr__(self, "rows", int(self.rows))
        object.__setattr__(self, "cols", int(self.cols))
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "camera_from_world", T)

    # ----- constructors -------------------------------------------------------------------
    @classmethod
    def from_detector(cls, spec: DetectorSpec, camera_from_world: np.ndarray | None = None) -> Camera:
        """Camera from a detector specification and an optional pose (identity by default)."""
        return cls(
            rows=spec.rows,
            cols=spec.cols,
            K=spec.K(),
            camera_from_world=np.eye(4) if camera_from_world is None else camera_from_world,
            pixel_spacing_mm=spec.pixel_spacing_mm,
        )

    # ----- derived quantities -------------------------------------------------------------
    @property
    def world_from_camera(self) -> np.ndarray:
        """(4, 4) inverse of ``camera_from_world``."""
        R = self.camera_from_world[:3, :3]
        t = self.camera_from_world[:3, 3]
        out = np.eye(4)
        out[:3, :3] = R.T
        out[:3, 3] = -R.T @ t
        return out

    @property
    def source_world(self) -> np.ndarray:
        """X-ray source position in world coordinates, mm, (3,)."""
        return self.world_from_camera[:3, 3].copy()

    @property
    def focal_length_px(self) -> float:
        """Mean focal length in pixels (source-to-detector distance over pixel spacing)."""
        return float(0.5 * (self.K[0, 0] + self.K[1, 1]))

    @property
    def sdd_mm(self) -> float | None:
        """Source-to-detector distance in mm, when the pixel spacing is known."""
        if self.pixel_spacing_mm is None:
            return None
        return self.focal_length_px * self.pixel_spacing_mm

    def tensors(
        self, *, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``(K (3,3), camera_from_world (4,4))`` as torch tensors."""
        return (
            torch.tensor(self.K, dtype=dtype, device=device),
            torch.tensor(self.camera_from_world, dtype=dtype, device=device),
        )

    @property
    def projection_matrix(self) -> np.ndarray:
        """(3, 4) world → homogeneous pixel matrix ``K [R | t]``."""
        return self.K @ self.camera_from_world[:3, :]

    # ----- projection ---------------------------------------------------------------------
    def project(self, points_world: np.ndarray) -> np.ndarray:
        """Project world points (..., 3) mm → pixels (..., 2) as (u, v)."""
        p = np.asarray(points_world, dtype=np.float64)
        cam = p @ self.camera_from_world[:3, :3].T + self.camera_from_world[:3, 3]
        uvw = cam @ self.K.T
        return uvw[..., :2] / uvw[..., 2:3]

    def to_camera(self, points_world: np.ndarray) -> np.ndarray:
        """World points (..., 3) → camera-frame points (..., 3), mm."""
        p = np.asarray(points_world, dtype=np.float64)
        return p @ self.camera_from_world[:3, :3].T + self.camera_from_world[:3, 3]

    def backproject(self, uv: np.ndarray, depth_mm: np.ndarray | float) -> np.ndarray:
        """Pixels (..., 2) at camera-frame depth z (mm) → world points (..., 3)."""
        uv = np.asarray(uv, dtype=np.float64)
        ones = np.ones((*uv.shape[:-1], 1))
        dirs = np.concatenate([uv, ones], axis=-1) @ np.linalg.inv(self.K).T  # z = 1
        cam = dirs * np.asarray(depth_mm, dtype=np.float64)[..., None]
        return cam @ self.world_from_camera[:3, :3].T + self.world_from_camera[:3, 3]

    def pixel_grid(self) -> np.ndarray:
        """(rows, cols, 2) pixel centres as (u, v)."""
        v, u = np.meshgrid(
            np.arange(self.rows, dtype=np.float64), np.arange(self.cols, dtype=np.float64), indexing="ij"
        )
        return np.stack([u, v], axis=-1)

    def ray_directions_world(self, uv: np.ndarray | None = None) -> np.ndarray:
        """Unit ray directions in world coordinates from the source through pixels.

        Args:
            uv: (..., 2) pixels; defaults to every pixel centre, giving (rows, cols, 3).
        """
        if uv is None:
            uv = self.pixel_grid()
        uv = np.asarray(uv, dtype=np.float64)
        ones = np.ones((*uv.shape[:-1], 1))
        d_cam = np.concatenate([uv, ones], axis=-1) @ np.linalg.inv(self.K).T
        d_world = d_cam @ self.world_from_camera[:3, :3].T
        return d_world / np.linalg.norm(d_world, axis=-1, keepdims=True)

    # ----- operations on the camera -------------------------------------------------------
    def with_pose(self, camera_from_world: np.ndarray) -> Camera:
        """The same intrinsics at another pose."""
        return Camera(self.rows, self.cols, self.K, camera_from_world, self.pixel_spacing_mm)

    def crop(self, *, row0: int, col0: int, rows: int, cols: int) -> Camera:
        """Camera of the sub-image ``[row0:row0+rows, col0:col0+cols]`` (may extend past the edges)."""
        K = self.K.copy()
        K[0, 2] -= col0
        K[1, 2] -= row0
        return Camera(rows, cols, K, self.camera_from_world, self.pixel_spacing_mm)

    def crop_around(
        self, center_uv: np.ndarray | tuple[float, float], size: int | tuple[int, int]
    ) -> tuple[Camera, tuple[int, int]]:
        """Crop of ``size`` (rows, cols) centred on pixel ``center_uv``; returns (camera, (row0, col0))."""
        rows, cols = (size, size) if isinstance(size, int) else size
        col0 = round(float(center_uv[0]) - (cols - 1) / 2.0)
        row0 = round(float(center_uv[1]) - (rows - 1) / 2.0)
        return self.crop(row0=row0, col0=col0, rows=rows, cols=cols), (row0, col0)

    def downsample(self, factor: int) -> Camera:
        """Camera of the image binned by ``factor`` × ``factor`` (trailing pixels dropped).

        A binned pixel covers ``factor`` original pixels, so the new pixel centre ``u'`` sits at
        ``u = factor·u' + (factor − 1)/2`` in the original image.
        """
        if factor < 1 or int(factor) != factor:
            raise ValueError(f"downsampling factor must be a positive integer, got {factor}")
        f = int(factor)
        S = np.array([[1.0 / f, 0.0, -(f - 1) / (2.0 * f)], [0.0, 1.0 / f, -(f - 1) / (2.0 * f)], [0, 0, 1]])
        ps = None if self.pixel_spacing_mm is None else self.pixel_spacing_mm * f
        return Camera(self.rows // f, self.cols // f, S @ self.K, self.camera_from_world, ps)

    def scaled_to(self, rows: int, cols: int) -> Camera:
        """Camera of the same field of view resampled to ``rows`` × ``cols`` (pixel-area aligned)."""
        sx, sy = cols / self.cols, rows / self.rows
        S = np.array([[sx, 0.0, 0.5 * (sx - 1.0)], [0.0, sy, 0.5 * (sy - 1.0)], [0, 0, 1]])
        ps = None if self.pixel_spacing_mm is None else self.pixel_spacing_mm / math.sqrt(sx * sy)
        return Camera(rows, cols, S @ self.K, self.camera_from_world, ps)

    # ----- files --------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready camera-file dict (rows, cols, K, camera_from_world, + pixel_spacing_mm)."""
        d: dict[str, Any] = {
            "rows": self.rows,
            "cols": self.cols,
            "K": self.K.tolist(),
            "camera_from_world": self.camera_from_world.tolist(),
        }
        if self.pixel_spacing_mm is not None:
            d["pixel_spacing_mm"] = float(self.pixel_spacing_mm)
        return d

    @classmethod
    def from_dict(cls, d: Any, *, source: str = "camera") -> Camera:
        """Parse and validate a camera dict; errors name ``source``."""
        if not isinstance(d, dict):
            raise InputError(source, "camera must be a JSON object")
        missing = [k for k in ("rows", "cols", "K", "camera_from_world") if k not in d]
        if missing:
            raise InputError(source, f"camera is missing {', '.join(missing)}")
        try:
            rows, cols = int(d["rows"]), int(d["cols"])
        except (TypeError, ValueError, OverflowError):
            raise InputError(source, "rows and cols must be integers") from None
        if rows <= 0 or cols <= 0 or rows != d["rows"] or cols != d["cols"]:
            raise InputError(source, f"rows and cols must be positive integers, got {d['rows']}x{d['cols']}")
        K = _as_matrix(d["K"], (3, 3), "K", source)
        T = _as_matrix(d["camera_from_world"], (4, 4), "camera_from_world", source)
        _check_rigid(T, "camera_from_world", source)
        ps = d.get("pixel_spacing_mm")
        if ps is not None:
            if not isinstance(ps, int | float) or not math.isfinite(ps) or ps <= 0:
                raise InputError(source, "pixel_spacing_mm must be a positive number")
            ps = float(ps)
        try:
            return cls(rows, cols, K, T, ps)
        except InputError as exc:
            raise InputError(source, exc.problem) from None

    def save(self, path: str | Path) -> None:
        """Write a camera file (JSON)."""
        Path(path).write_text(json.dumps(self.to_dict(), indent=2), encoding="utf-8")

    @classmethod
    def load(cls, path: str | Path) -> Camera:
        """Read and validate a camera file (JSON)."""
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise InputError(p, f"cannot read camera file ({exc.__class__.__name__})") from None
        if not text.strip():
            raise InputError(p, "camera file is empty")
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(p, f"camera file is not valid JSON ({exc.msg} at line {exc.lineno})") from None
        return cls.from_dict(d, source=str(p))


def stack_cameras(
    cameras: list[Camera] | tuple[Camera, ...],
    *,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Batch cameras of one image size: ``(K (V,3,3), camera_from_world (V,4,4))``."""
    if not cameras:
        raise ValueError("need at least one camera")
    if len({(c.rows, c.cols) for c in cameras}) != 1:
        raise ValueError("cameras in one batch must share rows and cols")
    K = torch.tensor(np.stack([c.K for c in cameras]), dtype=dtype, device=device)
    T = torch.tensor(np.stack([c.camera_from_world for c in cameras]), dtype=dtype, device=device)
    return K, T


def triangulate_points(cameras: Sequence[Camera], uv: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of points seen in several views.

    Args:
        cameras: V ≥ 2 cameras in one world frame.
        uv: (V, N, 2) pixel positions (u, v) of N points in each view.

    Returns:
        (N, 3) world points (mm) minimising the algebraic error of ``u·P₃ − P₁``, ``v·P₃ − P₂``
        over the views (rows scaled to unit norm so that no view dominates by its focal length).

    Raises:
        ValueError: fewer than two views or mismatched shapes.
    """
    uv = np.asarray(uv, dtype=np.float64)
    if len(cameras) < 2 or uv.ndim != 3 or uv.shape[0] != len(cameras) or uv.shape[2] != 2:
        raise ValueError(f"need (V ≥ 2, N, 2) pixels for {len(cameras)} cameras, got {uv.shape}")
    P = np.stack([c.projection_matrix for c in cameras])  # (V, 3, 4)
    out = np.empty((uv.shape[1], 3))
    for n in range(uv.shape[1]):  # N is a handful of landmarks
        rows = np.concatenate(
            [uv[:, n, 0:1] * P[:, 2] - P[:, 0], uv[:, n, 1:2] * P[:, 2] - P[:, 1]], axis=0
        )  # (2V, 4)
        rows /= np.linalg.norm(rows, axis=1, keepdims=True)
        _, _, vt = np.linalg.svd(rows)
        X = vt[-1]
        out[n] = X[:3] / X[3]
    return out


def triangulate_points_robust(
    cameras: Sequence[Camera], uv: np.ndarray, *, max_residual_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangulation that drops views whose pixel disagrees with the others (a wrong detection).

    Each point is triangulated from all views (:func:`triangulate_points`); while the largest
    reprojection residual exceeds ``max_residual_px`` and more than two views remain, the view whose
    removal leaves the smallest largest residual is dropped. With two views nothing can be told
    apart: both are kept whatever their residuals.

    Args:
        cameras: V ≥ 2 cameras in one world frame.
        uv: (V, N, 2) pixel positions.
        max_residual_px: largest acceptable reprojection error (the cameras' pixels).

    Returns:
        ``(points (N, 3) mm, inliers (V, N) bool, residuals_px (V, N))``: residuals of every view
        (dropped ones too) against the final points.
    """
    uv = np.asarray(uv, dtype=np.float64)
    pts = triangulate_points(cameras, uv)
    V, N = uv.shape[:2]
    inliers = np.ones((V, N), dtype=bool)

    def residuals(X: np.ndarray, n: int) -> np.ndarray:  # (V,) of point n
        return np.array([np.linalg.norm(c.project(X[None])[0] - uv[v, n]) for v, c in enumerate(cameras)])

    for n in range(N):
        keep = list(range(V))
        res = residuals(pts[n], n)
        while len(keep) > 2 and res[keep].max() > max_residual_px:
            trials = []
            for sub in combinations(keep, len(keep) - 1):
                X = triangulate_points([cameras[v] for v in sub], uv[list(sub)][:, n : n + 1])[0]
                r = residuals(X, n)
                trials.append((float(r[list(sub)].max()), sub, X, r))
            _, sub, X, res = min(trials, key=lambda t: t[0])
            keep, pts[n] = list(sub), X
        inliers[:, n] = np.isin(np.arange(V), keep)
    res_all = np.stack([residuals(pts[n], n) for n in range(N)], axis=1) if N else np.zeros((V, 0))
    return pts, inliers, res_all


def project_points(K: torch.Tensor, camera_from_world: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Batched pinhole projection in torch.

    Args:
        K: (..., 3, 3) intrinsics.
        camera_from_world: (..., 4, 4).
        points: (..., N, 3) world points, mm.

    Returns:
        (..., N, 2) pixels (u, v).
    """
    cam = points @ camera_from_world[..., :3, :3].transpose(-1, -2) + camera_from_world[..., None, :3, 3]
    uvw = cam @ K.transpose(-1, -2)
    return uvw[..., :2] / uvw[..., 2:3]
