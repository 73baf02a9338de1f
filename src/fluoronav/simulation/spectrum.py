"""X-ray tube spectra from the shipped SpekPy table (``fluoronav/data/spectra.npz``).

The table (made by ``tools/tabulate_spectra.py``) holds tungsten-anode spectra (12° anode) for
60–120 kVp every 5 kVp, 1 keV bins from 10 keV, for the total filtrations ``"al2.5"`` (2.5 mm Al)
and ``"al2.5_cu0.1"`` (2.5 mm Al + 0.1 mm Cu), as photons / (cm² · mAs) per bin at 1 m.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from importlib import resources
from typing import Any

import numpy as np

from fluoronav.errors import InputError
from fluoronav.simulation.materials import get_material, mass_attenuation

DEFAULT_FILTRATION = "al2.5"


@dataclass(frozen=True, eq=False)
class Spectrum:
    """A discrete photon spectrum.

    Attributes:
        energies_keV: (E,) float64 bin-centre photon energies in keV.
        fluence: (E,) float64 photons per bin (sums to 1 for a normalised spectrum; photons /
            (cm² · mAs) at 1 m for ``load_spectrum(..., normalize=False)``).
        kvp: tube potential in kV (``nan`` for a synthetic spectrum).
        label: human-readable description (filtration...).
    """

    energies_keV: np.ndarray  # noqa: N815 (unit suffix)
    fluence: np.ndarray
    kvp: float = float("nan")
    label: str = ""

    def __post_init__(self) -> None:
        e = np.atleast_1d(np.asarray(self.energies_keV, dtype=np.float64))
        f = np.atleast_1d(np.asarray(self.fluence, dtype=np.float64))
        if e.ndim != 1 or e.shape != f.shape or e.size == 0:
            raise InputError("spectrum", f"energies {e.shape} and fluence {f.shape} must be equal 1-D shapes")
        if np.any(f < 0) or not np.all(np.isfinite(f)) or f.sum() <= 0:
            raise InputError("spectrum", "fluence must be finite, non-negative and not all zero")
        object.__setattr__(self, "energies_keV", e)
        object.__setattr__(self, "fluence", f)

    @classmethod
    def monoenergetic(cls, energy_keV: float) -> Spectrum:
        """A single-energy spectrum with unit fluence."""
        return cls(np.array([energy_keV]), np.array([1.0]), kvp=float(energy_keV), label="monoenergetic")

    @property
    def total(self) -> float:
        """Sum of the fluence over all bins."""
        return float(self.fluence.sum())

    @property
    def mean_energy_keV(self) -> float:
        """Fluence-weighted mean photon energy in keV."""
        return float((self.fluence * self.energies_keV).sum() / self.fluence.sum())

    def normalized(self) -> Spectrum:
        """The same spectrum with fluence summing to 1."""
        return Spectrum(self.energies_keV, self.fluence / self.fluence.sum(), self.kvp, self.label)

    def trimmed(self, *, rel_threshold: float = 1e-6) -> Spectrum:
        """Drop bins whose fluence is below ``rel_threshold`` × the maximum (fewer energies to sum)."""
        keep = self.fluence >= rel_threshold * self.fluence.max()
        return Spectrum(self.energies_keV[keep], self.fluence[keep], self.kvp, self.label)

    def rebinned(self, width_keV: float) -> Spectrum:
        """Merge bins into ``width_keV`` wide bins at their fluence-weighted mean energies.

        Fewer energies make the polychromatic sum proportionally cheaper; with 3 keV bins the
        transmission through 0–30 cm of water or bone changes by well under 1 % (tests).
        """
        if width_keV <= 0:
            raise InputError("spectrum", f"bin width must be > 0 keV, got {width_keV}")
        e0 = float(self.energies_keV.min())
        idx = np.floor((self.energies_keV - e0) / width_keV + 1e-9).astype(int)
        fl = np.bincount(idx, weights=self.fluence)
        ef = np.bincount(idx, weights=self.fluence * self.energies_keV)
        keep = fl > 0
        return Spectrum(ef[keep] / fl[keep], fl[keep], self.kvp, self.label)

    def filtered(self, material: str, thickness_mm: float) -> Spectrum:
        """Attenuate by a slab of ``material`` at its nominal density (Beer–Lambert with xraylib μ/ρ).

        The result is not renormalised: its total is the transmitted fraction times the input total.
        """
        if thickness_mm < 0:
            raise InputError("filtration", f"thickness must be ≥ 0 mm, got {thickness_mm}")
        rho = get_material(material).density_g_cm3
        transmission = np.exp(-mass_attenuation(material, self.energies_keV) * rho * thickness_mm / 10.0)
        label = f"{self.label} + {thickness_mm:g} mm {material}".strip(" +")
        return Spectrum(self.energies_keV, self.fluence * transmission, self.kvp, label)


@functools.lru_cache(maxsize=1)
def _table() -> dict[str, Any]:
    path = resources.files("fluoronav") / "data" / "spectra.npz"
    with resources.as_file(path) as p, np.load(p, allow_pickle=False) as npz:
        table: dict[str, Any] = {k: npz[k] for k in npz.files}
    table["metadata"] = json.loads(str(table.pop("metadata_json")))
    return table


def spectrum_table() -> dict[str, Any]:
    """The shipped table: ``energies_keV`` (E,), ``kvps`` (K,), ``filtrations`` (F,), ``fluence``
    (F, K, E) photons/(cm² mAs) per bin at 1 m, ``hvl_mm_al`` (F, K), ``mean_energy_keV`` (F, K) (as
    SpekPy reports them) and ``metadata`` (dict: SpekPy version, anode angle, filtration details)."""
    return _table()


def available_filtrations() -> tuple[str, ...]:
    """Names of the tabulated total filtrations."""
    return tuple(str(f) for f in _table()["filtrations"])


def load_spectrum(
    kvp: float,
    *,
    filtration: str = DEFAULT_FILTRATION,
    extra_filtration_mm: dict[str, float] | None = None,
    normalize: bool = True,
) -> Spectrum:
    """Tube spectrum at ``kvp``, linearly interpolated in kVp between tabulated spectra.

    Args:
        kvp: tube potential in kV, within the tabulated range (60–120).
        filtration: one of :func:`available_filtrations` (``"al2.5"``, ``"al2.5_cu0.1"``).
        extra_filtration_mm: material name → thickness in mm added on top (xraylib attenuation).
        normalize: return fluence summing to 1 (default), else photons / (cm² · mAs) per bin at 1 m.

    Returns:
        :class:`Spectrum` on the 1 keV grid up to ``kvp`` (a bin straddling ``kvp`` is cut to its
        part below it).
    """
    table = _table()
    kvps = table["kvps"].astype(np.float64)
    names = available_filtrations()
    if filtration not in names:
        raise InputError("filtration", f"unknown filtration {filtration!r}; tabulated: {', '.join(names)}")
    if not kvps[0] <= kvp <= kvps[-1]:
        raise InputError("kvp", f"{kvp} kVp is outside the tabulated range {kvps[0]:g}–{kvps[-1]:g} kVp")
    flu = table["fluence"][names.index(filtration)].astype(np.float64)
    energies = table["energies_keV"].astype(np.float64)
    hi = int(np.clip(np.searchsorted(kvps, kvp), 1, len(kvps) - 1))
    t = (kvp - kvps[hi - 1]) / (kvps[hi] - kvps[hi - 1])
    fluence = (1.0 - t) * flu[hi - 1] + t * flu[hi]
    # Photons exist only below the tube potential: keep bins whose lower edge is below it, and
    # shrink a bin that straddles it to its valid part (fluence and centre).
    lower = energies - 0.5
    last = int(np.count_nonzero(lower < kvp - 1e-9))
    energies, fluence = energies[:last].copy(), fluence[:last].copy()
    valid = kvp - lower[last - 1]
    if valid < 1.0:
        fluence[-1] *= valid
        energies[-1] = lower[last - 1] + valid / 2.0
    spectrum = Spectrum(energies, fluence, float(kvp), f"{kvp:g} kVp, {filtration}")
    for material, thickness in (extra_filtration_mm or {}).items():
        spectrum = spectrum.filtered(material, thickness)
    return spectrum.normalized() if normalize else spectrum
