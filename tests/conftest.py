"""Shared pytest configuration."""

from __future__ import annotations

import os

# Two cores on CI: keep torch from oversubscribing when numba also runs threads.
os.environ.setdefault("OMP_NUM_THREADS", "2")

from hypothesis import settings

# CI is deterministic (the same examples every run); HYPOTHESIS_PROFILE=deep searches widely.
settings.register_profile("ci", derandomize=True, deadline=None)
settings.register_profile("deep", max_examples=1500, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
