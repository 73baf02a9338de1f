"""Two trees of demo and study outputs compared, seconds, paths and versions aside.

Each sub-directory of BEFORE is matched by name in AFTER; its ``results.json`` and
``navigation.json`` (demo) and ``trials.csv`` (study) are compared value by value after dropping
keys and columns that hold seconds, paths or the version; ``navigation.json``'s top-level
``settings`` (``config`` before 0.10.0) records the settings in force, not a result, and is left
out. Prints one line per file, IDENTICAL or DIFFER with the first differences; exit status 1 when
anything differs or is missing.

Run::

    python tools/compare_runs.py runs-0.9.0/ runs-0.10.0/
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import sys
from pathlib import Path
from typing import Any

#: keys and columns that hold seconds, paths, the version or the settings, not results
SKIP = re.compile(r"(seconds|_s$|^s$|time|timing|path|^out$|_dir$|duration|elapsed|version)")
#: top-level keys of ``navigation.json`` that record the settings in force
SETTINGS_KEYS = ("settings", "config")
#: the JSON files of a demo directory that are compared
JSON_FILES = ("results.json", "navigation.json")


def strip(value: Any) -> Any:
    """``value`` without the keys :data:`SKIP` matches, at any depth."""
    if isinstance(value, dict):
        return {k: strip(v) for k, v in value.items() if not SKIP.search(k)}
    if isinstance(value, list):
        return [strip(v) for v in value]
    return value


def count_values(value: Any) -> int:
    """The number of leaf values of a JSON value."""
    if isinstance(value, dict):
        return sum(count_values(v) for v in value.values())
    if isinstance(value, list):
        return sum(count_values(v) for v in value)
    return 1


def differences(a: Any, b: Any, where: str = "") -> list[str]:
    """Where two JSON values differ (``.key[index]`` paths), exact comparison of leaves."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                out.append(f"{where}.{k}: only {'after' if k not in a else 'before'}")
            else:
                out += differences(a[k], b[k], f"{where}.{k}")
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [
            d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in differences(x, y, f"{where}[{i}]")
        ]
    return [] if a == b else [f"{where}: {str(a)[:60]} != {str(b)[:60]}"]


def compare_json(a: Path, b: Path) -> tuple[int, list[str]]:
    """(values compared, differences) of two JSON files."""
    # a path inside the tree is compared relative to the tree
    left, right = (
        json.loads(p.read_text(encoding="utf-8").replace(str(p.parent.parent.resolve()), "<tree>"))
        for p in (a, b)
    )
    if a.name == "navigation.json":
        left, right = ({k: v for k, v in d.items() if k not in SETTINGS_KEYS} for d in (left, right))
    left = strip(left)
    return count_values(left), differences(left, strip(right))


def compare_csv(a: Path, b: Path) -> tuple[int, list[str]]:
    """(values compared, differences) of two ``trials.csv``, column by column as text."""
    with open(a, newline="", encoding="utf-8") as fa, open(b, newline="", encoding="utf-8") as fb:
        left, right = list(csv.DictReader(fa)), list(csv.DictReader(fb))
    out = [] if len(left) == len(right) else [f"rows: {len(left)} != {len(right)}"]
    if left and right and set(left[0]) != set(right[0]):
        out.append(f"columns only on one side: {sorted(set(left[0]) ^ set(right[0]))}")
    cols = [c for c in (left[0] if left else {}) if not SKIP.search(c)]
    for i, (x, y) in enumerate(zip(left, right, strict=False)):
        out += [f"row {i} {c}: {x.get(c)} != {y.get(c)}" for c in cols if x.get(c) != y.get(c)]
    return len(left) * len(cols), out


def compare_trees(before: Path, after: Path) -> list[str]:
    """One line per compared file, then its first differences (lines that start with a space)."""
    lines = []
    for run in sorted(p for p in before.iterdir() if p.is_dir()):
        for name in (*JSON_FILES, "trials.csv"):
            if not (run / name).is_file():
                continue
            other = after / run.name / name
            if not other.is_file():
                lines += [f"{run.name}/{name}: MISSING in {after}", " missing"]
                continue
            compare = compare_csv if name.endswith(".csv") else compare_json
            n, diffs = compare(run / name, other)
            lines.append(f"{run.name}/{name} ({n} values): {'DIFFER' if diffs else 'IDENTICAL'}")
            lines += [f"    {d}" for d in diffs[:10]]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", type=Path, help="the reference tree (one directory per demo or study)")
    ap.add_argument("after", type=Path, help="the tree to compare with it")
    args = ap.parse_args(argv)
    lines = compare_trees(args.before, args.after)
    print("\n".join(lines))
    return 1 if any(line.startswith(" ") for line in lines) or not lines else 0


if __name__ == "__main__":
    sys.exit(main())
