"""Tube spectra: shipped table, interpolation, normalisation, filtration."""

from __future__ import annotations

from importlib import resources

import numpy as np
import pytest

from fluoronav.errors import InputError
from fluoronav.simulation.materials import mass_attenuation
from fluoronav.simulation.spectrum import Spectrum, available_filtrations, load_spectrum, spectrum_table


def test_table_is_small_and_described() -> None:
    path = resources.files("fluoronav") / "data" / "spectra.npz"
    with resources.as_file(path) as p:
        assert p.stat().st_size < 200_000
    table = spectrum_table()
    assert table["metadata"]["spekpy_version"]
    assert table["metadata"]["anode_angle_deg"] == pytest.approx(12.0)
    assert set(available_filtrations()) == {"al2.5", "al2.5_cu0.1"}
    assert table["fluence"].shape == (2, len(table["kvps"]), len(table["energies_keV"]))
    np.testing.assert_allclose(np.diff(table["energies_keV"]), 1.0)


@pytest.mark.parametrize("filtration", ["al2.5", "al2.5_cu0.1"])
@pytest.mark.parametrize("kvp", [60.0, 77.5, 90.0, 120.0])
def test_normalised_spectrum_sums_to_one_and_ends_at_kvp(kvp: float, filtration: str) -> None:
    s = load_spectrum(kvp, filtration=filtration)
    assert s.total == pytest.approx(1.0, abs=1e-12)
    assert s.energies_keV.max() < kvp
    assert s.energies_keV.max() > kvp - 1.0
    assert s.energies_keV.min() == pytest.approx(10.5)
    assert np.all(s.fluence >= 0)


def test_absolute_spectrum_matches_table_at_tabulated_kvp() -> None:
    table = spectrum_table()
    ki = int(np.nonzero(table["kvps"] == 90.0)[0][0])
    s = load_spectrum(90.0, normalize=False)
    ref = table["fluence"][0, ki, : len(s.fluence)]
    np.testing.assert_allclose(s.fluence, ref, rtol=1e-6)
    # Photons per mAs per cm² at 1 m for a 90 kVp, 2.5 mm Al beam: order 1e8 (SpekPy ~2e8 total).
    assert 5e7 < s.total < 1e9


def test_mean_energy_matches_spekpy_and_rises_with_kvp_and_filtration() -> None:
    table = spectrum_table()
    for fi, name in enumerate(available_filtrations()):
        for ki, kvp in enumerate(table["kvps"]):
            # SpekPy's mean includes < 10 keV photons, which 2.5 mm Al leaves negligible.
            assert load_spectrum(float(kvp), filtration=name).mean_energy_keV == pytest.approx(
                table["mean_energy_keV"][fi, ki], rel=5e-3
            )
    kvps = np.arange(60.0, 120.01, 2.5)
    for name in available_filtrations():
        means = np.array([load_spectrum(k, filtration=name).mean_energy_keV for k in kvps])
        assert np.all(np.diff(means) > 0)
    for k in kvps:
        assert load_spectrum(k, filtration="al2.5_cu0.1").mean_energy_keV > load_spectrum(k).mean_energy_keV


def test_interpolation_is_continuous_in_kvp() -> None:
    a, b = load_spectrum(90.0), load_spectrum(89.99)
    assert np.abs(a.fluence[: len(b.fluence)] - b.fluence).sum() < 1e-3
    assert a.mean_energy_keV == pytest.approx(b.mean_energy_keV, rel=1e-3)


def test_extra_filtration_uses_beer_lambert() -> None:
    base = load_spectrum(90.0, normalize=False)
    filtered = base.filtered("copper", 0.1)
    expected = base.fluence * np.exp(-mass_attenuation("copper", base.energies_keV) * 8.96 * 0.01)
    np.testing.assert_allclose(filtered.fluence, expected, rtol=1e-12)
    assert filtered.total < base.total
    assert filtered.mean_energy_keV > base.mean_energy_keV
    via_loader = load_spectrum(90.0, extra_filtration_mm={"copper": 0.1})
    np.testing.assert_allclose(via_loader.fluence, filtered.normalized().fluence, rtol=1e-12)


def test_errors() -> None:
    with pytest.raises(InputError):
        load_spectrum(150.0)
    with pytest.raises(InputError):
        load_spectrum(90.0, filtration="lead")
    with pytest.raises(InputError):
        Spectrum(np.array([50.0, 60.0]), np.array([1.0]))
    with pytest.raises(InputError):
        load_spectrum(90.0).filtered("copper", -1.0)


def test_rebinned_spectrum_keeps_transmission_within_half_a_percent() -> None:
    import torch

    from fluoronav.simulation.physics import XrayPhysics

    fine = XrayPhysics(photons_per_pixel=None)
    coarse = XrayPhysics(photons_per_pixel=None, energy_bin_keV=3.0)
    assert len(coarse.spectrum.energies_keV) < len(fine.spectrum.energies_keV) / 2.5
    assert coarse.spectrum.mean_energy_keV == pytest.approx(fine.spectrum.mean_energy_keV, rel=1e-9)
    for material, rho in (("water", 1.0), ("bone_cortical", 1.85), ("nitinol", 6.45)):
        t_cm = torch.tensor([0.1, 1.0, 5.0, 10.0, 30.0], dtype=torch.float64)
        if material == "nitinol":
            t_cm = t_cm / 50.0
        a = {material: t_cm * rho}
        lf = -torch.log(fine.primary(a))
        lc = -torch.log(coarse.primary(a))
        assert torch.allclose(lc, lf, rtol=5e-3), (material, lf, lc)
