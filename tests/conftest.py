"""Shared pytest configuration."""

from __future__ import annotations

import os

# Two cores on CI: keep torch from oversubscribing when numba also runs threads.
os.environ.setdefault("OMP_NUM_THREADS", "2")
