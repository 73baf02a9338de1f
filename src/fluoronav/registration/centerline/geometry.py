"""Geometry of the CM's A→B chord: candidate poses from (depth, roll, branch), turns about the chord
and the roll error about it (Gao et al., IEEE TBME 69(1), 2022, sec. II-B).

Conventions (see :mod:`fluoronav.registration.centerline`): ``depth_mm`` (d_A) is the
camera-frame z of landmark A, ``theta_deg`` (θ) the roll of the CM about the chord A→B, θ = 0 where
the CM's x axis (the normal of its bending plane) is along ``r_A × (B3D − A3D)``; ``branch`` 0 / 1
is the near / far root of B on its ray.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from fluoronav.geometry.rotations import matrix_to_quat
from fluoronav.geometry.transforms import make_transform
from fluoronav.manipulator import CMConfig, CMKinematics

__all__ = [
    "cm_basis",
    "mirror_about_chord",
    "normalize",
    "poses_from_depth_theta",
    "roll_about_axis_deg",
    "roll_of_pose",
    "turn_about_chord",
]


def normalize(v: torch.Tensor) -> torch.Tensor:
    """``v`` (..., 3) scaled to unit length along the last dim (zero vectors stay finite)."""
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-300)


def cm_basis(chord_cm: torch.Tensor) -> torch.Tensor:
    """(3,) chord A→B in the CM frame → (3, 3) orthonormal columns [chord, x', chord × x']."""
    u = normalize(chord_cm)
    x = torch.tensor([1.0, 0.0, 0.0], dtype=u.dtype, device=u.device)
    if float(torch.linalg.cross(u, x).norm()) < 1e-6:  # a chord along x cannot happen for a planar CM
        x = torch.tensor([0.0, 1.0, 0.0], dtype=u.dtype, device=u.device)
    n = normalize(x - (x @ u) * u)
    return torch.stack([u, n, torch.linalg.cross(u, n)], dim=-1)


def poses_from_depth_theta(
    ray_a: torch.Tensor,
    ray_b: torch.Tensor,
    landmarks_cm: torch.Tensor,
    depth_mm: torch.Tensor,
    theta_deg: torch.Tensor,
    branch: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Candidate poses from (d_A, θ, branch), batched.

    Args:
        ray_a: (3,) ``K⁻¹ [u_A, v_A, 1]`` (camera frame, z = 1).
        ray_b: (3,) ``K⁻¹ [u_B, v_B, 1]`` (any positive scale).
        landmarks_cm: (2, 3) model landmarks A, B in the CM frame, mm.
        depth_mm: (N,) camera-frame z of A.
        theta_deg: (N,) roll about the chord.
        branch: (N,) 0 = near root, 1 = far root for B on its ray.

    Returns:
        ``camera_from_cm`` (N, 4, 4) and ``feasible`` (N,) bool (real root in front of the source).
        Infeasible rows hold a valid rigid transform built from the clamped root; ignore them.
    """
    a_cm, b_cm = landmarks_cm[0], landmarks_cm[1]
    length = (b_cm - a_cm).norm()
    rb = normalize(ray_b)
    A = depth_mm.unsqueeze(-1) * ray_a  # (N, 3)
    proj = A @ rb  # (N,)
    disc = length**2 - ((A * A).sum(-1) - proj**2)
    sign = torch.where(branch > 0, 1.0, -1.0).to(A.dtype)
    t = proj + sign * disc.clamp_min(0.0).sqrt()
    feasible = (disc >= 0.0) & (t > 0.0)
    B = t.unsqueeze(-1) * rb
    u = normalize(B - A)
    ref = torch.linalg.cross(ray_a.expand_as(u), u)
    ref = normalize(ref)
    th = torch.deg2rad(theta_deg).unsqueeze(-1)
    e2 = torch.cos(th) * ref + torch.sin(th) * torch.linalg.cross(u, ref)
    cam_basis = torch.stack([u, e2, torch.linalg.cross(u, e2)], dim=-1)  # (N, 3, 3)
    R = cam_basis @ cm_basis(b_cm - a_cm).T
    trans = A - (R @ a_cm.unsqueeze(-1)).squeeze(-1)
    return make_transform(R, trans), feasible


def roll_of_pose(camera_from_cm: np.ndarray, ray_a: torch.Tensor, landmarks_cm: torch.Tensor) -> float:
    """θ (degrees, [0, 360)) of a (4, 4) pose in the convention of :func:`poses_from_depth_theta`."""
    R = torch.as_tensor(camera_from_cm[:3, :3], dtype=ray_a.dtype, device=ray_a.device)
    basis = R @ cm_basis(landmarks_cm[1] - landmarks_cm[0])  # [u, e2, u × e2] in the camera
    u, e2 = basis[:, 0], basis[:, 1]
    ref = normalize(torch.linalg.cross(ray_a, u))
    return math.degrees(math.atan2(float(e2 @ torch.linalg.cross(u, ref)), float(e2 @ ref))) % 360.0


def turn_about_chord(
    world_from_cm: np.ndarray,
    control_points_deg: np.ndarray,
    angle_deg: float,
    config: CMConfig | None = None,
) -> np.ndarray:
    """The CM pose turned by ``angle_deg`` about its A→B chord: A and B stay put (on their rays), the
    bending plane turns. (4, 4), same frame as ``world_from_cm``."""
    kin = CMKinematics(config or CMConfig())
    ab = kin.landmarks_cm(torch.as_tensor(control_points_deg, dtype=torch.float64)).numpy()
    axis = ab[1] - ab[0]
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec(math.radians(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()
    turn[:3, 3] = ab[0] - turn[:3, :3] @ ab[0]
    return np.asarray(world_from_cm, dtype=np.float64) @ turn


def mirror_about_chord(
    world_from_cm: np.ndarray, control_points_deg: np.ndarray, config: CMConfig | None = None
) -> np.ndarray:
    """The CM pose turned 180° about its A→B chord: A and B stay put, the bending plane flips.

    A centreline seen in one view hardly tells these two apart (the paper's θ ambiguity), so both are
    worth a start.

    Args:
        world_from_cm: (4, 4) CM base pose (any frame).
        control_points_deg: (5,) shape.
        config: CM geometry (default :class:`CMConfig`).

    Returns:
        (4, 4) the mirrored pose, same frame.
    """
    return turn_about_chord(world_from_cm, control_points_deg, 180.0, config)


def roll_about_axis_deg(
    camera_from_cm_est: np.ndarray | torch.Tensor,
    camera_from_cm_true: np.ndarray | torch.Tensor,
    axis_cm: np.ndarray | torch.Tensor,
) -> torch.Tensor:
    """Roll error (twist of the swing-twist decomposition) about a CM-frame axis, degrees in [0, 180].

    Args:
        camera_from_cm_est, camera_from_cm_true: (..., 4, 4).
        axis_cm: (..., 3) axis in the CM frame (the chord A→B).

    Returns:
        (...) |twist angle| of ``R_trueᵀ R_est`` about the axis.
    """
    Te = torch.as_tensor(camera_from_cm_est, dtype=torch.float64)
    Tt = torch.as_tensor(camera_from_cm_true, dtype=torch.float64, device=Te.device)
    axis = normalize(torch.as_tensor(axis_cm, dtype=torch.float64, device=Te.device))
    rel = Tt[..., :3, :3].transpose(-1, -2) @ Te[..., :3, :3]
    q = matrix_to_quat(rel)  # (x, y, z, w), w ≥ 0
    twist = 2.0 * torch.atan2((q[..., :3] * axis).sum(-1), q[..., 3])
    twist = torch.remainder(torch.rad2deg(twist) + 180.0, 360.0) - 180.0
    return twist.abs()
