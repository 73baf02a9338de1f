"""``fluoronav navigate`` loads only what it runs: no simulation, studies, detector training or
benchmarks, whose modules the command never uses (a process of its own, as a user starts it)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from fluoronav.navigation.case.model import write_navigation_case

#: module prefixes ``fluoronav navigate`` never imports
NOT_NAVIGATE = (
    "fluoronav.simulation",
    "fluoronav.studies",
    "fluoronav.detection.training",
    "fluoronav.bench",
    "dask",
)

#: the command in a fresh interpreter, then the modules it loaded (one line, after a marker)
_RUN_AND_LIST = """
import sys
from fluoronav.cli.main import main
try:
    main(sys.argv[1:])
except SystemExit as exc:
    print("exit status", exc.code)
print("modules:", *sorted(sys.modules))
"""


def test_navigate_loads_no_simulation_studies_training_or_bench(tmp_path: Path, make_no_cm_case) -> None:
    """The small case without a CM: preflight, then the detector finds nothing and the run refuses
    (exit status 3) with its report written, in seconds."""
    case = write_navigation_case(make_no_cm_case(n_views=2), tmp_path / "case")
    argv = ["navigate", str(case), "--out", str(tmp_path / "out"), "--device", "cpu"]
    proc = subprocess.run(
        [sys.executable, "-c", _RUN_AND_LIST, *argv], capture_output=True, encoding="utf-8", timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    assert "exit status 3" in proc.stdout and "refused: stage detect" in proc.stderr
    modules = proc.stdout.split("modules:", 1)[1].split()
    assert "fluoronav.navigation.pipeline" in modules  # the listing is the command's
    loaded = [m for m in modules if m.startswith(NOT_NAVIGATE)]
    assert not loaded, f"fluoronav navigate imported {loaded}"


#: libraries that no stage before the registrations uses; ``navigate`` imports them at first use
NOT_BEFORE_REGISTRATION = ("roma", "cma", "matplotlib", "scipy.optimize", "scipy.interpolate", "scipy.stats")


def test_navigate_reaches_its_case_without_the_registrations_libraries(tmp_path: Path) -> None:
    """Up to reading the case (here missing: exit status 2), ``navigate`` has not imported the
    libraries of later stages (``navigate_startup_s`` in ``fluoronav bench`` times this path)."""
    argv = ["navigate", str(tmp_path / "no_case" / "navigation.json"), "--out", str(tmp_path / "out")]
    proc = subprocess.run(
        [sys.executable, "-c", _RUN_AND_LIST, *argv], capture_output=True, encoding="utf-8", timeout=300
    )
    assert "exit status 2" in proc.stdout and "navigation case not found" in proc.stderr, proc.stderr
    modules = proc.stdout.split("modules:", 1)[1].split()
    assert "fluoronav.navigation.pipeline" in modules and "torch" in modules  # the listing is the command's
    later = NOT_BEFORE_REGISTRATION
    loaded = [m for m in modules if m in later or m.startswith(tuple(f"{name}." for name in later))]
    assert not loaded, f"fluoronav navigate imported {loaded} before its first stage"


def test_the_cli_names_the_benchmark_stages_as_the_benchmarks_do() -> None:
    """``fluoronav bench`` names its stages without importing the benchmarks."""
    from fluoronav.bench import BENCH_STAGES
    from fluoronav.cli.bench import BENCH_STAGES as CLI_BENCH_STAGES

    assert CLI_BENCH_STAGES == BENCH_STAGES
