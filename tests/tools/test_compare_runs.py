"""``tools/compare_runs.py``: demo and study outputs compared, seconds, paths and versions aside."""

from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path
from types import ModuleType

import pytest

TOOL = Path(__file__).resolve().parents[2] / "tools" / "compare_runs.py"


@pytest.fixture(scope="module")
def tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("compare_runs", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _tree(root: Path, *, tip_mm: float, seconds: float, version: str, settings: dict) -> Path:
    demo = root / "demo"
    demo.mkdir(parents=True)
    results = {"version": version, "status": "ok", "errors": {"tip_mm": tip_mm}, "timings_s": {"cm": seconds}}
    (demo / "results.json").write_text(json.dumps(results))
    navigation = {"case": str(demo / "case" / "navigation.json"), "settings": settings, "tip": [tip_mm, 1.0]}
    (demo / "navigation.json").write_text(json.dumps(navigation))
    study = root / "study"
    study.mkdir()
    with open(study / "trials.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, ["trial", "tip_mm", "cm_s"])
        writer.writeheader()
        writer.writerow({"trial": 0, "tip_mm": tip_mm, "cm_s": seconds})
    return root


def test_seconds_paths_versions_and_settings_are_left_out(tool: ModuleType, tmp_path: Path) -> None:
    a = _tree(tmp_path / "a", tip_mm=0.25, seconds=1.0, version="0.9.0", settings={})
    b = _tree(tmp_path / "b", tip_mm=0.25, seconds=9.0, version="0.10.0", settings={"seed": 0})
    lines = tool.compare_trees(a, b)
    assert lines == [
        "demo/results.json (2 values): IDENTICAL",
        "demo/navigation.json (3 values): IDENTICAL",
        "study/trials.csv (2 values): IDENTICAL",
    ]
    assert tool.main([str(a), str(b)]) == 0


def test_a_result_that_moved_by_one_ulp_differs(tool: ModuleType, tmp_path: Path) -> None:
    a = _tree(tmp_path / "a", tip_mm=0.25, seconds=1.0, version="0.9.0", settings={})
    b = _tree(tmp_path / "b", tip_mm=0.25000000000000006, seconds=1.0, version="0.9.0", settings={})
    lines = tool.compare_trees(a, b)
    assert "demo/results.json (2 values): DIFFER" in lines
    assert "    .errors.tip_mm: 0.25 != 0.25000000000000006" in lines
    assert "    .tip[0]: 0.25 != 0.25000000000000006" in lines
    assert "study/trials.csv (2 values): DIFFER" in lines
    assert tool.main([str(a), str(b)]) == 1


def test_a_missing_run_fails(tool: ModuleType, tmp_path: Path) -> None:
    a = _tree(tmp_path / "a", tip_mm=0.25, seconds=1.0, version="0.9.0", settings={})
    (tmp_path / "b").mkdir()
    assert tool.main([str(a), str(tmp_path / "b")]) == 1
