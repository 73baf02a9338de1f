"""Self-contained HTML/Markdown reports: the demo report and the paper's Table I from study outputs."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from fluoronav.htmlpage import Section, cell_text, figure_png, html_page, table_html

__all__ = [
    "PAPER_TABLE_I",
    "Section",
    "figure_png",
    "html_page",
    "outcome_table",
    "table_html",
    "table_i",
    "table_markdown",
]

#: The paper's Table I (mean, std, median) for the CM workflows.
PAPER_TABLE_I: dict[str, dict[str, tuple[float, float, float]]] = {
    "single-view": {
        "tip_mm": (1.65, 1.13, 1.33),
        "relative_mm": (2.07, 1.52, 1.73),
        "base_translation_mm": (1.24, 1.05, 1.03),
        "base_rotation_deg": (3.32, 4.17, 1.68),
        "notch_rotation_deg": (0.23, 0.26, 0.16),
    },
    "multi-view": {
        "tip_mm": (0.59, 0.37, 0.42),
        "relative_mm": (0.63, 0.39, 0.55),
        "base_translation_mm": (0.52, 0.43, 0.40),
        "base_rotation_deg": (1.38, 1.32, 0.88),
        "notch_rotation_deg": (0.22, 0.23, 0.15),
    },
    "multi-cm": {
        "tip_mm": (0.99, 0.59, 0.94),
        "relative_mm": (1.10, 0.72, 0.51),
        "base_translation_mm": (1.00, 0.60, 0.95),
        "base_rotation_deg": (0.14, 0.10, 0.12),
        "notch_rotation_deg": (0.18, 0.21, 0.12),
    },
}
#: Best figures of the paper's running text: the numbers to beat.
PAPER_BEST_TIP_MM = {"single-view": 1.17, "multi-view": 0.59, "multi-cm": 0.99}
TABLE_COLUMNS = ("tip_mm", "relative_mm", "base_translation_mm", "base_rotation_deg", "notch_rotation_deg")


def table_markdown(header: list[str], rows: list[list[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell_text(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def _fmt(stats: dict[str, float] | None) -> str:
    if not stats:
        return "–"
    return f"{stats['mean']:.2f} ± {stats['std']:.2f} ({stats['median']:.2f})"


def table_i(study_dirs: list[Path]) -> tuple[list[str], list[list[Any]]]:
    """Table I rows (ours and the paper's) from study output directories (their summary.json)."""
    header = ["workflow", "source", "trials", *TABLE_COLUMNS]
    rows: list[list[Any]] = []
    for d in study_dirs:
        s = json.loads((Path(d) / "summary.json").read_text(encoding="utf-8"))
        wf = s["workflow"]
        rows.append(
            [
                wf,
                f"fluoronav {s.get('version', '')}",
                f"{s['completed'] - s['failed']}/{s['trials']}",
                *[_fmt(s["metrics"].get(c)) for c in TABLE_COLUMNS],
            ]
        )
        if wf in PAPER_TABLE_I:
            p = PAPER_TABLE_I[wf]
            rows.append(
                [
                    wf,
                    "Gao et al. 2022",
                    "1000",
                    *[f"{p[c][0]:.2f} ± {p[c][1]:.2f} ({p[c][2]:.2f})" for c in TABLE_COLUMNS],
                ]
            )
    return header, rows


def outcome_table(study_dirs: list[Path]) -> tuple[list[str], list[list[Any]]]:
    """Per study: trials, failed, refused (the navigation gave no command), unflagged gross
    failures (status ok, final true tip more than 2 mm from the plan) and the refusal reasons."""
    header = ["study", "trials", "failed", "refused", "unflagged gross failures", "refusal reasons"]
    rows: list[list[Any]] = []
    for d in study_dirs:
        s = json.loads((Path(d) / "summary.json").read_text(encoding="utf-8"))
        reasons = "; ".join(f"{n}× {r}" for r, n in s.get("refusal_reasons", {}).items()) or "–"
        rows.append(
            [
                f"{s['workflow']} ({Path(d).name})",
                s["completed"],
                s["failed"],
                s.get("refused", 0),
                s.get("unflagged_gross_failures", "–"),
                reasons,
            ]
        )
    return header, rows
