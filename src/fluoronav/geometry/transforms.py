"""Batched rigid transforms as homogeneous 4×4 matrices (torch, float32 or float64).

Naming: a transform ``a_from_b`` maps coordinates in frame ``b`` to frame ``a``; compose right to
left, ``a_from_c = a_from_b @ b_from_c``. Translations are in mm.
"""

from __future__ import annotations

import numpy as np
import torch

from fluoronav.geometry.rotations import matrix_to_rotvec, rotvec_to_matrix

__all__ = [
    "apply_transform",
    "as_tensor",
    "compose",
    "invert_transform",
    "make_transform",
    "params_from_transform",
    "rotation_about_point",
    "transform_from_params",
]


def as_tensor(
    x: torch.Tensor | np.ndarray | list,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """``torch.as_tensor`` that keeps float64 numpy input as float64 unless ``dtype`` is given."""
    return torch.as_tensor(np.asarray(x) if isinstance(x, list) else x, dtype=dtype, device=device)


def make_transform(rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """Build homogeneous transforms.

    Args:
        rotation: (..., 3, 3) rotation matrices.
        translation: (..., 3) translations in mm.

    Returns:
        (..., 4, 4) transforms.
    """
    batch = torch.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    T = torch.zeros(*batch, 4, 4, dtype=rotation.dtype, device=rotation.device)
    T[..., :3, :3] = rotation
    T[..., :3, 3] = translation
    T[..., 3, 3] = 1.0
    return T


def invert_transform(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms (..., 4, 4), using Rᵀ rather than a general matrix inverse."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    Rt = R.transpose(-1, -2)
    return make_transform(Rt, -(Rt @ t.unsqueeze(-1)).squeeze(-1))


def apply_transform(T: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Apply transforms (..., 4, 4) to points (..., N, 3); batch dimensions broadcast."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    return points @ R.transpose(-1, -2) + t.unsqueeze(-2)


def compose(*transforms: torch.Tensor) -> torch.Tensor:
    """Compose transforms right to left: ``compose(a_from_b, b_from_c) == a_from_c``."""
    if not transforms:
        raise ValueError("compose needs at least one transform")
    out = transforms[0]
    for T in transforms[1:]:
        out = out @ T
    return out


def rotation_about_point(rotation: torch.Tensor, center: torch.Tensor) -> torch.Tensor:
    """Transform (..., 4, 4) that rotates by ``rotation`` (..., 3, 3) about ``center`` (..., 3) mm."""
    t = center - (rotation @ center.unsqueeze(-1)).squeeze(-1)
    return make_transform(rotation, t)


def transform_from_params(params: torch.Tensor) -> torch.Tensor:
    """Transforms from 6-vectors ``(rx, ry, rz, tx, ty, tz)``: rotation vector in rad, translation mm.

    Args:
        params: (..., 6).

    Returns:
        (..., 4, 4).
    """
    return make_transform(rotvec_to_matrix(params[..., :3]), params[..., 3:6])


def params_from_transform(T: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`transform_from_params`: (..., 4, 4) → (..., 6)."""
    return torch.cat([matrix_to_rotvec(T[..., :3, :3]), T[..., :3, 3]], dim=-1)
