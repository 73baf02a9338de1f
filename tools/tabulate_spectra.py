"""Tabulate X-ray tube spectra with SpekPy into ``src/fluoronav/data/spectra.npz`` (build time only).

SpekPy is a build-time dependency (``pip install fluoronav[build]``); the package reads the shipped
table and never imports SpekPy.

The table holds the photon fluence per 1 keV energy bin, in photons / (cm² · mAs) at 1 m from the
focal spot, of a tungsten-anode tube (anode angle 12°) for every tube potential in ``KVPS`` and for
each total filtration in ``FILTRATIONS``. All spectra share one energy grid: bin ``i`` covers
``[E_MIN_KEV + i, E_MIN_KEV + i + 1)`` keV and is stored at its centre; bins above the tube potential
hold zero. Usage::

    python tools/tabulate_spectra.py [--out src/fluoronav/data/spectra.npz]
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

logger = logging.getLogger("tabulate_spectra")

KVPS = np.arange(60.0, 121.0, 5.0)
ANODE_ANGLE_DEG = 12.0
E_MIN_KEV = 10.0
E_MAX_KEV = 120.0
BIN_KEV = 1.0
DISTANCE_CM = 100.0
# Total filtration (inherent + added), as SpekPy (material, thickness_mm) pairs.
FILTRATIONS: dict[str, list[tuple[str, float]]] = {
    "al2.5": [("Al", 2.5)],
    "al2.5_cu0.1": [("Al", 2.5), ("Cu", 0.1)],
}


def tabulate() -> dict[str, np.ndarray]:
    """Run SpekPy for every (filtration, kVp) and return the arrays saved in the npz."""
    import spekpy

    edges = np.arange(E_MIN_KEV, E_MAX_KEV + BIN_KEV / 2, BIN_KEV)
    centres = 0.5 * (edges[:-1] + edges[1:])
    fluence = np.zeros((len(FILTRATIONS), len(KVPS), len(centres)), dtype=np.float64)
    hvl_mm_al = np.zeros((len(FILTRATIONS), len(KVPS)))
    mean_keV = np.zeros((len(FILTRATIONS), len(KVPS)))
    for fi, filters in enumerate(FILTRATIONS.values()):
        for ki, kvp in enumerate(KVPS):
            spek = spekpy.Spek(kvp=float(kvp), th=ANODE_ANGLE_DEG, dk=BIN_KEV, mas=1.0, z=DISTANCE_CM)
            for material, thickness_mm in filters:
                spek.filter(material, thickness_mm)
            # Mid-bin energies; fluence differential in energy (photons / cm² / keV / mAs at z).
            k, phi = spek.get_spectrum(edges=False, flu=True, diff=True)
            per_bin = np.asarray(phi) * BIN_KEV
            idx = np.round(np.asarray(k) - centres[0]).astype(int)
            keep = (idx >= 0) & (idx < len(centres))
            fluence[fi, ki, idx[keep]] = per_bin[keep]
            hvl_mm_al[fi, ki] = spek.get_hvl1()
            mean_keV[fi, ki] = spek.get_emean()
            logger.info(
                "%s %5.1f kVp: mean %.2f keV, HVL %.2f mm Al",
                filters,
                kvp,
                mean_keV[fi, ki],
                hvl_mm_al[fi, ki],
            )
    metadata = {
        "generator": "tools/tabulate_spectra.py",
        "spekpy_version": getattr(spekpy, "__version__", None) or _package_version("spekpy"),
        "anode": "W",
        "anode_angle_deg": ANODE_ANGLE_DEG,
        "distance_cm": DISTANCE_CM,
        "bin_keV": BIN_KEV,
        "fluence_unit": "photons / (cm^2 mAs) per energy bin at distance_cm",
        "filtrations": {name: [[m, t] for m, t in f] for name, f in FILTRATIONS.items()},
    }
    return {
        "energies_keV": centres.astype(np.float32),
        "kvps": KVPS.astype(np.float32),
        "filtrations": np.array(list(FILTRATIONS), dtype="U32"),
        "fluence": fluence.astype(np.float32),
        "hvl_mm_al": hvl_mm_al.astype(np.float32),
        "mean_energy_keV": mean_keV.astype(np.float32),
        "metadata_json": np.array(json.dumps(metadata)),
    }


def _package_version(name: str) -> str:
    from importlib.metadata import version

    return version(name)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default_out = Path(__file__).resolve().parents[1] / "src" / "fluoronav" / "data" / "spectra.npz"
    parser.add_argument("--out", type=Path, default=default_out)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    table = tabulate()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, **table)
    logger.info("wrote %s (%d bytes)", args.out, args.out.stat().st_size)


if __name__ == "__main__":
    main()
