"""The input-fault table: one markdown row per ``fluoronav study navigation --fault NAME`` directory.

Reads each directory's ``summary.json`` (its ``fault``) and ``trials.csv`` (each row's
``fault_outcome`` and ``check``) and prints: fault | cases | landed | refused naming it | refused
otherwise | unsafe | what the reasons said (the most common refusal check, with its count). Failed
trials are counted in the cases column.

Run::

    python tools/fault_table.py runs/fault-*/
"""

from __future__ import annotations

import argparse
import csv
import json
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

HEADER = (
    "| fault | cases | landed | refused naming it | refused otherwise | unsafe | "
    "what the reasons said (most common check) |"
)


def read_study(path: Path) -> tuple[str, list[dict[str, Any]]]:
    """(the fault, the rows) of one study directory."""
    summary = json.loads((path / "summary.json").read_text(encoding="utf-8"))
    with open(path / "trials.csv", newline="", encoding="utf-8") as fh:
        rows = [r for r in csv.DictReader(fh) if r.get("trial")]
    return str(summary.get("fault") or "none"), rows


def table_row(fault: str, rows: Sequence[dict[str, Any]]) -> str:
    """The markdown row of one fault's trials."""
    outcomes = Counter(str(r.get("fault_outcome") or "failed") for r in rows)
    checks = Counter(
        str(r["check"]) for r in rows if r.get("check") and str(r.get("status")) in ("refused", "input_error")
    )
    cases = str(len(rows)) + (f" ({outcomes['failed']} failed)" if outcomes["failed"] else "")
    said = "; ".join(f"{c} ({n})" for c, n in checks.most_common(1)) or "–"
    cells = [
        fault,
        cases,
        outcomes["landed"],
        outcomes["refused_named"],
        outcomes["refused_other"],
        outcomes["unsafe"],
        said,
    ]
    return "| " + " | ".join(str(c) for c in cells) + " |"


def fault_table(dirs: Sequence[Path]) -> str:
    """The whole table (header, separator, one row per directory, in the given order)."""
    lines = [HEADER, "|" + "---|" * 7]
    for d in dirs:
        fault, rows = read_study(Path(d))
        lines.append(table_row(fault, rows))
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dirs", nargs="+", type=Path, help="study directories (summary.json + trials.csv)")
    args = ap.parse_args(argv)
    for d in args.dirs:
        for name in ("summary.json", "trials.csv"):
            if not (d / name).is_file():
                raise SystemExit(f"error: {d}: no {name} (not a finished study directory)")
    print(fault_table(args.dirs))


if __name__ == "__main__":
    main()
