"""``navigate_startup_s``: its keys are there and positive (the speed itself is not asserted: shared
machines)."""

from __future__ import annotations

import math

import pytest

from fluoronav.bench.navigation import navigate_startup


@pytest.mark.slow  # two navigate processes, ~15 s on 2 cores
def test_navigate_startup_reports_its_figure_reference_and_speedup() -> None:
    figures = navigate_startup(quick=True)
    assert set(figures) == {
        "navigate_startup_s",
        "navigate_startup_s_reference",
        "navigate_startup_s_speedup",
    }
    assert all(math.isfinite(v) and v > 0 for v in figures.values())
    assert figures["navigate_startup_s_speedup"] == pytest.approx(
        figures["navigate_startup_s_reference"] / figures["navigate_startup_s"]
    )
