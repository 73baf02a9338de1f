"""Regularisers added to the image similarity (torch, batched, float64 recommended).

The landmark reprojection penalty is eqs. 2, 4 and 6 of the paper:
``R = 1/(2σ²) Σ_k Σ_l ||P(p3D^(k,l)) − p2D^(k,l)||²`` over views (or CM poses) k and landmarks l.

Because both the residual and σ scale with the image resolution, a penalty computed in full-resolution
pixels with σ = 100 px equals the authors' "σ = 100 px × downsampling factor" at the working
resolution (``LevelConfig.landmark_sigma_px`` gives the latter).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from fluoronav.geometry.transforms import as_tensor

__all__ = [
    "GaussianParameterPrior",
    "LandmarkPrior",
    "control_point_prior",
    "gaussian_parameter_prior",
    "landmark_reprojection_prior",
]


def landmark_reprojection_prior(
    projected_px: torch.Tensor,
    detected_px: torch.Tensor,
    sigma_px: float,
    *,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Landmark reprojection penalty ``1/(2σ²) Σ ||p − q||²``.

    Args:
        projected_px: (B, K, L, 2) projections of the model landmarks (u, v), for B candidates,
            K views/poses and L landmarks.
        detected_px: (K, L, 2) detected 2D landmarks; NaN entries count as missing.
        sigma_px: σ in the same pixel units.
        mask: optional (K, L) bool, True where a landmark was detected (combined with the NaN test).

    Returns:
        (B,) penalty, dtype of ``projected_px``. Missing landmarks contribute 0.
    """
    if sigma_px <= 0:
        raise ValueError(f"sigma_px must be positive, got {sigma_px}")
    if projected_px.dim() != 4 or projected_px.shape[1:] != detected_px.shape:
        raise ValueError(
            f"projected (B, K, L, 2) {tuple(projected_px.shape)} does not match detected "
            f"(K, L, 2) {tuple(detected_px.shape)}"
        )
    q = detected_px.to(device=projected_px.device, dtype=projected_px.dtype)
    valid = torch.isfinite(q).all(dim=-1)
    if mask is not None:
        valid = valid & mask.to(device=valid.device, dtype=torch.bool)
    d2 = ((projected_px - torch.where(valid[..., None], q, torch.zeros_like(q))) ** 2).sum(dim=-1)
    d2 = torch.where(valid, d2, torch.zeros_like(d2))
    return d2.sum(dim=(1, 2)) / (2.0 * sigma_px**2)


def gaussian_parameter_prior(
    params: torch.Tensor, mean: torch.Tensor, std: torch.Tensor, tolerance: torch.Tensor | None = None
) -> torch.Tensor:
    """Independent Gaussian prior on parameters: ``½ Σ ((x − μ)/σ)²``, or with a ``tolerance`` τ a
    flat-bottomed one, ``½ Σ (max(|x − μ| − τ, 0)/σ)²``: free within ±τ of the mean (a sensor's stated
    accuracy), Gaussian walls beyond.

    Args:
        params: (B, D); mean, std: (D,) (std = inf disables a parameter); tolerance: (D,) ≥ 0 or None.

    Returns:
        (B,) negative log-density up to a constant.
    """
    d = params - mean.to(params)
    if tolerance is not None:
        d = torch.clamp(d.abs() - tolerance.to(params), min=0.0)
    z = d / std.to(params)
    return 0.5 * (z * z).sum(dim=-1)


class LandmarkPrior:
    """Callable prior ``params (B, D) → (B,)`` from a projection function and detections.

    Args:
        project: ``params (B, D) → (B, K, L, 2)`` model landmark projections in pixels.
        detected_px: (K, L, 2) detected landmarks (NaN = missing) in the same pixel units.
        sigma_px: σ in those pixels (authors: 100 px at full resolution).
        mask: optional (K, L) detection mask.
    """

    def __init__(
        self,
        project: Callable[[torch.Tensor], torch.Tensor],
        detected_px: torch.Tensor | np.ndarray,
        sigma_px: float,
        *,
        mask: torch.Tensor | None = None,
    ) -> None:
        self.project = project
        self.detected_px = as_tensor(detected_px, dtype=torch.float64)
        self.sigma_px = float(sigma_px)
        self.mask = mask

    def __call__(self, params: torch.Tensor) -> torch.Tensor:
        return landmark_reprojection_prior(
            self.project(params), self.detected_px, self.sigma_px, mask=self.mask
        )


class GaussianParameterPrior:
    """Callable (flat-bottomed) Gaussian prior on parameters (see :func:`gaussian_parameter_prior`)."""

    def __init__(
        self,
        mean: torch.Tensor | np.ndarray,
        std: torch.Tensor | np.ndarray,
        *,
        tolerance: torch.Tensor | np.ndarray | None = None,
    ) -> None:
        self.mean = as_tensor(mean, dtype=torch.float64)
        self.std = as_tensor(std, dtype=torch.float64)
        self.tolerance = None if tolerance is None else as_tensor(tolerance, dtype=torch.float64)
        if torch.any(self.std <= 0):
            raise ValueError("prior standard deviations must be positive")
        if self.tolerance is not None and torch.any(self.tolerance < 0):
            raise ValueError("prior tolerances must be non-negative")

    def __call__(self, params: torch.Tensor) -> torch.Tensor:
        return gaussian_parameter_prior(params, self.mean, self.std, self.tolerance)


def control_point_prior(
    control_points_deg: np.ndarray,
    *,
    n_leading: int,
    sigma_deg: float,
    tolerance_deg: float = 0.0,
) -> GaussianParameterPrior:
    """Prior of a parameter vector ``[n_leading pose parameters, control points]``: the control points
    free within ± ``tolerance_deg`` of ``control_points_deg`` (the FBG reading), Gaussian walls of
    ``sigma_deg`` beyond (a plain Gaussian for tolerance 0); the leading parameters carry none."""
    cp = np.asarray(control_points_deg, np.float64).reshape(-1)
    n = cp.size
    return GaussianParameterPrior(
        np.concatenate([np.zeros(n_leading), cp]),
        np.concatenate([np.full(n_leading, np.inf), np.full(n, sigma_deg)]),
        tolerance=np.concatenate([np.zeros(n_leading), np.full(n, tolerance_deg)]),
    )
