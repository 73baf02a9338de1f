"""Rotation parameterisations in torch (batched): rotation vectors, quaternions, Euler angles.

Rotation vectors are in radians; the ``*_deg`` helpers take degrees. Quaternions are (x, y, z, w),
as roma. Euler angles follow scipy's convention strings (upper case = intrinsic).
"""

from __future__ import annotations

import math
from types import ModuleType

import torch

__all__ = [
    "angle_between_rotations_deg",
    "axis_angle_to_matrix",
    "euler_to_matrix",
    "matrix_to_quat",
    "matrix_to_rotvec",
    "quat_to_matrix",
    "random_rotation_about_random_axis",
    "rotvec_to_matrix",
    "rotx",
    "roty",
    "rotz",
]


def _roma() -> ModuleType:
    """roma, imported at first use: its import loads ``torch._dynamo``, slower than ``torch`` itself."""
    import roma

    return roma


def rotvec_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """(..., 3) rotation vectors in rad → (..., 3, 3) rotation matrices."""
    return _roma().rotvec_to_rotmat(rotvec)


def matrix_to_rotvec(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices → (..., 3) rotation vectors in rad, angle in [0, π]."""
    return _roma().rotmat_to_rotvec(R)


def quat_to_matrix(q_xyzw: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternions (x, y, z, w), normalised here → (..., 3, 3)."""
    return _roma().unitquat_to_rotmat(q_xyzw / q_xyzw.norm(dim=-1, keepdim=True))


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) → (..., 4) unit quaternions (x, y, z, w) with w ≥ 0."""
    q = _roma().rotmat_to_unitquat(R)
    return torch.where(q[..., 3:4] < 0, -q, q)


def euler_to_matrix(convention: str, angles_deg: torch.Tensor) -> torch.Tensor:
    """Euler angles in degrees (..., len(convention)) → (..., 3, 3), scipy's convention strings."""
    return _roma().euler_to_rotmat(convention, angles_deg, degrees=True)


def axis_angle_to_matrix(axis: torch.Tensor, angle_rad: torch.Tensor) -> torch.Tensor:
    """Unit-normalised axis (..., 3) and angle (...) in rad → (..., 3, 3)."""
    axis = axis / axis.norm(dim=-1, keepdim=True)
    return rotvec_to_matrix(axis * angle_rad.unsqueeze(-1))


def _elementary(angle_rad: torch.Tensor, i: int, j: int) -> torch.Tensor:
    c, s = torch.cos(angle_rad), torch.sin(angle_rad)
    R = torch.zeros(*angle_rad.shape, 3, 3, dtype=angle_rad.dtype, device=angle_rad.device)
    k = 3 - i - j
    R[..., k, k] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def rotx(angle_rad: torch.Tensor) -> torch.Tensor:
    """Rotation about +x by ``angle_rad`` (...) → (..., 3, 3)."""
    return _elementary(angle_rad, 1, 2)


def roty(angle_rad: torch.Tensor) -> torch.Tensor:
    """Rotation about +y by ``angle_rad`` (...) → (..., 3, 3)."""
    return _elementary(angle_rad, 2, 0)


def rotz(angle_rad: torch.Tensor) -> torch.Tensor:
    """Rotation about +z by ``angle_rad`` (...) → (..., 3, 3)."""
    return _elementary(angle_rad, 0, 1)


def angle_between_rotations_deg(Ra: torch.Tensor, Rb: torch.Tensor) -> torch.Tensor:
    """Geodesic angle in degrees between rotations (..., 3, 3)."""
    rel = Ra.transpose(-1, -2) @ Rb
    cos = ((rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.acos(cos))


def random_rotation_about_random_axis(
    generator: torch.Generator, n: int, *, max_angle_deg: float, dtype: torch.dtype = torch.float64
) -> torch.Tensor:
    """Rotations about uniformly random unit axes with angles U(−max, max) degrees → (n, 3, 3).

    This is the perturbation model of the paper's simulation protocol.
    """
    axis = torch.randn(n, 3, generator=generator, dtype=dtype)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = (torch.rand(n, generator=generator, dtype=dtype) * 2.0 - 1.0) * math.radians(max_angle_deg)
    return axis_angle_to_matrix(axis, angle)
