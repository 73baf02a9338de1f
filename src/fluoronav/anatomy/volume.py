"""A CT (or any scalar) volume in a physical frame, with optional labels and landmarks.

Array order is SimpleITK's ``GetArrayFromImage`` order, ``data[k, j, i]`` = (z, y, x) index. The
geometry follows ITK: the world (LPS, mm) position of voxel index ``(i, j, k)`` is
``origin + direction · diag(spacing) · (i, j, k)``, which :attr:`Volume.world_from_index` holds
as a 4×4 matrix acting on ``(i, j, k, 1)``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Volume", "hu_to_mu"]

#: Linear attenuation of water at ~60 keV effective energy in 1/mm (a common DRR default).
MU_WATER_PER_MM = 0.02


def hu_to_mu(hu: np.ndarray, mu_water_per_mm: float = MU_WATER_PER_MM) -> np.ndarray:
    """Hounsfield units → linear attenuation (1/mm): ``μ = μ_water · max(0, 1 + HU/1000)``."""
    return (mu_water_per_mm * np.maximum(0.0, 1.0 + np.asarray(hu, dtype=np.float32) / 1000.0)).astype(
        np.float32
    )


@dataclass(frozen=True, eq=False)
class Volume:
    """A scalar volume with ITK geometry.

    Attributes:
        data: (nz, ny, nx) array (HU for CTs).
        spacing_mm: (sx, sy, sz) voxel size along i, j, k.
        origin_mm: world position of voxel (0, 0, 0)'s centre.
        direction: (3, 3) direction cosines (columns = world directions of the i, j, k axes).
        labels: optional (nz, ny, nx) integer label map on the same grid.
        label_names: label value → name (e.g. ``{1: "pelvis", 2: "femur_left", 3: "femur_right"}``).
        landmarks_world: name → (3,) world point in mm (e.g. ``"femoral_head_left"``, ``"entry_left"``).
        name: a short name for the volume (file stem or ``phantom-<seed>``).
    """

    data: np.ndarray
    spacing_mm: tuple[float, float, float]
    origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    direction: np.ndarray = field(default_factory=lambda: np.eye(3))
    labels: np.ndarray | None = None
    label_names: dict[int, str] = field(default_factory=dict)
    landmarks_world: dict[str, np.ndarray] = field(default_factory=dict)
    name: str = "volume"

    def __post_init__(self) -> None:
        if self.data.ndim != 3:
            raise ValueError(f"volume data must be 3D, got shape {self.data.shape}")
        if self.labels is not None and self.labels.shape != self.data.shape:
            raise ValueError("labels must have the same shape as data")
        object.__setattr__(self, "spacing_mm", tuple(float(s) for s in self.spacing_mm))
        object.__setattr__(self, "origin_mm", tuple(float(s) for s in self.origin_mm))
        object.__setattr__(self, "direction", np.asarray(self.direction, dtype=np.float64).reshape(3, 3))

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        """(nx, ny, nz)."""
        nz, ny, nx = self.data.shape
        return nx, ny, nz

    @property
    def world_from_index(self) -> np.ndarray:
        """(4, 4) map from continuous index (i, j, k, 1) to world mm."""
        T = np.eye(4)
        T[:3, :3] = self.direction @ np.diag(self.spacing_mm)
        T[:3, 3] = self.origin_mm
        return T

    @property
    def index_from_world(self) -> np.ndarray:
        """(4, 4) inverse of :attr:`world_from_index`."""
        return np.linalg.inv(self.world_from_index)

    @property
    def center_world(self) -> np.ndarray:
        """World position of the volume's geometric centre, mm."""
        idx = (np.asarray(self.shape_xyz, dtype=np.float64) - 1.0) / 2.0
        return (self.world_from_index @ np.append(idx, 1.0))[:3]

    def corners_world(self) -> np.ndarray:
        """(8, 3) world positions of the outer corners of the voxel grid (half a voxel beyond centres)."""
        nx, ny, nz = self.shape_xyz
        c = np.array(
            [[i, j, k] for i in (-0.5, nx - 0.5) for j in (-0.5, ny - 0.5) for k in (-0.5, nz - 0.5)]
        )
        return c @ self.world_from_index[:3, :3].T + self.world_from_index[:3, 3]

    def label_value(self, name: str) -> int | None:
        """Label value for a name, or None."""
        for value, n in self.label_names.items():
            if n == name:
                return value
        return None

    def replace(self, **changes: object) -> Volume:
        """A copy with some fields replaced."""
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]
