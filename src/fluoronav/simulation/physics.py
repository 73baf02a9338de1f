"""Polychromatic X-ray transport through per-material areal densities, and the detector model.

Units: areal densities ``A_m = ∫ρ_m dl`` in g/cm² (from mm: ``materials.areal_density_g_cm2``), keV,
μ/ρ in cm²/g, intensities relative to the flat field I0, images after ``−ln(I/I0)`` (bone and metal
bright). Model (after DeepDRR, Unberath et al. 2018)::

    I/I0 = Σ_E w(E) · exp(−Σ_m (μ/ρ)_m(E) · A_m),   w(E) ∝ Φ(E) · E · η(E)   (energy integrating)
                                                     w(E) ∝ Φ(E) · η(E)       (photon counting)

with Φ the tube spectrum, η(E) = 1 − exp(−(μ/ρ)_CsI ρ_CsI t) the CsI absorption and Σ w = 1; then
scatter, noise and blur (docs/simulation.md, "Image formation").
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from collections.abc import Mapping
from typing import Literal

import numpy as np
import torch

import fluoronav.simulation.noise as noise
from fluoronav.simulation.materials import get_material, mass_attenuation, mass_attenuation_table
from fluoronav.simulation.spectrum import DEFAULT_FILTRATION, Spectrum, load_spectrum

logger = logging.getLogger(__name__)

DetectorKind = Literal["energy_integrating", "photon_counting"]


def detector_weights(
    spectrum: Spectrum,
    *,
    detector: DetectorKind = "energy_integrating",
    scintillator_csi_mm: float = 0.0,
) -> np.ndarray:
    """Per-bin detector signal weights w(E), summing to 1 (the flat-field signal).

    Args:
        spectrum: incident spectrum (any normalisation).
        detector: ``"energy_integrating"`` (signal ∝ deposited energy, w ∝ Φ·E·η) or
            ``"photon_counting"`` (w ∝ Φ·η).
        scintillator_csi_mm: CsI thickness in mm for the absorption efficiency η(E); 0 means an
            ideal absorber (η = 1).

    Returns:
        (E,) float64 weights.
    """
    w = spectrum.fluence.copy()
    if detector == "energy_integrating":
        w = w * spectrum.energies_keV
    elif detector != "photon_counting":
        raise ValueError(f"unknown detector {detector!r}; use 'energy_integrating' or 'photon_counting'")
    if scintillator_csi_mm > 0:
        rho = get_material("csi").density_g_cm3
        w = w * -np.expm1(-mass_attenuation("csi", spectrum.energies_keV) * rho * scintillator_csi_mm / 10.0)
    return w / w.sum()


def polychromatic_intensity(
    areal_density: Mapping[str, torch.Tensor],
    spectrum: Spectrum,
    *,
    detector: DetectorKind = "energy_integrating",
    scintillator_csi_mm: float = 0.0,
    chunk_elements: int = 1 << 24,
) -> torch.Tensor:
    """Noise-free detected intensity relative to the flat field, ``I/I0`` ∈ (0, 1].

    Args:
        areal_density: material name → (…, H, W) tensor of ``∫ρ_m dl`` in g/cm² (broadcastable
            shapes, same device). Names are keys of ``materials.MATERIALS``.
        spectrum: incident spectrum (normalisation irrelevant).
        detector: ``"energy_integrating"`` or ``"photon_counting"`` (see :func:`detector_weights`).
        scintillator_csi_mm: CsI thickness in mm for η(E) (0: ideal detector).
        chunk_elements: at most this many (energy × pixel) exponentials are held at once.

    Returns:
        (…, H, W) tensor, float32 (float64 if any input is float64), on the inputs' device.
    """
    if not areal_density:
        raise ValueError("areal_density needs at least one material")
    names = list(areal_density)
    tensors = torch.broadcast_tensors(*[torch.as_tensor(areal_density[n]) for n in names])
    dtype = torch.float64 if any(t.dtype == torch.float64 for t in tensors) else torch.float32
    device = tensors[0].device
    shape = tensors[0].shape
    a = torch.stack([t.reshape(-1) for t in tensors]).to(dtype)  # (M, N) g/cm²
    mu = torch.as_tensor(mass_attenuation_table(names, spectrum.energies_keV).T, dtype=dtype, device=device)
    w = torch.as_tensor(
        detector_weights(spectrum, detector=detector, scintillator_csi_mm=scintillator_csi_mm),
        dtype=dtype,
        device=device,
    )
    n_pix = a.shape[1]
    n_e = mu.shape[0]
    e_chunk = max(1, min(n_e, chunk_elements // max(n_pix, 1)))
    p_chunk = n_pix if e_chunk > 1 else max(1, chunk_elements)
    out = torch.zeros(n_pix, dtype=dtype, device=device)
    for p0 in range(0, n_pix, p_chunk):
        a_p = a[:, p0 : p0 + p_chunk]
        acc = torch.zeros(a_p.shape[1], dtype=dtype, device=device)
        for e0 in range(0, n_e, e_chunk):
            # (e, M) @ (M, n) → line integrals per energy; exp then weighted sum over energies.
            acc += w[e0 : e0 + e_chunk] @ torch.exp(-(mu[e0 : e0 + e_chunk] @ a_p))
        out[p0 : p0 + p_chunk] = acc
    return out.reshape(shape)


@dataclasses.dataclass(frozen=True)
class XrayPhysics:
    """Polychromatic X-ray image formation with scatter, detector blur and noise.

    ``apply`` runs: primary ``P = I/I0`` (:func:`polychromatic_intensity`) → plus scatter
    (:func:`noise.scatter_estimate`) → quantum noise, counts ~ Poisson(N0·(P + S)) → scintillator
    blur (Gaussian PSF + Lorentzian glare tail, acting on the detected quanta) → electronic noise
    (Gaussian, in detected-photon units) → clip to ≥ 1 photon → ``gain·(−ln(counts/N0)) + offset``.

    Attributes:
        kvp: tube potential in kV (60–120, spectra interpolated between tabulated kVps).
        filtration: tabulated total filtration (``"al2.5"`` or ``"al2.5_cu0.1"``).
        extra_filtration_mm: extra (material, thickness mm) filters applied with xraylib μ.
        detector: ``"energy_integrating"`` (flat panel) or ``"photon_counting"``.
        scintillator_csi_mm: CsI thickness in mm for the spectral absorption efficiency (0: ideal).
        photons_per_pixel: N0, mean detected photons per detector pixel in the flat field (the
            authors use 5000 on the 0.194 mm pixels of the 1536² detector); a binned pixel collects
            the photons of all its detector pixels (see :meth:`with_pixel_scale`). ``None`` gives
            the noise-free image (no quantum or electronic noise).
        electronic_noise_std: additive Gaussian noise std per detector pixel in detected-photon
            units.
        blur_sigma_px: Gaussian PSF std in pixels.
        glare_fraction: weight of the Lorentzian tail of the PSF (veiling glare), 0–1.
        glare_gamma_px: Lorentzian scale in pixels.
        scatter_to_primary: scatter-to-primary ratio behind a wide uniform object of line integral
            ``scatter_reference_line_integral`` (0 disables scatter).
        scatter_reference_line_integral: −ln(P) at which the SPR equals ``scatter_to_primary``.
        scatter_sigma_px: scatter kernel std in pixels.
        scatter_downsample: compute the scatter on this many times coarser pixels (see
            :func:`~fluoronav.simulation.noise.scatter_estimate`; 1 = full resolution).
        gain: multiplies the log image.
        offset: added to the log image.
        energy_bin_keV: width of the energy bins summed over (the table has 1 keV bins; wider bins
            are merged by :meth:`Spectrum.rebinned`, proportionally faster).
        custom_spectrum: use this incident spectrum instead of the tabulated one (``kvp``,
            ``filtration`` and ``extra_filtration_mm`` are then ignored), e.g.
            ``Spectrum.monoenergetic(60.0)``.
    """

    kvp: float = 90.0
    filtration: str = DEFAULT_FILTRATION
    extra_filtration_mm: tuple[tuple[str, float], ...] = ()
    detector: DetectorKind = "energy_integrating"
    scintillator_csi_mm: float = 0.6
    photons_per_pixel: float | None = 5000.0
    electronic_noise_std: float = 1.0
    blur_sigma_px: float = 0.5
    glare_fraction: float = 0.02
    glare_gamma_px: float = 8.0
    scatter_to_primary: float = 0.2
    scatter_reference_line_integral: float = 4.0
    scatter_sigma_px: float = 40.0
    scatter_downsample: int = 1
    gain: float = 1.0
    offset: float = 0.0
    custom_spectrum: Spectrum | None = None
    energy_bin_keV: float = 1.0  # noqa: N815 (unit suffix)

    def __post_init__(self) -> None:
        if self.photons_per_pixel is not None and self.photons_per_pixel <= 0:
            raise ValueError("photons_per_pixel must be > 0 or None")
        if not 0.0 <= self.glare_fraction <= 1.0:
            raise ValueError("glare_fraction must be in [0, 1]")
        if self.scatter_to_primary < 0 or self.scatter_reference_line_integral <= 0:
            raise ValueError("scatter_to_primary must be ≥ 0 and scatter_reference_line_integral > 0")
        for name in ("electronic_noise_std", "blur_sigma_px", "glare_gamma_px", "scatter_sigma_px"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be ≥ 0")

    def with_pixel_scale(self, factor: float) -> XrayPhysics:
        """The same physics for pixels ``factor`` times larger, e.g. after 2× binning ``factor=2``.

        Blur, glare and scatter widths in pixels are divided by ``factor``; a binned pixel sums the
        photons of ``factor²`` detector pixels (N0 × factor²) and their independent read-out noise
        (std × factor), so binning lowers the relative quantum noise as a real detector's does.
        """
        if factor <= 0:
            raise ValueError("factor must be > 0")
        area = factor * factor
        return dataclasses.replace(
            self,
            blur_sigma_px=self.blur_sigma_px / factor,
            glare_gamma_px=self.glare_gamma_px / factor,
            scatter_sigma_px=self.scatter_sigma_px / factor,
            photons_per_pixel=None if self.photons_per_pixel is None else self.photons_per_pixel * area,
            electronic_noise_std=self.electronic_noise_std * factor,
        )

    @functools.cached_property
    def spectrum(self) -> Spectrum:
        """Normalised incident spectrum (bins below 1e-6 of the peak dropped)."""
        if self.custom_spectrum is not None:
            return self.custom_spectrum.normalized()
        s = load_spectrum(
            self.kvp, filtration=self.filtration, extra_filtration_mm=dict(self.extra_filtration_mm)
        )
        s = s.trimmed()
        if self.energy_bin_keV > 1.0:
            s = s.rebinned(self.energy_bin_keV)
        return s.normalized()

    def primary(self, areal_density: Mapping[str, torch.Tensor]) -> torch.Tensor:
        """Noise-free primary transmission I/I0, (…, H, W) (see :func:`polychromatic_intensity`)."""
        return polychromatic_intensity(
            areal_density, self.spectrum, detector=self.detector, scintillator_csi_mm=self.scintillator_csi_mm
        )

    def detected(
        self,
        areal_density: Mapping[str, torch.Tensor],
        *,
        generator: torch.Generator | None = None,
        seed: int | None = None,
    ) -> torch.Tensor:
        """Flat-field-normalised detector signal (…, H, W) before the log (≥ 1/N0 with noise).

        Args:
            areal_density: material name → (…, H, W) g/cm².
            generator: torch generator on the inputs' device (needed when ``photons_per_pixel`` is
                set, unless ``seed`` is given).
            seed: seed for a fresh generator on the inputs' device.
        """
        p = self.primary(areal_density)
        total = p + noise.scatter_estimate(
            p,
            scatter_to_primary=self.scatter_to_primary,
            reference_line_integral=self.scatter_reference_line_integral,
            sigma_px=self.scatter_sigma_px,
            downsample=self.scatter_downsample,
        )
        noisy = self.photons_per_pixel is not None
        if noisy and generator is None:
            if seed is None:
                raise ValueError("noise is enabled: pass generator= or seed= (no global RNG state is used)")
            generator = torch.Generator(device=p.device).manual_seed(int(seed))
        n0 = 1.0 if self.photons_per_pixel is None else float(self.photons_per_pixel)
        counts = n0 * total
        if self.photons_per_pixel is not None:
            counts = noise.poisson_counts(counts, generator=generator)
        counts = noise.filter_image(
            counts,
            gaussian_sigma_px=self.blur_sigma_px,
            lorentz_fraction=self.glare_fraction,
            lorentz_gamma_px=self.glare_gamma_px,
        )
        if noisy:
            counts = counts + noise.gaussian_noise(counts, self.electronic_noise_std, generator=generator)
        floor = 1.0 if self.photons_per_pixel is not None else float(torch.finfo(counts.dtype).tiny)
        return counts.clamp_min(floor) / n0

    def apply(
        self,
        areal_density: Mapping[str, torch.Tensor],
        *,
        generator: torch.Generator | None = None,
        seed: int | None = None,
    ) -> torch.Tensor:
        """Simulated X-ray image after the log transform, ``gain·(−ln(I/I0)) + offset``.

        Args:
            areal_density: material name → (…, H, W) tensor of ``∫ρ_m dl`` in g/cm².
            generator: torch generator on the inputs' device (or pass ``seed``).
            seed: seed for a fresh generator on the inputs' device.

        Returns:
            (…, H, W) float32 (float64 for float64 inputs) image; air ≈ 0, bone and metal bright.
        """
        signal = self.detected(areal_density, generator=generator, seed=seed)
        return self.gain * -torch.log(signal) + self.offset
