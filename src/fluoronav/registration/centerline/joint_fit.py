"""Joint refinement of a centreline initialisation: all 11 DoF (pose and control points) fitted to the
centreline with the landmarks and the FBG control points as Gaussian priors.

The grid search of :func:`~fluoronav.registration.centerline.centerline_initialize` pins A and B
exactly on the detected landmarks' rays and the chord at the FBG shape's length, so 3 px of landmark
noise or 0.5° of FBG error moves the best (d_A, θ) far along the depth valley; this robust
least-squares fit (soft-L1 loss, point-to-polyline distances both ways) polishes each refined minimum,
A's depth kept inside the search range.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from fluoronav.geometry.camera import project_points
from fluoronav.geometry.rotations import rotvec_to_matrix
from fluoronav.manipulator import CMKinematics
from fluoronav.registration.centerline.cost import fixed_points_to_polylines, point_to_fixed_polyline
from fluoronav.registration.centerline.shaft_depth import ShaftDepthCue, shaft_depth_residual

if TYPE_CHECKING:
    from scipy.optimize import OptimizeResult

__all__ = ["JointFitConfig", "joint_fit"]


@dataclass(frozen=True)
class JointFitConfig:
    """Settings of the joint (11-DoF) refinement.

    Attributes:
        landmark_sigma_px: landmark prior σ, pixels of the image; None: ``landmark_sigma_mm`` at the
            detector, or ``landmark_sigma_fallback_px`` when the camera has no pixel spacing.
        landmark_sigma_mm: default landmark σ at the detector (the shipped detector's median error).
        landmark_sigma_fallback_px: landmark σ without a pixel spacing.
        control_point_sigma_deg: control-point prior σ (FBG U(±0.5°): σ 0.29°).
        centerline_sigma_px: σ of a centreline point's distance, pixels.
        points_per_term: the centreline residuals of each direction are weighted √(points_per_term / n)
            so that each direction counts like this many landmark-sized terms per σ².
        loss_scale: soft-L1 scale of the residuals (in σ units).
        max_evaluations: residual evaluations of the least-squares solver.
        step_rotation_rad, step_translation_mm, step_control_point_deg: forward-difference steps of
            the Jacobian.
    """

    landmark_sigma_px: float | None = None
    landmark_sigma_mm: float = 1.0
    landmark_sigma_fallback_px: float = 3.0
    control_point_sigma_deg: float = 0.3
    centerline_sigma_px: float = 1.0
    points_per_term: float = 8.0
    loss_scale: float = 2.0
    max_evaluations: int = 60
    step_rotation_rad: float = 1e-4
    step_translation_mm: float = 1e-3
    step_control_point_deg: float = 1e-3

    def landmark_sigma_for(self, pixel_spacing_mm: float | None) -> float:
        """The landmark σ in pixels for an image of this pixel spacing (mm, None: unknown)."""
        if self.landmark_sigma_px is not None:
            return self.landmark_sigma_px
        if pixel_spacing_mm:
            return self.landmark_sigma_mm / pixel_spacing_mm
        return self.landmark_sigma_fallback_px


def joint_fit(
    K: torch.Tensor,
    camera_from_cm0: torch.Tensor,
    control_points0_deg: torch.Tensor,
    landmarks_px: torch.Tensor,
    extracted_px: torch.Tensor,
    kin: CMKinematics,
    *,
    depth_range_mm: tuple[float, float],
    landmark_sigma_px: float,
    n_model_points: int,
    config: JointFitConfig,
    depth_cue: ShaftDepthCue | None = None,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Robust least-squares fit of pose (rotation about A, A's position) and control points to a
    centreline, with landmark and control-point priors.

    Args:
        K: (3, 3) intrinsics.
        camera_from_cm0: (4, 4) start pose.
        control_points0_deg: (5,) start (and prior mean) of the control points.
        landmarks_px: (2, 2) detected A, B, pixels.
        extracted_px: (Q, 2) extracted centreline, pixels.
        kin: CM kinematics.
        depth_range_mm: (min, max) A's camera-frame depth stays inside.
        landmark_sigma_px: landmark prior σ, pixels.
        n_model_points: points on the model centreline.
        config: priors, loss and solver settings (its ``landmark_sigma_px`` is not used).
        depth_cue: the shaft depth cue, one more residual (None: none).

    Returns:
        (camera_from_cm (4, 4), control points (5,), final cost). Jacobians by forward differences, all
        evaluations of one Jacobian in one batched call.
    """
    dt, dev = K.dtype, K.device
    R0, a0 = camera_from_cm0[:3, :3], camera_from_cm0[:3, 3]
    n_cp = control_points0_deg.shape[0]
    centre = extracted_px.mean(0)
    ext = extracted_px - centre
    w_model = 1.0 / (config.centerline_sigma_px * math.sqrt(n_model_points / config.points_per_term))
    w_ext = 1.0 / (config.centerline_sigma_px * math.sqrt(ext.shape[0] / config.points_per_term))

    def residuals(X: torch.Tensor) -> torch.Tensor:  # (N, 6 + n_cp) → (N, R)
        T = torch.zeros(X.shape[0], 4, 4, dtype=dt, device=dev)
        T[:, :3, :3] = rotvec_to_matrix(X[:, :3]) @ R0
        T[:, :3, 3] = a0 + X[:, 3:6]
        T[:, 3, 3] = 1.0
        cp = control_points0_deg + X[:, 6:]
        uv = project_points(K, T, kin.centerline_cm(cp, n_points=n_model_points)) - centre
        d_model = point_to_fixed_polyline(uv, ext)
        d_ext = fixed_points_to_polylines(ext, uv)
        lm = project_points(K, T, kin.landmarks_cm(cp))
        parts = [
            d_model * w_model,
            d_ext * w_ext,
            ((lm - landmarks_px) / landmark_sigma_px).reshape(X.shape[0], -1),
            X[:, 6:] / config.control_point_sigma_deg,
        ]
        if depth_cue is not None:
            parts.append(shaft_depth_residual(depth_cue, K, T)[:, None])
        return torch.cat(parts, dim=1)

    sol = _solve(residuals, n_cp, float(a0[2]), depth_range_mm, config, dt, dev)
    x = torch.as_tensor(sol.x, dtype=dt, device=dev)
    T = torch.eye(4, dtype=dt, device=dev)
    T[:3, :3] = rotvec_to_matrix(x[:3]) @ R0
    T[:3, 3] = a0 + x[3:6]
    return T.cpu().numpy(), (control_points0_deg + x[6:]).cpu().numpy(), float(sol.cost)


def _solve(
    residuals: Callable[[torch.Tensor], torch.Tensor],
    n_cp: int,
    z0: float,
    depth_range_mm: tuple[float, float],
    config: JointFitConfig,
    dt: torch.dtype,
    dev: torch.device,
) -> OptimizeResult:
    """The bounded soft-L1 least squares from the start (A's depth ``z0`` mm kept in the range), with
    forward-difference Jacobians: the residuals and their Jacobian come from one batched call."""
    step = np.array(
        [config.step_rotation_rad] * 3
        + [config.step_translation_mm] * 3
        + [config.step_control_point_deg] * n_cp
    )
    cache: dict[bytes, np.ndarray] = {}

    def both(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = x.tobytes()
        if key not in cache:
            X = torch.as_tensor(np.vstack([x, x + np.diag(step)]), dtype=dt, device=dev)
            r = residuals(X).cpu().numpy()
            cache.clear()
            cache[key] = r
        r = cache[key]
        return r[0], ((r[1:] - r[0]) / step[:, None]).T

    lo = np.full(6 + n_cp, -np.inf)
    hi = np.full(6 + n_cp, np.inf)
    lo[5], hi[5] = depth_range_mm[0] - z0, depth_range_mm[1] - z0  # A's depth stays in the range
    x0 = np.zeros(6 + n_cp)
    x0[5] = np.clip(0.0, lo[5] + 1e-6, hi[5] - 1e-6)
    from scipy.optimize import least_squares  # here: a slow import, not needed at start-up

    return least_squares(
        lambda x: both(x)[0], x0, jac=lambda x: both(x)[1], bounds=(lo, hi), method="trf",
        loss="soft_l1", f_scale=config.loss_scale, max_nfev=config.max_evaluations,
    )  # fmt: skip
