"""The world table: one markdown row per ``fluoronav study navigation --world W`` directory.

Reads each directory's ``summary.json`` (its ``world``'s name and the unflagged counts) and
``trials.csv`` and prints: world | trials | ok / refused | after the correction: true tip to plan,
mean (median), p95, and CM axis | first move: tip to plan and axis | first registration: CM tip and
axis in the femur's frame, CM tip in the AP C-arm frame | verification: CM tip relative to the femur
| unflagged gross / first-move failures | the refusals' checks. Means are over the trials that
reached each stage (the first move: every trial whose first command was carried out).

Run::

    python tools/world_table.py runs/world-*/
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import statistics
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

HEADER = (
    "| world | trials | ok / refused | after the correction: tip mm (median), p95; axis ° | "
    "first move: tip mm; axis ° | first CM in the femur frame: tip mm; axis ° | first CM tip, "
    "C-arm frame mm | verification CM tip rel. femur mm | unflagged gross / first-move | refusals |"
)


def read_study(path: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """(the summary, the rows) of one study directory."""
    summary = json.loads((path / "summary.json").read_text(encoding="utf-8"))
    with open(path / "trials.csv", newline="", encoding="utf-8") as fh:
        rows = [r for r in csv.DictReader(fh) if r.get("trial")]
    return summary, rows


def _values(rows: Sequence[dict[str, Any]], key: str) -> list[float]:
    out = []
    for r in rows:
        try:
            v = float(r.get(key) or "nan")
        except ValueError:
            continue
        if math.isfinite(v):
            out.append(v)
    return out


def _p95(values: Sequence[float]) -> float:
    v = sorted(values)
    return v[int(0.95 * (len(v) - 1) + 0.5)]


def _mean(values: Sequence[float], *, median: bool = False, p95: bool = False) -> str:
    if not values:
        return "–"
    text = f"{statistics.mean(values):.2f}"
    if median:
        text += f" ({statistics.median(values):.2f})"
    if p95:
        text += f", p95 {_p95(values):.2f}"
    return text


def table_row(summary: dict[str, Any], rows: Sequence[dict[str, Any]]) -> str:
    """The markdown row of one world's trials."""
    world = summary.get("world") or {}
    name = str(world.get("name", "ideal")) if isinstance(world, dict) else str(world)
    ok = [r for r in rows if r.get("status") == "ok"]
    refused = [r for r in rows if r.get("status") == "refused"]
    moved = [r for r in rows if _values([r], "reposition_open_loop_mm")]
    checks = Counter(str(r.get("check") or "other") for r in refused)
    said = ", ".join(f"{c} ({n})" for c, n in checks.most_common()) or "–"
    cells = [
        name,
        str(len(rows)),
        f"{len(ok)} / {len(refused)}",
        f"{_mean(_values(ok, 'reposition_tip_mm'), median=True, p95=True)}; "
        f"{_mean(_values(ok, 'reposition_axis_deg'))}",
        f"{_mean(_values(moved, 'reposition_open_loop_mm'))}; "
        f"{_mean(_values(moved, 'reposition_open_loop_axis_deg'))}",
        f"{_mean(_values(moved, 'femur_tip_mm'))}; {_mean(_values(moved, 'femur_axis_deg'))}",
        _mean(_values(moved, "tip_mm")),
        _mean(_values(rows, "verify_relative_mm")),
        f"{summary.get('unflagged_gross_failures', '–')} / "
        f"{summary.get('unflagged_first_move_failures', '–')}",
        said,
    ]
    return "| " + " | ".join(cells) + " |"


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dirs", nargs="+", type=Path, help="navigation study directories")
    args = parser.parse_args(argv)
    print(HEADER)
    print("|" + "---|" * HEADER.count(" | ") + "---|")
    for d in args.dirs:
        print(table_row(*read_study(d)))


if __name__ == "__main__":
    main()
