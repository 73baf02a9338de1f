"""CM kinematics, batched in torch: control points → joint angles → link poses → landmarks.

The joint angle of notch ``j`` is a natural cubic spline through the control points placed at the
knots of :meth:`CMConfig.knot_positions` and evaluated at ``j = 0 … N−1`` (extrapolated with the end
pieces outside the knots); it is linear in the control points, a fixed (N, n) weight matrix, so
batching is one matrix product. Each joint rotates everything distal to it about the x axis through
the notch centre on the tube axis, as in the authors' model (how a real tube differs:
docs/conventions.md). There are ``N + 1`` rigid links: link 0 is the base (up to notch 0's centre),
link ``k`` lies between notch ``k−1`` and ``k``, and link ``N`` is the top. ``cm_from_link[k]`` maps
a point given in straight-configuration CM coordinates on link ``k`` to its bent position in the CM
base frame.
"""

from __future__ import annotations

import functools

import numpy as np
import torch

from fluoronav.manipulator.config import CMConfig

__all__ = ["CMKinematics"]


@functools.lru_cache(maxsize=32)
def _spline_weights(config: CMConfig) -> np.ndarray:
    from scipy.interpolate import CubicSpline  # at first use: its import loads scipy.optimize

    knots = np.asarray(config.knot_positions())
    eye = np.eye(config.n_control_points)
    spline = CubicSpline(knots, eye, axis=0, bc_type="natural", extrapolate=True)
    return np.asarray(spline(np.arange(config.n_notches, dtype=np.float64)))  # (N, n)


class CMKinematics:
    """Forward kinematics of a notched CM, batched over any leading dimensions.

    Args:
        config: CM geometry; the paper's CM by default.
    """

    def __init__(self, config: CMConfig | None = None) -> None:
        self.config = config or CMConfig()
        self._W = _spline_weights(self.config)
        c = self.config
        self.notch_z_mm = np.array([c.notch_z_mm(j) for j in range(c.n_notches)])

    @property
    def n_links(self) -> int:
        return self.config.n_notches + 1

    def spline_weights(self, like: torch.Tensor) -> torch.Tensor:
        """(N, n) matrix mapping control points to joint angles, in ``like``'s dtype/device."""
        return torch.as_tensor(self._W, dtype=like.dtype, device=like.device)

    def joint_angles_deg(self, control_points_deg: torch.Tensor) -> torch.Tensor:
        """(..., n) control points in degrees → (..., N) notch joint angles in degrees."""
        return control_points_deg @ self.spline_weights(control_points_deg).T

    def link_transforms(self, control_points_deg: torch.Tensor) -> torch.Tensor:
        """(..., n) control points in degrees → (..., N+1, 4, 4) ``cm_from_link`` transforms."""
        return self.link_transforms_from_angles(self.joint_angles_deg(control_points_deg))

    def link_transforms_from_angles(
        self, joint_angles_deg: torch.Tensor, *, notch_z_mm: np.ndarray | None = None
    ) -> torch.Tensor:
        """``cm_from_link`` transforms of explicit joint angles (not necessarily a spline's).

        Args:
            joint_angles_deg: (..., N) notch joint angles in degrees.
            notch_z_mm: (N,) straight-frame joint centres, mm; the config's (uniform pitch) if None.
                An as-built instrument's notches sit where they were really cut.

        Returns:
            (..., N+1, 4, 4) ``cm_from_link`` transforms.
        """
        phi = torch.deg2rad(joint_angles_deg)  # (..., N)
        batch = phi.shape[:-1]
        zeros = torch.zeros(*batch, 1, dtype=phi.dtype, device=phi.device)
        Phi = torch.cat([zeros, torch.cumsum(phi, dim=-1)], dim=-1)  # (..., N+1) cumulative angle
        centres = self.notch_z_mm if notch_z_mm is None else np.asarray(notch_z_mm, dtype=np.float64)
        if centres.shape != (self.config.n_notches,):
            raise ValueError(f"notch_z_mm must have shape ({self.config.n_notches},), got {centres.shape}")
        z = torch.as_tensor(centres, dtype=phi.dtype, device=phi.device)  # straight centres
        # bent position of joint j: p_j = p_{j−1} + R_x(Φ_j)·(0, 0, z_j − z_{j−1}); p_0 = (0, 0, z_0)
        seg = torch.diff(z, prepend=torch.zeros(1, dtype=z.dtype, device=z.device))  # (N,)
        seg = seg.expand(*batch, -1)
        Phi_before = Phi[..., :-1]  # rotation of the link that leads into joint j
        py = torch.cumsum(-torch.sin(Phi_before) * seg, dim=-1)  # (..., N)
        pz = torch.cumsum(torch.cos(Phi_before) * seg, dim=-1)
        # link k (k ≥ 1) rotates about joint k−1: T_k = [R_x(Φ_k) | p_{k−1} − R_x(Φ_k)·c_{k−1}]
        c, s = torch.cos(Phi), torch.sin(Phi)
        T = torch.zeros(*batch, self.n_links, 4, 4, dtype=phi.dtype, device=phi.device)
        T[..., 0, 0] = 1.0
        T[..., 1, 1] = c
        T[..., 1, 2] = -s
        T[..., 2, 1] = s
        T[..., 2, 2] = c
        T[..., 3, 3] = 1.0
        # translation: p − R c with c = (0, 0, z_{k−1}); for the base link it is zero
        zc = torch.cat([torch.zeros(1, dtype=z.dtype, device=z.device), z])  # centre per link
        py_full = torch.cat([zeros, py], dim=-1)
        pz_full = torch.cat([zeros, pz], dim=-1)
        T[..., 1, 3] = py_full - (-s * zc)
        T[..., 2, 3] = pz_full - (c * zc)
        return T

    def _point_on_link(
        self, control_points_deg: torch.Tensor, link: int, z_straight_mm: float
    ) -> torch.Tensor:
        T = self.link_transforms(control_points_deg)[..., link, :, :]
        return T[..., :3, 2] * z_straight_mm + T[..., :3, 3]

    def landmarks_cm(self, control_points_deg: torch.Tensor) -> torch.Tensor:
        """(..., n) → (..., 2, 3): landmark A (base origin) and B (distal plane of the last notch)."""
        B = self._point_on_link(control_points_deg, self.n_links - 1, self.config.distal_notch_plane_mm)
        A = torch.zeros_like(B)
        return torch.stack([A, B], dim=-2)

    def tip_cm(self, control_points_deg: torch.Tensor) -> torch.Tensor:
        """(..., n) → (..., 3): the distal end point of the CM (used for tip errors)."""
        return self._point_on_link(control_points_deg, self.n_links - 1, self.config.tip_z_mm)

    def link_z_ranges_mm(self) -> np.ndarray:
        """(N+1, 2) straight-configuration axial extent of each link's material."""
        c = self.config
        bounds = np.concatenate([[-c.base_length_mm], self.notch_z_mm, [c.tip_z_mm]])
        return np.stack([bounds[:-1], bounds[1:]], axis=1)

    def centerline_cm(
        self,
        control_points_deg: torch.Tensor,
        *,
        n_points: int = 64,
        from_z_mm: float = 0.0,
        to_z_mm: float | None = None,
    ) -> torch.Tensor:
        """(..., n) → (..., n_points, 3) points on the bent axis from A (z=0) to B by default."""
        to_z = self.config.distal_notch_plane_mm if to_z_mm is None else to_z_mm
        zs = np.linspace(from_z_mm, to_z, n_points)
        link = np.clip(np.searchsorted(self.notch_z_mm, zs, side="right"), 0, self.n_links - 1)
        T = self.link_transforms(control_points_deg)[..., link, :, :]  # (..., P, 4, 4)
        zt = torch.as_tensor(zs, dtype=T.dtype, device=T.device)
        return T[..., :3, 2] * zt.unsqueeze(-1) + T[..., :3, 3]
