"""Detector stages on images (…, H, W): scatter, blur (PSF with a Lorentzian tail) and noise.

All functions are pure torch, device-agnostic, and work in float32 or float64. Filters are applied
in the Fourier domain on an edge-replicated padding, with analytic transfer functions:

- Gaussian PSF of standard deviation σ px: ``exp(−2π²σ²|f|²)``.
- 2D Lorentzian (Cauchy) tail ``γ / (2π (r² + γ²)^{3/2})`` of scale γ px: ``exp(−2πγ|f|)``.
"""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as nnf


def _frequency_radius(h: int, w: int, *, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    fy = torch.fft.fftfreq(h, device=device, dtype=dtype)
    fx = torch.fft.rfftfreq(w, device=device, dtype=dtype)
    return torch.sqrt(fy[:, None] ** 2 + fx[None, :] ** 2)


def _fast_length(n: int) -> int:
    """Smallest 2·3·5-smooth integer ≥ n (FFT sizes with large prime factors are several times slower)."""
    m = n
    while True:
        k = m
        for p in (2, 3, 5):
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m += 1


@functools.lru_cache(maxsize=16)
def _transfer(
    hp: int, wp: int, sigma: float, fraction: float, gamma: float, device: torch.device, dtype: torch.dtype
) -> torch.Tensor:
    """Cached transfer function (the same detector is filtered for every image of a data set)."""
    f = _frequency_radius(hp, wp, device=device, dtype=dtype)
    transfer = torch.exp(-2.0 * math.pi**2 * sigma**2 * f**2)
    if fraction > 0 and gamma > 0:
        transfer = transfer * ((1.0 - fraction) + fraction * torch.exp(-2.0 * math.pi * gamma * f))
    return transfer


def filter_image(
    image: torch.Tensor,
    *,
    gaussian_sigma_px: float = 0.0,
    lorentz_fraction: float = 0.0,
    lorentz_gamma_px: float = 0.0,
    pad_px: int | None = None,
) -> torch.Tensor:
    """Convolve with ``G_σ ⊛ [(1 − a)·δ + a·L_γ]`` (unit-sum kernel, so flat regions are kept).

    Args:
        image: (…, H, W) real tensor.
        gaussian_sigma_px: Gaussian PSF standard deviation in pixels (0: none).
        lorentz_fraction: weight ``a`` ∈ [0, 1] of the Lorentzian (glare) tail.
        lorentz_gamma_px: Lorentzian scale γ in pixels.
        pad_px: edge-replicated padding (default: 6σ + 20γ, at most the image size).

    Returns:
        (…, H, W) filtered image, same dtype and device.
    """
    use_lorentz = lorentz_fraction > 0 and lorentz_gamma_px > 0
    if gaussian_sigma_px <= 0 and not use_lorentz:
        return image
    h, w = image.shape[-2:]
    if pad_px is None:
        pad_px = math.ceil(6 * gaussian_sigma_px + (20 * lorentz_gamma_px if use_lorentz else 0))
    pad_y, pad_x = min(pad_px, h - 1), min(pad_px, w - 1)
    batch_shape = image.shape[:-2]
    x = image.reshape(-1, 1, h, w)
    # extra padding at the far ends up to a fast FFT length (it only widens the replicated border)
    extra_y = _fast_length(h + 2 * pad_y) - (h + 2 * pad_y)
    extra_x = _fast_length(w + 2 * pad_x) - (w + 2 * pad_x)
    if pad_y > 0 or pad_x > 0 or extra_y or extra_x:
        x = nnf.pad(x, (pad_x, pad_x + extra_x, pad_y, pad_y + extra_y), mode="replicate")
    hp, wp = x.shape[-2:]
    real_dtype = image.dtype if image.dtype in (torch.float32, torch.float64) else torch.float32
    transfer = _transfer(
        hp,
        wp,
        float(gaussian_sigma_px),
        float(lorentz_fraction) if use_lorentz else 0.0,
        float(lorentz_gamma_px) if use_lorentz else 0.0,
        image.device,
        real_dtype,
    )
    out = torch.fft.irfft2(torch.fft.rfft2(x.to(real_dtype)) * transfer, s=(hp, wp))
    out = out[..., pad_y : pad_y + h, pad_x : pad_x + w]
    return out.reshape(*batch_shape, h, w).to(image.dtype)


def scatter_estimate(
    primary: torch.Tensor,
    *,
    scatter_to_primary: float,
    reference_line_integral: float,
    sigma_px: float,
    downsample: int = 1,
) -> torch.Tensor:
    """Object scatter from the primary, kernel-superposition style (after Ohnesorge et al. 1999).

    Each pixel emits scatter in proportion to ``P·(−ln P)`` (photons that reach the detector after
    interacting: zero in air, small behind opaque objects), spread by a wide Gaussian:
    ``S = c · G_σ ⊛ (P·(−ln P))`` with ``c = scatter_to_primary / reference_line_integral``, so a
    wide uniform object of line integral ``reference_line_integral`` has exactly that
    scatter-to-primary ratio (SPR ∝ line integral elsewhere).

    Args:
        primary: (…, H, W) primary transmission P = I/I0 in (0, 1].
        scatter_to_primary: SPR at the reference line integral (≥ 0; 0 disables scatter).
        reference_line_integral: −ln P at which the SPR is ``scatter_to_primary`` (> 0).
        sigma_px: kernel standard deviation in pixels.
        downsample: compute the (smooth) scatter on ``downsample``× area-binned pixels and
            upsample it bilinearly; used only where the kernel stays ≥ 2 binned pixels wide and
            the image size is a multiple (the sum over a uniform object is unchanged).

    Returns:
        (…, H, W) scatter in the units of ``primary`` (flat-field relative).
    """
    if scatter_to_primary <= 0:
        return torch.zeros_like(primary)
    p = primary.clamp_min(torch.finfo(primary.dtype).tiny)
    source = p * (-torch.log(p)).clamp_min(0.0)
    c = scatter_to_primary / reference_line_integral
    h, w = source.shape[-2:]
    f = int(downsample)
    if f > 1 and sigma_px / f >= 2.0 and h % f == 0 and w % f == 0:
        flat = source.reshape(-1, 1, h, w)
        small = filter_image(nnf.avg_pool2d(flat, f), gaussian_sigma_px=sigma_px / f)
        up = nnf.interpolate(small, scale_factor=f, mode="bilinear", align_corners=False)
        return c * up.reshape(source.shape)
    return c * filter_image(source, gaussian_sigma_px=sigma_px)


def poisson_counts(expected: torch.Tensor, *, generator: torch.Generator | None = None) -> torch.Tensor:
    """Poisson-distributed photon counts with the given (…, H, W) expectation (≥ 0), same dtype."""
    return torch.poisson(expected.clamp_min(0.0), generator=generator).to(expected.dtype)


def gaussian_noise(
    shape_like: torch.Tensor, std: float, *, generator: torch.Generator | None = None
) -> torch.Tensor:
    """Zero-mean Gaussian noise of standard deviation ``std`` shaped like ``shape_like``."""
    if std <= 0:
        return torch.zeros_like(shape_like)
    return std * torch.randn(
        shape_like.shape, generator=generator, device=shape_like.device, dtype=shape_like.dtype
    )
