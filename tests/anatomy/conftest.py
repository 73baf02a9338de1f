"""Anatomy tests: a small synthetic DeepFluoro file, written once for the directory."""

from __future__ import annotations

import pytest

from fluoronav.simulation.deepfluoro_synthetic import SyntheticDeepFluoro, write_synthetic_deepfluoro


@pytest.fixture(scope="session")
def deepfluoro_file(tmp_path_factory: pytest.TempPathFactory) -> SyntheticDeepFluoro:
    """Three 192² projections of the phantom (2 mm CT) in the DeepFluoro layout; one rot-180-for-up."""
    return write_synthetic_deepfluoro(tmp_path_factory.mktemp("deepfluoro") / "synthetic.h5")
