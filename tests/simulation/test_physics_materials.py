"""Materials (xraylib μ/ρ) and the HU → material decomposition."""

from __future__ import annotations

import numpy as np
import pytest
import xraylib

from fluoronav.errors import InputError
from fluoronav.simulation.materials import (
    CT_MATERIALS,
    MATERIALS,
    areal_density_g_cm2,
    decompose_hu,
    hu_to_density,
    linear_attenuation_per_mm,
    mass_attenuation,
)

# NIST XCOM total attenuation with coherent scattering for liquid water (cm²/g).
WATER_XCOM = {30.0: 0.3756, 60.0: 0.2059, 100.0: 0.1707}


def test_required_materials_exist_with_unit_weight_fractions() -> None:
    for name in (
        "air",
        "water",
        "soft_tissue",
        "adipose",
        "bone_cortical",
        "bone_cancellous",
        "nitinol",
        "stainless_steel",
        "titanium",
    ):
        m = MATERIALS[name]
        assert sum(w for _, w in m.composition) == pytest.approx(1.0, abs=1e-9)
    nitinol = MATERIALS["nitinol"]
    assert dict(nitinol.composition)["Ni"] == pytest.approx(0.558, abs=0.003)
    assert nitinol.density_g_cm3 == pytest.approx(6.45)
    assert MATERIALS["water"].density_g_cm3 == pytest.approx(1.0)
    assert MATERIALS["bone_cancellous"].density_g_cm3 == pytest.approx(1.18)


def test_water_matches_nist_xcom_within_1_percent() -> None:
    energies = np.array(sorted(WATER_XCOM))
    mu = mass_attenuation("water", energies)
    np.testing.assert_allclose(mu, [WATER_XCOM[e] for e in energies], rtol=0.01)
    np.testing.assert_allclose(linear_attenuation_per_mm("water", [60.0]), 0.02059, rtol=0.01)


@pytest.mark.parametrize(
    ("name", "nist"),
    [
        ("soft_tissue", "Tissue, Soft (ICRP)"),
        ("bone_cortical", "Bone, Cortical (ICRP)"),
        ("adipose", "Adipose Tissue (ICRP)"),
        ("air", "Air, Dry (near sea level)"),
    ],
)
def test_compounds_match_xraylib_compound_parser(name: str, nist: str) -> None:
    energies = np.arange(15.0, 121.0, 15.0)
    ref = np.array([xraylib.CS_Total_CP(nist, float(e)) for e in energies])
    np.testing.assert_allclose(mass_attenuation(name, energies), ref, rtol=1e-5)


def test_metal_attenuation_from_elements() -> None:
    e = np.array([40.0, 80.0])
    ni, ti = xraylib.SymbolToAtomicNumber("Ni"), xraylib.SymbolToAtomicNumber("Ti")
    ref = [0.558 * xraylib.CS_Total(ni, x) + 0.442 * xraylib.CS_Total(ti, x) for x in e]
    np.testing.assert_allclose(mass_attenuation("nitinol", e), ref, rtol=1e-9)
    # Metals attenuate far more than bone per gram below the tungsten K-edge region.
    assert np.all(mass_attenuation("stainless_steel", e) > mass_attenuation("bone_cortical", e))


def test_unknown_material() -> None:
    with pytest.raises(InputError):
        mass_attenuation("unobtainium", [60.0])


def test_mm_to_g_cm2() -> None:
    # 100 mm of water (1 g/cm³) is 10 g/cm².
    assert areal_density_g_cm2(1.0 * 100.0) == pytest.approx(10.0)


def test_hu_to_density_anchors_and_monotone() -> None:
    assert hu_to_density(np.array([0.0]))[0] == pytest.approx(1.0, abs=0.01)
    assert hu_to_density(np.array([-1000.0]))[0] == pytest.approx(0.0, abs=0.002)
    hu = np.linspace(-1200, 3000, 42001)
    rho = hu_to_density(hu)
    assert np.all(np.diff(rho) >= 0)
    assert np.max(np.abs(np.diff(rho))) < 0.01  # continuous: 0.1 HU steps change ρ by < 0.01


def test_decompose_hu_partials_sum_to_total_and_are_physical() -> None:
    hu = np.linspace(-1200, 3000, 42001).astype(np.float32)
    parts = decompose_hu(hu)
    assert tuple(parts) == CT_MATERIALS
    total = sum(parts.values())
    np.testing.assert_allclose(total, hu_to_density(hu), rtol=1e-5, atol=1e-6)
    assert np.all(np.diff(total) >= -1e-6)
    for v in parts.values():
        assert v.dtype == np.float32 and np.all(v >= 0)
    at = {h: {k: float(v[0]) for k, v in decompose_hu(np.array([h])).items()} for h in (-1000, -500, 0, 1600)}
    assert at[-1000]["air"] == pytest.approx(0.0, abs=0.002) and sum(at[-1000].values()) < 0.002
    assert at[0]["soft_tissue"] == pytest.approx(1.0, abs=0.01) and at[0]["adipose"] == 0.0
    assert at[-500]["adipose"] > 0 and at[-500]["air"] == 0.0
    assert at[1600]["bone_cortical"] == pytest.approx(MATERIALS["bone_cortical"].density_g_cm3, rel=0.01)
    # Bone fraction grows with HU above the 350 HU threshold.
    bone = decompose_hu(np.array([300.0, 400.0, 800.0, 1200.0]))["bone_cortical"]
    assert bone[0] == 0.0 and np.all(np.diff(bone) > 0)


def test_decompose_hu_in_chunks_gives_every_voxel_the_same_value() -> None:
    """Chunks of any size, or a subset of the materials, change no value (bit for bit)."""
    from fluoronav.simulation.materials import decompose_hu

    rng = np.random.default_rng(3)
    hu = rng.uniform(-1100.0, 3000.0, (7, 11, 13)).astype(np.float32)
    hu.flat[:6] = [-1000.0, -800.0, -100.0, 350.0, 1600.0, 0.0]  # the ramps' nodes
    whole = decompose_hu(hu, chunk_voxels=hu.size)
    for chunk in (1, 97, 1000):
        parts = decompose_hu(hu, ("bone_cortical", "adipose"), chunk_voxels=chunk)
        assert set(parts) == {"bone_cortical", "adipose"}
        for m, density in parts.items():
            assert density.dtype == np.float32 and density.shape == hu.shape
            assert np.array_equal(density, whole[m]), (m, chunk)
    with pytest.raises(ValueError, match="unknown materials"):
        decompose_hu(hu, ("bone",))
