"""Materials, their mass attenuation coefficients and the CT material decomposition.

Units: mass attenuation coefficients μ/ρ in cm²/g, densities in g/cm³, areal densities
(``∫ρ dl``) in g/cm², photon energies in keV. The renderers integrate in mm, so a density
integral ``∫ρ dl`` in (g/cm³)·mm becomes g/cm² through :func:`areal_density_g_cm2`.

μ/ρ comes from xraylib (``CS_Total``: photoelectric + coherent + incoherent, i.e. the narrow-beam
total attenuation): elements through ``CS_Total(Z, E)``, compounds as the weight-fraction sum
``Σ_i w_i (μ/ρ)_i``. Compositions of the tissues are the NIST/ICRP ones shipped with xraylib.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import xraylib

from fluoronav.errors import InputError

logger = logging.getLogger(__name__)

MM_PER_CM = 10.0


@dataclass(frozen=True)
class Material:
    """A homogeneous material.

    Attributes:
        name: key used everywhere (``"soft_tissue"``...).
        composition: element symbol → mass fraction (sums to 1).
        density_g_cm3: nominal density in g/cm³ (the CT decomposition overrides it per voxel).
        source: where the composition and density come from.
    """

    name: str
    composition: tuple[tuple[str, float], ...]
    density_g_cm3: float
    source: str


def _nist(name: str, nist_name: str, density_g_cm3: float | None = None) -> Material:
    data = xraylib.GetCompoundDataNISTByName(nist_name)
    comp = tuple(
        (xraylib.AtomicNumberToSymbol(int(z)), float(w))
        for z, w in zip(data["Elements"], data["massFractions"], strict=True)
    )
    density = float(data["density"]) if density_g_cm3 is None else density_g_cm3
    return Material(name, _normalise(comp), density, f"NIST via xraylib: {nist_name!r}")


def _normalise(comp: tuple[tuple[str, float], ...]) -> tuple[tuple[str, float], ...]:
    total = sum(w for _, w in comp)
    return tuple((s, w / total) for s, w in comp)


def _mixture(
    name: str, parts: Sequence[tuple[Material, float]], density_g_cm3: float, source: str
) -> Material:
    """Mass-fraction mixture of materials (``parts`` = (material, mass fraction))."""
    acc: dict[str, float] = {}
    for material, fraction in parts:
        for symbol, w in material.composition:
            acc[symbol] = acc.get(symbol, 0.0) + fraction * w
    return Material(name, _normalise(tuple(acc.items())), density_g_cm3, source)


def _build_materials() -> dict[str, Material]:
    air = _nist("air", "Air, Dry (near sea level)")
    water = _nist("water", "Water, Liquid")
    soft = _nist("soft_tissue", "Tissue, Soft (ICRP)", 1.03)
    adipose = _nist("adipose", "Adipose Tissue (ICRP)", 0.95)
    cortical = _nist("bone_cortical", "Bone, Cortical (ICRP)")
    # Spongiosa as red-marrow-like soft tissue plus trabecular (cortical-composition) bone at a
    # volume fraction giving 1.18 g/cm³ (ICRU 46 adult spongiosa density).
    rho_sp = 1.18
    vol_bone = (rho_sp - soft.density_g_cm3) / (cortical.density_g_cm3 - soft.density_g_cm3)
    mass_bone = vol_bone * cortical.density_g_cm3 / rho_sp
    cancellous = _mixture(
        "bone_cancellous",
        [(cortical, mass_bone), (soft, 1.0 - mass_bone)],
        rho_sp,
        f"soft tissue + cortical bone mixture, bone mass fraction {mass_bone:.3f}, 1.18 g/cm³",
    )
    metals = [
        Material("nitinol", (("Ni", 0.558), ("Ti", 0.442)), 6.45, "NiTi, 55.8 wt% Ni (ASTM F2063)"),
        Material(
            "stainless_steel",
            _normalise(
                (("Fe", 0.6545), ("Cr", 0.17), ("Ni", 0.12), ("Mo", 0.025), ("Mn", 0.02), ("Si", 0.0075))
            ),
            8.0,
            "AISI 316L nominal composition",
        ),
        Material("titanium", (("Ti", 1.0),), 4.506, "pure Ti"),
        Material("aluminium", (("Al", 1.0),), 2.699, "pure Al (filtration)"),
        Material("copper", (("Cu", 1.0),), 8.96, "pure Cu (filtration)"),
        _nist("csi", "Cesium Iodide"),
    ]
    return {m.name: m for m in [air, water, soft, adipose, cortical, cancellous, *metals]}


MATERIALS: dict[str, Material] = _build_materials()


def get_material(name: str) -> Material:
    """Look up a material by name; raises :class:`InputError` for unknown names."""
    try:
        return MATERIALS[name]
    except KeyError:
        raise InputError("material", f"unknown material {name!r}; known: {', '.join(MATERIALS)}") from None


@functools.lru_cache(maxsize=256)
def _mass_attenuation_cached(name: str, energies: tuple[float, ...]) -> np.ndarray:
    material = get_material(name)
    out = np.zeros(len(energies), dtype=np.float64)
    for symbol, w in material.composition:
        z = xraylib.SymbolToAtomicNumber(symbol)
        out += w * np.array([xraylib.CS_Total(z, e) for e in energies])
    out.setflags(write=False)
    return out


def mass_attenuation(name: str, energies_keV: np.ndarray | Sequence[float]) -> np.ndarray:
    """Mass attenuation coefficient μ/ρ of a material.

    Args:
        name: material name (a key of :data:`MATERIALS`).
        energies_keV: (E,) photon energies in keV (1–1000).

    Returns:
        (E,) float64 μ/ρ in cm²/g (read-only, cached).
    """
    energies = tuple(float(e) for e in np.atleast_1d(np.asarray(energies_keV, dtype=np.float64)))
    return _mass_attenuation_cached(name, energies)


def linear_attenuation_per_mm(
    name: str, energies_keV: np.ndarray | Sequence[float], density_g_cm3: float | None = None
) -> np.ndarray:
    """Linear attenuation μ in 1/mm at ``density_g_cm3`` (nominal density by default); (E,) float64."""
    rho = get_material(name).density_g_cm3 if density_g_cm3 is None else density_g_cm3
    return mass_attenuation(name, energies_keV) * rho / MM_PER_CM


def mass_attenuation_table(names: Sequence[str], energies_keV: np.ndarray | Sequence[float]) -> np.ndarray:
    """(M, E) float64 table of μ/ρ in cm²/g for ``names`` × ``energies_keV``."""
    return np.stack([mass_attenuation(n, energies_keV) for n in names])


def areal_density_g_cm2(density_times_length_g_cm3_mm: np.ndarray | float) -> np.ndarray | float:
    """Convert a renderer's ``∫ρ dl`` with ρ in g/cm³ and l in mm to an areal density in g/cm²."""
    return density_times_length_g_cm3_mm / MM_PER_CM


# ---------------------------------------------------------------------------------------------
# CT material decomposition (HU → per-material partial densities)
# ---------------------------------------------------------------------------------------------

#: Materials produced by :func:`decompose_hu`, in this order.
CT_MATERIALS: tuple[str, ...] = ("air", "adipose", "soft_tissue", "bone_cortical")

#: Piecewise-linear HU → mass density calibration nodes (HU, g/cm³); linear extrapolation above the
#: last node with the slope of the last segment. Air, ICRP adipose, water, ICRP cortical bone (1.85
#: g/cm³); the bone segment (5.3e-4 g/cm³ per HU) is close to Schneider et al. 2000's bone line.
HU_DENSITY_NODES: tuple[tuple[float, float], ...] = (
    (-1000.0, 0.001205),
    (-100.0, 0.95),
    (0.0, 1.0),
    (1600.0, 1.85),
)
AIR_MAX_HU = -800.0
BONE_MIN_HU = 350.0
CORTICAL_HU = 1600.0
ADIPOSE_HU = -100.0
#: voxels :func:`decompose_hu` splits at a time (its float64 temporaries: ~0.1 GB)
DECOMPOSE_CHUNK_VOXELS = 1 << 22


def hu_to_density(hu: np.ndarray) -> np.ndarray:
    """Total mass density (g/cm³) from HU by :data:`HU_DENSITY_NODES`; continuous, non-decreasing.

    Args:
        hu: array of Hounsfield units (any shape).

    Returns:
        float32 array of the same shape; HU ≤ −1000 gives the density of air.
    """
    hu = np.asarray(hu, dtype=np.float64)
    xs = np.array([n[0] for n in HU_DENSITY_NODES])
    ys = np.array([n[1] for n in HU_DENSITY_NODES])
    rho = np.interp(hu, xs, ys)
    slope = (ys[-1] - ys[-2]) / (xs[-1] - xs[-2])
    above = hu > xs[-1]
    rho = np.where(above, ys[-1] + slope * (hu - xs[-1]), rho)
    return rho.astype(np.float32)


def decompose_hu(
    hu: np.ndarray, materials: Sequence[str] = CT_MATERIALS, *, chunk_voxels: int = DECOMPOSE_CHUNK_VOXELS
) -> dict[str, np.ndarray]:
    """Split a CT into per-material partial densities (DeepDRR-style, with soft mixing ramps).

    With ρ = :func:`hu_to_density` (HU):

    - HU < −800: all of ρ is ``air``.
    - −800 ≤ HU ≤ 350 (tissue): adipose mass fraction ``f_a = clip(−HU/100, 0, 1)``, the rest
      ``soft_tissue`` (−100 HU and below is fat-like; lung is then low-density adipose, which
      attenuates almost like lung tissue).
    - HU > 350 (bone): ``bone_cortical`` mass fraction ``f_b = clip((HU − 350)/(1600 − 350), 0, 1)``,
      the rest ``soft_tissue`` (so spongiosa is a soft-tissue/bone mixture).

    The partial densities sum to ρ in every voxel (total density is continuous and non-decreasing in
    HU); only the air/adipose switch at −800 HU changes composition abruptly. The volume is split in
    chunks of ``chunk_voxels`` so that a fine patient's float64 temporaries stay small; every voxel
    gets the same value as in one piece.

    Args:
        hu: (…) array of Hounsfield units.
        materials: the materials to return (a subset of :data:`CT_MATERIALS`).
        chunk_voxels: voxels decomposed at a time.

    Returns:
        material name → (…) float32 partial density in g/cm³.
    """
    unknown = set(materials) - set(CT_MATERIALS)
    if unknown:
        raise ValueError(f"unknown materials {sorted(unknown)}; known: {CT_MATERIALS}")
    flat = np.asarray(hu, dtype=np.float32).reshape(-1)
    out = {m: np.empty(flat.shape, dtype=np.float32) for m in materials}
    for lo in range(0, flat.size, max(int(chunk_voxels), 1)):
        part = _decompose_chunk(flat[lo : lo + chunk_voxels])
        for m in materials:
            out[m][lo : lo + chunk_voxels] = part[m]
    return {m: v.reshape(np.shape(hu)) for m, v in out.items()}


def _decompose_chunk(hu: np.ndarray) -> dict[str, np.ndarray]:
    """:func:`decompose_hu` of a float32 (N,) chunk, every material."""
    rho = hu_to_density(hu)
    is_air = hu < AIR_MAX_HU
    is_bone = hu > BONE_MIN_HU
    is_tissue = ~is_air & ~is_bone
    f_adipose = np.clip(hu / ADIPOSE_HU, 0.0, 1.0)  # clip(-HU/100, 0, 1)
    f_adipose = np.where(is_tissue, f_adipose, 0.0)
    f_bone = np.where(is_bone, np.clip((hu - BONE_MIN_HU) / (CORTICAL_HU - BONE_MIN_HU), 0.0, 1.0), 0.0)
    zero = np.zeros_like(rho)
    out = {
        "air": np.where(is_air, rho, zero),
        "adipose": (rho * f_adipose).astype(np.float32),
        "soft_tissue": np.where(is_air, zero, rho * (1.0 - f_adipose - f_bone)).astype(np.float32),
        "bone_cortical": (rho * f_bone).astype(np.float32),
    }
    return {k: v.astype(np.float32) for k, v in out.items()}
