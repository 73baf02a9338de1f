"""``tools/world_table.py``: the simulated worlds' table from navigation study directories."""

from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path
from types import ModuleType

import pytest

TOOL = Path(__file__).resolve().parents[2] / "tools" / "world_table.py"
FIELDS = [
    "trial",
    "status",
    "check",
    "reposition_tip_mm",
    "reposition_axis_deg",
    "reposition_open_loop_mm",
    "reposition_open_loop_axis_deg",
    "femur_tip_mm",
    "femur_axis_deg",
    "tip_mm",
    "verify_relative_mm",
]


@pytest.fixture(scope="module")
def tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("world_table", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_one_row_per_world_with_means_over_the_trials_that_reached_each_stage(
    tool: ModuleType, tmp_path: Path
) -> None:
    d = tmp_path / "motion"
    d.mkdir()
    summary = {"world": {"name": "realistic_motion_only"}, "unflagged_gross_failures": 0}
    summary["unflagged_first_move_failures"] = 1
    (d / "summary.json").write_text(json.dumps(summary))
    rows = [
        # ok: every stage
        ["0", "ok", "", "0.2", "1.0", "1.0", "1.0", "0.1", "1.0", "2.0", "0.2"],
        ["1", "ok", "", "0.4", "2.0", "3.0", "2.0", "0.3", "2.0", "3.0", "0.4"],
        # refused after the first move: counts in the first move's means, not the final ones
        ["2", "refused", "kinematics_disagree", "", "", "5.0", "3.0", "0.5", "3.0", "1.0", ""],
        # refused before any command
        ["3", "refused", "edge_ncc", "", "", "", "", "", "", "", ""],
    ]
    with open(d / "trials.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(FIELDS)
        w.writerows(rows)
    row = tool.table_row(*tool.read_study(d))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[:3] == ["realistic_motion_only", "4", "2 / 2"]
    assert cells[3] == "0.30 (0.30), p95 0.40; 1.50"
    assert cells[4] == "3.00; 2.00" and cells[5] == "0.30; 2.00" and cells[6] == "2.00"
    assert cells[7] == "0.30" and cells[8] == "0 / 1"
    assert cells[9] == "kinematics_disagree (1), edge_ncc (1)"
