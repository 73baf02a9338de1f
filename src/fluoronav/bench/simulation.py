"""Benchmark of the data set simulation (``fluoronav bench`` key ``simulate_samples_per_s``).

At the default settings (the 1 mm hip phantom, 512² images from the 1536² detector, noise on), after a
warm-up: ``_in_process`` (:meth:`XraySimulator.simulate` here), ``_workers`` (the ``simulate`` path on a
Dask LocalCluster of 2 single-threaded workers, after each one's first sample), the headline (the higher),
``_baseline`` (scatter at full resolution, 1 keV spectrum bins: the accuracy reference) and ``_speedup``;
``simulate_cpu_s_per_sample`` (and ``_baseline``): CPU time per in-process sample, load-independent.
``simulate_realistic_samples_per_s``: the realistic world's data set (the 0.5 mm patient, navigation
scenes, randomisation, distractors) on 2 workers; ``simulate_realistic_peak_rss_gb``: the peak memory of
one such process. Keys: docs/simulation.md ("Speed"); figures: docs/validation.md.
"""

from __future__ import annotations

import logging
import resource
import subprocess
import sys
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


#: the realistic data set the bench times (``fluoronav simulate`` options)
REALISTIC_OPTIONS = (
    "--world", "realistic", "--phantoms", "1", "--scenes", "navigation",
    "--randomise", "realistic", "--distractors", "realistic",
)  # fmt: skip


def _realistic_peak_rss_gb(n: int, device: str) -> float:
    """Peak resident memory (GB) of a process that simulates ``n`` realistic samples in itself."""
    with tempfile.TemporaryDirectory(prefix="fluoronav-bench-") as tmp:
        argv = [
            "simulate",
            "--n",
            str(n),
            "--out",
            tmp,
            "--workers",
            "0",
            "--seed",
            "4242",
            "--device",
            device,
        ]
        code = "import sys; from fluoronav.cli.main import main; main(sys.argv[1:])"
        proc = subprocess.run([sys.executable, "-c", code, *argv, *REALISTIC_OPTIONS], capture_output=True)
        if proc.returncode != 0:
            raise RuntimeError(f"realistic simulate failed: {proc.stderr.decode()[-400:]}")
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e6  # kB on Linux


def _realistic_rate(n: int, workers: int, device: str) -> float:
    from fluoronav.simulation.dataset import DatasetSpec, simulate_dataset
    from fluoronav.simulation.distractors import DISTRACTORS_REALISTIC
    from fluoronav.simulation.randomisation import RANDOMISATION_REALISTIC
    from fluoronav.simulation.sample_variation import SampleVariation
    from fluoronav.simulation.world import REALISTIC

    stamps: list[float] = []
    variation = SampleVariation(randomisation=RANDOMISATION_REALISTIC, distractors=DISTRACTORS_REALISTIC)
    spec = DatasetSpec(
        n_phantoms=1, seed=4243, device=device, world=REALISTIC, scenes="navigation", variation=variation
    )
    with tempfile.TemporaryDirectory(prefix="fluoronav-bench-") as tmp:
        simulate_dataset(
            Path(tmp), n, spec, workers=workers, on_result=lambda _row: stamps.append(time.perf_counter()),
            contact_sheet_png=False,
        )  # fmt: skip
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
    peak_gb = _realistic_peak_rss_gb(2 if quick else 3, device)  # before any realistic worker ends
    realistic = _realistic_rate(4 if quick else 12, 2, device)
    log.info("simulate realistic: %.3f samples/s with 2 workers, %.2f GB per process", realistic, peak_gb)
    return {
        "simulate_realistic_samples_per_s": realistic,
        "simulate_realistic_peak_rss_gb": peak_gb,
        "simulate_samples_per_s": headline,
        "simulate_samples_per_s_in_process": fast,
        "simulate_samples_per_s_workers": workers,
        "simulate_samples_per_s_baseline": base,
        "simulate_samples_per_s_speedup": headline / base,
        "simulate_cpu_s_per_sample": fast_cpu,
        "simulate_cpu_s_per_sample_baseline": base_cpu,
    }
