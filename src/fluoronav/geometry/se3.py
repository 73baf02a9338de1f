"""Small float64 numpy helpers for rigid transforms (robot, tracker, calibration and navigation code).

The torch versions in :mod:`fluoronav.geometry.transforms` serve the differentiable pipeline; the
robot, tracker and OpenCV adapters work on float64 numpy arrays, where these avoid round trips.
Rotation angles are computed from the rotation vector (atan2-based in scipy), not ``acos`` of the
trace, so that angles of 1e-9 degrees are still resolved.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

__all__ = [
    "apply",
    "as_transform_array",
    "inv",
    "make",
    "mean_rotation",
    "project_to_so3",
    "rotation_angle_deg",
    "rotvec",
]


def as_transform_array(T: object, name: str = "transform") -> np.ndarray:
    """Float64 array of shape (..., 4, 4); raises ValueError for any other shape."""
    arr = np.asarray(T, dtype=np.float64)
    if arr.ndim < 2 or arr.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must have shape (..., 4, 4), got {arr.shape}")
    return arr


def make(R: ArrayLike, t: ArrayLike) -> np.ndarray:
    """(..., 3, 3) rotations and (..., 3) translations in mm → (..., 4, 4)."""
    Ra = np.asarray(R, dtype=np.float64)
    ta = np.asarray(t, dtype=np.float64)
    batch = np.broadcast_shapes(Ra.shape[:-2], ta.shape[:-1])
    T = np.zeros((*batch, 4, 4))
    T[..., :3, :3] = Ra
    T[..., :3, 3] = ta
    T[..., 3, 3] = 1.0
    return T


def inv(T: np.ndarray) -> np.ndarray:
    """Rigid inverse of (..., 4, 4) using Rᵀ."""
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    return make(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def rotvec(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) → (..., 3) rotation vectors in rad."""
    R = np.asarray(R, dtype=np.float64)
    flat = R.reshape(-1, 3, 3)
    return Rotation.from_matrix(flat).as_rotvec().reshape(*R.shape[:-2], 3)


def rotation_angle_deg(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) → (...) rotation angle in degrees, in [0, 180]."""
    return np.rad2deg(np.linalg.norm(rotvec(R), axis=-1))


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius) to each (..., 3, 3) matrix, via SVD with det = +1."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.zeros_like(M)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    return U @ D @ Vt


def mean_rotation(R: np.ndarray) -> np.ndarray:
    """Chordal L2 mean of rotations (N, 3, 3) → (3, 3)."""
    return project_to_so3(np.asarray(R, dtype=np.float64).mean(axis=0))


def apply(T: np.ndarray, p: ArrayLike) -> np.ndarray:
    """Apply a (4, 4) transform to (..., 3) points."""
    return np.asarray(p, np.float64) @ np.asarray(T)[:3, :3].T + np.asarray(T)[:3, 3]
