"""Benchmarks of the pipeline stages (``fluoronav bench``), an application layer beside ``studies``.

One module per stage, ``fluoronav.bench.<stage>``, provides
``run(quick: bool, device: str) -> dict[str, float]``; :data:`BENCH_STAGES` lists them in the order
:func:`collect` runs them. Stage modules are imported on demand, so that ``--only`` loads only the
stages it names.
"""

from __future__ import annotations

import importlib
import logging
import platform
from typing import Any

import torch

from fluoronav import __version__
from fluoronav.device import resolve_device

__all__ = ["BENCH_STAGES", "collect"]

log = logging.getLogger(__name__)

#: stages with a ``fluoronav.bench.<stage>`` module, in the order they run
BENCH_STAGES = ("rendering", "simulation", "detection", "registration", "navigation")


def collect(*, quick: bool = False, only: list[str] | None = None, device: str = "cpu") -> dict[str, Any]:
    """Run every stage's benchmarks on ``device`` (``cpu``, ``cuda`` or ``auto``) and merge their
    figures into one dict; each figure's baseline runs on the same device."""
    dev = str(resolve_device(device))
    figures: dict[str, Any] = {}
    for stage in BENCH_STAGES:
        if only and stage not in only:
            continue
        module = importlib.import_module(f"fluoronav.bench.{stage}")  # heavy: each stage's stack
        log.info("benchmarking %s on %s", stage, dev)
        figures.update(module.run(quick=quick, device=dev))
    figures["machine"] = {
        "cpu_threads": torch.get_num_threads(),
        "platform": platform.platform(),
        "torch": torch.__version__,
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "device": dev,
    }
    figures["version"] = __version__
    return figures
