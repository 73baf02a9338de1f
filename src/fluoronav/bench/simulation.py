"""Benchmark of the data set simulation (``fluoronav bench`` key ``simulate_samples_per_s``).

At the default settings (the 1 mm hip phantom, 512² images binned from the 1536² detector, noise
on), after a warm-up (phantom build, numba compilation): ``_in_process``
(:meth:`XraySimulator.simulate` in this process), ``_workers`` (the ``simulate`` data set path,
:func:`run_tasks` on a Dask LocalCluster of 2 single-threaded workers, the rate after each worker's
first sample), the headline (the higher of the two), ``_baseline`` (the same scenes with scatter
convolved at full resolution and the spectrum in 1 keV bins, the accuracy reference of those two
speed-ups) and ``_speedup``. ``simulate_cpu_s_per_sample`` (and ``_baseline``) is the CPU time per
in-process sample, a load-independent cost: with C idle cores the data set path reaches at most
about C / it samples per second. Keys: docs/simulation.md ("Speed"); figures: docs/validation.md.
"""

from __future__ import annotations

import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.simulation.physics import XrayPhysics
from fluoronav.simulation.scene import sample_scene
from fluoronav.simulation.xray import SimulationConfig, XraySimulator

log = logging.getLogger(__name__)

__all__ = ["BASELINE_CONFIG", "run"]

#: the naive configuration the speed-ups are measured against
BASELINE_CONFIG = SimulationConfig(physics=XrayPhysics(energy_bin_keV=1.0, scatter_downsample=1))


def _rate(sim: XraySimulator, scenes: list, *, seed: int) -> tuple[float, float]:
    """(samples per second of wall time, CPU seconds per sample of this process)."""
    sim.simulate(scenes[0], seed=seed)  # warm-up (compilation, caches)
    t0, c0 = time.perf_counter(), time.process_time()
    for i, scene in enumerate(scenes[1:]):
        sim.simulate(scene, seed=seed + i)
    n = len(scenes) - 1
    return n / (time.perf_counter() - t0), (time.process_time() - c0) / n


def _workers_rate(n: int, workers: int, device: str) -> float:
    from fluoronav.simulation.dataset import DatasetSpec, simulate_dataset

    stamps: list[float] = []
    spec = DatasetSpec(n_phantoms=1, seed=12345, device=device)
    with tempfile.TemporaryDirectory(prefix="fluoronav-bench-") as tmp:
        simulate_dataset(
            Path(tmp),
            n,
            spec,
            workers=workers,
            on_result=lambda _row: stamps.append(time.perf_counter()),
            contact_sheet_png=False,
        )
    if len(stamps) <= workers:
        return float("nan")
    return (len(stamps) - workers) / (stamps[-1] - stamps[workers - 1])


def run(quick: bool = False, device: str = "cpu") -> dict[str, float]:
    """Measure the simulation throughput and its baseline on ``device`` (see the module docstring;
    on CUDA the workers share the one GPU)."""
    n = 3 if quick else 6
    volume = hip_phantom(seed=0)
    rng = np.random.default_rng(2024)
    scenes = [sample_scene(volume, rng) for _ in range(n)]
    fast, fast_cpu = _rate(XraySimulator(volume, config=SimulationConfig(), device=device), scenes, seed=1)
    base, base_cpu = _rate(XraySimulator(volume, config=BASELINE_CONFIG, device=device), scenes, seed=1)
    workers = _workers_rate(6 if quick else 12, 2, device)
    headline = max(fast, workers) if np.isfinite(workers) else fast
    log.info("simulate: %.3f samples/s in process, %.3f with 2 workers, baseline %.3f", fast, workers, base)
    return {
        "simulate_samples_per_s": headline,
        "simulate_samples_per_s_in_process": fast,
        "simulate_samples_per_s_workers": workers,
        "simulate_samples_per_s_baseline": base,
        "simulate_samples_per_s_speedup": headline / base,
        "simulate_cpu_s_per_sample": fast_cpu,
        "simulate_cpu_s_per_sample_baseline": base_cpu,
    }
