"""Polychromatic transport and the XrayPhysics image chain (noise-free parts)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import xraylib

from fluoronav.simulation.materials import mass_attenuation
from fluoronav.simulation.physics import XrayPhysics, detector_weights, polychromatic_intensity
from fluoronav.simulation.spectrum import Spectrum, load_spectrum

CLEAN = {"photons_per_pixel": None, "scatter_to_primary": 0.0, "blur_sigma_px": 0.0, "glare_fraction": 0.0}


def _mu_eff(physics: XrayPhysics, material: str, density: float, thickness_cm: np.ndarray) -> np.ndarray:
    t = torch.as_tensor(thickness_cm, dtype=torch.float64)
    image = physics.apply({material: density * t})
    return (image / t).numpy()


def test_monoenergetic_log_image_equals_line_integral() -> None:
    e = 60.0
    physics = XrayPhysics(custom_spectrum=Spectrum.monoenergetic(e), **CLEAN)
    gen = torch.Generator().manual_seed(0)
    areal = {  # g/cm²
        "water": torch.rand(3, 8, 9, generator=gen) * 20.0,
        "bone_cortical": torch.rand(3, 8, 9, generator=gen) * 3.0,
        "nitinol": torch.rand(3, 8, 9, generator=gen) * 0.5,
    }
    image = physics.apply(areal)
    assert image.dtype == torch.float32 and image.shape == (3, 8, 9)
    # Reference from xraylib's compound parser (independent of our weight-fraction sums).
    ni, ti = xraylib.SymbolToAtomicNumber("Ni"), xraylib.SymbolToAtomicNumber("Ti")
    mu = {
        "water": xraylib.CS_Total_CP("H2O", e),
        "bone_cortical": xraylib.CS_Total_CP("Bone, Cortical (ICRP)", e),
        "nitinol": 0.558 * xraylib.CS_Total(ni, e) + 0.442 * xraylib.CS_Total(ti, e),
    }
    expected = sum(mu[k] * areal[k].double() for k in areal)
    torch.testing.assert_close(image.double(), expected, rtol=0.01, atol=0.0)


def test_water_slab_transmission_at_60_keV_matches_xraylib() -> None:
    physics = XrayPhysics(custom_spectrum=Spectrum.monoenergetic(60.0), **CLEAN)
    t = np.array([1.0, 5.0, 10.0, 20.0, 30.0])  # cm of water at 1 g/cm³
    np.testing.assert_allclose(_mu_eff(physics, "water", 1.0, t), xraylib.CS_Total_CP("H2O", 60.0), rtol=0.01)


@pytest.mark.parametrize(("material", "density"), [("water", 1.0), ("bone_cortical", 1.85)])
def test_beam_hardening_effective_mu_falls_with_thickness(material: str, density: float) -> None:
    physics = XrayPhysics(kvp=90.0, **CLEAN)
    t = np.array([0.01, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 30.0])
    mu_eff = _mu_eff(physics, material, density, t)
    assert np.all(np.diff(mu_eff) < 0)
    # Thin-slab limit: μ_eff → detector-weighted mean of μ over the spectrum.
    w = detector_weights(physics.spectrum, scintillator_csi_mm=physics.scintillator_csi_mm)
    mu_mean = float(w @ mass_attenuation(material, physics.spectrum.energies_keV)) * density
    assert mu_eff[0] == pytest.approx(mu_mean, rel=0.005)
    # Hardening is substantial for a pelvis-sized water path: μ_eff(20 cm) at least 10 % below thin.
    assert mu_eff[-2] < 0.9 * mu_eff[0]


def test_harder_spectrum_attenuates_less() -> None:
    t = np.array([10.0])
    soft = _mu_eff(XrayPhysics(kvp=70.0, **CLEAN), "water", 1.0, t)
    hard = _mu_eff(XrayPhysics(kvp=110.0, **CLEAN), "water", 1.0, t)
    cu = _mu_eff(XrayPhysics(kvp=70.0, filtration="al2.5_cu0.1", **CLEAN), "water", 1.0, t)
    assert hard[0] < soft[0] and cu[0] < soft[0]
    # Energy weighting favours high energies: energy-integrating sees a lower μ than photon counting.
    ei = _mu_eff(XrayPhysics(detector="energy_integrating", **CLEAN), "water", 1.0, t)
    pc = _mu_eff(XrayPhysics(detector="photon_counting", **CLEAN), "water", 1.0, t)
    assert ei[0] < pc[0]


def test_polychromatic_matches_numpy_reference_and_chunking() -> None:
    spectrum = load_spectrum(80.0, filtration="al2.5_cu0.1")
    gen = torch.Generator().manual_seed(1)
    areal = {
        "soft_tissue": torch.rand(2, 5, 7, generator=gen, dtype=torch.float64) * 25.0,
        "titanium": torch.rand(5, 7, generator=gen, dtype=torch.float64) * 0.3,
    }
    w = spectrum.fluence * spectrum.energies_keV
    w = w / w.sum()
    mu_s = mass_attenuation("soft_tissue", spectrum.energies_keV)
    mu_t = mass_attenuation("titanium", spectrum.energies_keV)
    a_s, a_t = areal["soft_tissue"].numpy()[..., None], areal["titanium"].numpy()[None, ..., None]
    ref = (w * np.exp(-(mu_s * a_s + mu_t * a_t))).sum(-1)
    full = polychromatic_intensity(areal, spectrum)
    chunked = polychromatic_intensity(areal, spectrum, chunk_elements=3)
    assert full.dtype == torch.float64 and full.shape == (2, 5, 7)
    np.testing.assert_allclose(full.numpy(), ref, rtol=1e-10)
    np.testing.assert_allclose(chunked.numpy(), ref, rtol=1e-10)
    f32 = polychromatic_intensity({k: v.float() for k, v in areal.items()}, spectrum)
    assert f32.dtype == torch.float32
    np.testing.assert_allclose(f32.numpy(), ref, rtol=1e-4)


def test_flat_field_is_zero_and_bone_metal_bright() -> None:
    physics = XrayPhysics(**CLEAN)
    zero = torch.zeros(4, 4)
    assert torch.allclose(physics.apply({"water": zero}), zero, atol=1e-6)
    water = physics.apply({"water": torch.full((1, 1), 2.0)})
    bone = physics.apply({"bone_cortical": torch.full((1, 1), 2.0)})
    metal = physics.apply({"nitinol": torch.full((1, 1), 2.0)})
    assert float(water) < float(bone) < float(metal)


def test_gain_offset() -> None:
    a = {"water": torch.full((2, 2), 10.0)}
    base = XrayPhysics(**CLEAN).apply(a)
    scaled = XrayPhysics(**CLEAN, gain=2.0, offset=-0.5).apply(a)
    torch.testing.assert_close(scaled, 2.0 * base - 0.5)


def test_with_pixel_scale() -> None:
    physics = XrayPhysics(blur_sigma_px=1.0, glare_gamma_px=8.0, scatter_sigma_px=40.0)
    half = physics.with_pixel_scale(2.0)
    assert (half.blur_sigma_px, half.glare_gamma_px, half.scatter_sigma_px) == (0.5, 4.0, 20.0)
    assert half.kvp == physics.kvp
    # a 2×2 binned pixel collects the photons and read-out noise of four detector pixels
    assert half.photons_per_pixel == 4.0 * physics.photons_per_pixel
    assert half.electronic_noise_std == 2.0 * physics.electronic_noise_std
    assert XrayPhysics(photons_per_pixel=None).with_pixel_scale(3.0).photons_per_pixel is None


def test_binning_noise_matches_binned_detector() -> None:
    """Noise of an image simulated at 2× binned pixels = the detector image area-binned 2×2."""
    physics = XrayPhysics(
        photons_per_pixel=200.0, scatter_to_primary=0.0, blur_sigma_px=0.0, glare_fraction=0.0
    )
    a = {"water": torch.full((256, 256), 5.0, dtype=torch.float64)}
    full = physics.detected(a, seed=1)  # (256, 256) detector pixels
    binned_from_full = torch.nn.functional.avg_pool2d(full[None, None], 2)[0, 0]
    small = {"water": torch.full((128, 128), 5.0, dtype=torch.float64)}
    direct = physics.with_pixel_scale(2.0).detected(small, seed=2)
    ratio = float(direct.std() / binned_from_full.std())
    assert abs(ratio - 1.0) < 0.05, ratio  # 128² samples: std estimated within ~1.3 %
    torch.testing.assert_close(direct.mean(), binned_from_full.mean(), rtol=0.01, atol=0.0)


def test_scatter_to_primary_ratio_on_uniform_slab() -> None:
    e = 60.0
    mu = float(mass_attenuation("water", [e])[0])
    thickness = 4.0 / mu  # line integral exactly the reference 4.0
    clean = dict(CLEAN, scatter_to_primary=0.25, scatter_reference_line_integral=4.0, scatter_sigma_px=10.0)
    physics = XrayPhysics(custom_spectrum=Spectrum.monoenergetic(e), **clean)
    a = {"water": torch.full((64, 64), thickness, dtype=torch.float64)}
    primary = physics.primary(a)
    detected = physics.detected(a)
    spr = (detected - primary) / primary
    np.testing.assert_allclose(spr.numpy(), 0.25, rtol=1e-6)
    # Air scatters nothing, so the flat field stays at 1.
    air = physics.detected({"water": torch.zeros(16, 16, dtype=torch.float64)})
    np.testing.assert_allclose(air.numpy(), 1.0, rtol=1e-12)


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu() -> None:
    a = {"water": torch.rand(2, 32, 32) * 20, "bone_cortical": torch.rand(2, 32, 32)}
    physics = XrayPhysics()
    cpu = XrayPhysics(**CLEAN).apply(a)
    gpu = XrayPhysics(**CLEAN).apply({k: v.cuda() for k, v in a.items()})
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-4, atol=1e-5)
    noisy = physics.apply({k: v.cuda() for k, v in a.items()}, seed=0)
    assert noisy.device.type == "cuda" and torch.isfinite(noisy).all()
