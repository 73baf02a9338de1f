"""``tools/fault_table.py``: the input-fault table from study directories."""

from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path
from types import ModuleType

import pytest

TOOL = Path(__file__).resolve().parents[2] / "tools" / "fault_table.py"


@pytest.fixture(scope="module")
def tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("fault_table", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _study(path: Path, fault: str, rows: list[dict[str, str]]) -> Path:
    path.mkdir()
    (path / "summary.json").write_text(json.dumps({"workflow": "navigation", "fault": fault}))
    with open(path / "trials.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=["trial", "status", "check", "fault_outcome"])
        w.writeheader()
        w.writerows(rows)
    return path


def test_one_row_per_study_with_its_outcomes_and_commonest_check(tool: ModuleType, tmp_path: Path) -> None:
    mirror = _study(
        tmp_path / "a",
        "mirror_one",
        [
            {"trial": "0", "status": "ok", "check": "", "fault_outcome": "landed"},
            {"trial": "1", "status": "refused", "check": "mirrored", "fault_outcome": "refused_named"},
            {"trial": "2", "status": "refused", "check": "mirrored", "fault_outcome": "refused_named"},
            {"trial": "3", "status": "refused", "check": "edge_ncc", "fault_outcome": "refused_other"},
            {"trial": "4", "status": "failed", "check": "", "fault_outcome": "failed"},
        ],
    )
    plan = _study(
        tmp_path / "b",
        "plan_inward_300",
        [{"trial": "0", "status": "ok", "check": "", "fault_outcome": "unsafe"}],
    )
    lines = tool.fault_table([mirror, plan]).splitlines()
    assert lines[0].startswith("| fault | cases | landed | refused naming it | refused otherwise | unsafe |")
    assert lines[2] == "| mirror_one | 5 (1 failed) | 1 | 2 | 1 | 0 | mirrored (2) |"
    assert lines[3] == "| plan_inward_300 | 1 | 0 | 0 | 0 | 1 | – |"
