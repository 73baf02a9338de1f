"""Timing helper shared by the benchmarks."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable

from fluoronav.device import synchronize

__all__ = ["time_ms"]


def time_ms(fn: Callable[[], object], *, repeats: int, warmup: int = 1, device: str = "cpu") -> float:
    """Median wall time of ``fn()`` in ms over ``repeats`` calls after ``warmup`` untimed calls
    (each call waits for the work it queued on ``device``)."""
    for _ in range(warmup):
        fn()
    synchronize(device)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        synchronize(device)
        times.append((time.perf_counter() - t) * 1e3)
    return float(statistics.median(times))
