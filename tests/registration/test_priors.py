"""Landmark reprojection penalty (eqs. 2, 4, 6) and parameter priors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fluoronav.registration.priors import (
    GaussianParameterPrior,
    LandmarkPrior,
    gaussian_parameter_prior,
    landmark_reprojection_prior,
)


def test_landmark_prior_value_and_missing() -> None:
    rng = np.random.default_rng(0)
    proj = rng.normal(size=(3, 2, 2, 2)) * 50
    det = rng.normal(size=(2, 2, 2)) * 50
    sigma = 25.0
    expected = ((proj - det) ** 2).sum(axis=(1, 2, 3)) / (2 * sigma**2)
    got = landmark_reprojection_prior(torch.tensor(proj), torch.tensor(det), sigma)
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-12)
    det_missing = det.copy()
    det_missing[1, 0] = np.nan
    exp_m = (((proj - det) ** 2).sum(-1) * np.array([[1, 1], [0, 1]])).sum(axis=(1, 2)) / (2 * sigma**2)
    got_m = landmark_reprojection_prior(torch.tensor(proj), torch.tensor(det_missing), sigma)
    np.testing.assert_allclose(got_m.numpy(), exp_m, rtol=1e-12)
    mask = torch.tensor([[True, False], [True, True]])
    exp_k = (((proj - det) ** 2).sum(-1) * np.array([[1, 0], [1, 1]])).sum(axis=(1, 2)) / (2 * sigma**2)
    np.testing.assert_allclose(
        landmark_reprojection_prior(torch.tensor(proj), torch.tensor(det), sigma, mask=mask).numpy(),
        exp_k,
        rtol=1e-12,
    )
    with pytest.raises(ValueError):
        landmark_reprojection_prior(torch.tensor(proj), torch.tensor(det[:1]), sigma)


def test_landmark_prior_resolution_invariant() -> None:
    # 100 px at full resolution equals 25 px after 4× binning (the authors' "100 px × factor")
    proj = torch.tensor([[[[400.0, 300.0], [500.0, 700.0]]]], dtype=torch.float64)
    det = torch.tensor([[[420.0, 290.0], [470.0, 730.0]]], dtype=torch.float64)
    full = landmark_reprojection_prior(proj, det, 100.0)
    f = 4
    binned = landmark_reprojection_prior((proj - (f - 1) / 2) / f, (det - (f - 1) / 2) / f, 25.0)
    torch.testing.assert_close(full, binned)


def test_callable_priors() -> None:
    def project(p: torch.Tensor) -> torch.Tensor:
        return p.reshape(-1, 1, 2, 2)

    prior = LandmarkPrior(project, np.zeros((1, 2, 2)), 2.0)
    p = torch.tensor([[1.0, 2.0, 3.0, 4.0]], dtype=torch.float64)
    torch.testing.assert_close(prior(p), torch.tensor([30.0 / 8.0], dtype=torch.float64))
    g = GaussianParameterPrior(np.array([0.0, 0, 0, 0]), np.array([2.0, 1, 1, np.inf]))
    torch.testing.assert_close(g(p), torch.tensor([0.5 * (0.25 + 4 + 9)], dtype=torch.float64))
    torch.testing.assert_close(
        gaussian_parameter_prior(p, torch.zeros(4), torch.ones(4)), torch.tensor([15.0], dtype=torch.float64)
    )
    with pytest.raises(ValueError):
        GaussianParameterPrior(np.zeros(2), np.array([1.0, 0.0]))


def test_flat_bottomed_prior_is_free_within_the_tolerance() -> None:
    """½ (max(|x − μ| − τ, 0)/σ)²: zero inside ±τ, hand-computed values outside, τ = 0 is the Gaussian."""
    mean, std = torch.tensor([1.0, -2.0], dtype=torch.float64), torch.tensor([0.25, 0.5], dtype=torch.float64)
    tol = torch.tensor([1.0, 0.5], dtype=torch.float64)
    p = torch.tensor([[1.9, -2.4], [2.5, -2.0], [-0.5, -3.0]], dtype=torch.float64)
    got = gaussian_parameter_prior(p, mean, std, tol)
    # row 0 inside; row 1: |1.5| − 1 = 0.5 → ½·(0.5/0.25)² = 2; row 2: 2 + ½·((1 − 0.5)/0.5)² = 2.5
    torch.testing.assert_close(got, torch.tensor([0.0, 2.0, 2.5], dtype=torch.float64))
    torch.testing.assert_close(
        gaussian_parameter_prior(p, mean, std, torch.zeros(2, dtype=torch.float64)),
        gaussian_parameter_prior(p, mean, std),
    )
    g = GaussianParameterPrior(mean.numpy(), std.numpy(), tolerance=tol.numpy())
    torch.testing.assert_close(g(p), got)
    with pytest.raises(ValueError, match="tolerances"):
        GaussianParameterPrior(mean.numpy(), std.numpy(), tolerance=np.array([-1.0, 0.0]))
