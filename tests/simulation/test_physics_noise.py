"""Quantum/electronic noise statistics, detector blur and reproducibility."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.ndimage as ndi
import torch

from fluoronav.simulation.noise import filter_image
from fluoronav.simulation.physics import XrayPhysics

N0 = 5000.0
NOISE_ONLY = {
    "photons_per_pixel": N0,
    "electronic_noise_std": 0.0,
    "scatter_to_primary": 0.0,
    "blur_sigma_px": 0.0,
    "glare_fraction": 0.0,
}


def test_flat_field_counts_and_log_variance_match_poisson() -> None:
    physics = XrayPhysics(**NOISE_ONLY)
    a = {"water": torch.zeros(256, 256)}
    counts = physics.detected(a, seed=3).double() * N0
    assert float(counts.mean()) == pytest.approx(N0, rel=0.002)
    assert float(counts.var()) == pytest.approx(N0, rel=0.10)
    log = physics.apply(a, seed=3).double()
    assert float(log.var()) == pytest.approx(1.0 / N0, rel=0.10)  # delta method: var(−ln X) ≈ 1/N
    assert np.allclose(counts.numpy(), np.round(counts.numpy()), atol=1e-2)  # integer photon counts


def test_log_variance_behind_water_matches_delta_method() -> None:
    physics = XrayPhysics(**NOISE_ONLY)
    a = {"water": torch.full((256, 256), 15.0)}
    p = float(physics.primary({"water": torch.full((1, 1), 15.0)}))
    log = physics.apply(a, generator=torch.Generator().manual_seed(11)).double()
    assert float(log.var()) == pytest.approx(1.0 / (N0 * p), rel=0.10)
    assert float(log.mean()) == pytest.approx(-math.log(p), rel=0.01)


def test_electronic_noise_adds_variance() -> None:
    physics = XrayPhysics(**dict(NOISE_ONLY, electronic_noise_std=50.0))
    counts = physics.detected({"water": torch.zeros(256, 256)}, seed=5).double() * N0
    assert float(counts.var()) == pytest.approx(N0 + 50.0**2, rel=0.10)


def test_counts_clipped_to_one_photon() -> None:
    physics = XrayPhysics(**dict(NOISE_ONLY, photons_per_pixel=10.0))
    image = physics.apply({"stainless_steel": torch.full((64, 64), 20.0)}, seed=0)
    assert torch.isfinite(image).all()
    assert float(image.max()) == pytest.approx(math.log(10.0), rel=1e-5)


def test_reproducible_with_seed_and_generator() -> None:
    physics = XrayPhysics()
    a = {"water": torch.rand(2, 32, 32) * 20}
    one = physics.apply(a, seed=7)
    two = physics.apply(a, generator=torch.Generator().manual_seed(7))
    other = physics.apply(a, seed=8)
    torch.testing.assert_close(one, two, rtol=0, atol=0)
    assert not torch.equal(one, other)
    with pytest.raises(ValueError, match="seed"):
        physics.apply(a)


def test_gaussian_blur_matches_scipy() -> None:
    rng = np.random.default_rng(0)
    img = rng.random((48, 40))
    out = filter_image(torch.from_numpy(img), gaussian_sigma_px=1.5).numpy()
    ref = ndi.gaussian_filter(img, 1.5, mode="nearest", truncate=6.0)
    # The analytic transfer function is cut at the Nyquist frequency, where it still has
    # exp(-2π²σ²/4) ≈ 1.5e-5 for σ = 1.5: that bounds the difference to the sampled kernel.
    np.testing.assert_allclose(out, ref, atol=2e-5)


def test_blur_reduces_white_noise_variance_by_psf_energy() -> None:
    # For a Gaussian PSF the variance of filtered white noise is σ_n² / (4πσ²).
    gen = torch.Generator().manual_seed(0)
    noise = torch.randn(512, 512, generator=gen, dtype=torch.float64)
    sigma = 2.0
    out = filter_image(noise, gaussian_sigma_px=sigma)
    assert float(out[16:-16, 16:-16].var()) == pytest.approx(1.0 / (4 * math.pi * sigma**2), rel=0.10)


def test_psf_with_glare_tail_preserves_flat_and_total() -> None:
    flat = torch.full((40, 50), 3.0, dtype=torch.float64)
    torch.testing.assert_close(
        filter_image(flat, gaussian_sigma_px=1.0, lorentz_fraction=0.1, lorentz_gamma_px=4.0),
        flat,
        rtol=1e-12,
        atol=1e-12,
    )
    impulse = torch.zeros(401, 401, dtype=torch.float64)
    impulse[200, 200] = 1.0
    out = filter_image(impulse, lorentz_fraction=0.2, lorentz_gamma_px=2.0, pad_px=0)
    assert float(out[200, 200]) == pytest.approx(0.8 + 0.2 / (2 * math.pi * 2.0**2), rel=0.02)
    # Lorentzian tail ∝ r⁻³ far out: doubling the distance divides the value by ~8.
    assert float(out[200, 240] / out[200, 280]) == pytest.approx(8.0, rel=0.1)
