"""Self-contained HTML/Markdown reports: the demo report and the paper's Table I from study outputs."""

from __future__ import annotations

import base64
import html
import io
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["PAPER_TABLE_I", "Section", "figure_png", "html_page", "table_html", "table_i", "table_markdown"]

#: The paper's Table I (mean, std, median) for the CM workflows; FACTS.md explains the column reading.
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
#: Best figures of the running text (FACTS.md): the numbers to beat.
PAPER_BEST_TIP_MM = {"single-view": 1.17, "multi-view": 0.59, "multi-cm": 0.99}
TABLE_COLUMNS = ("tip_mm", "relative_mm", "base_translation_mm", "base_rotation_deg", "notch_rotation_deg")


@dataclass
class Section:
    """One report section: a heading, paragraphs, tables (header + rows) and PNG figures."""

    title: str
    paragraphs: list[str] = field(default_factory=list)
    tables: list[tuple[list[str], list[list[Any]]]] = field(default_factory=list)
    figures: list[tuple[str, bytes]] = field(default_factory=list)  # (caption, PNG bytes)
    raw_html: str = ""


def figure_png(fig: Any, *, dpi: int = 100) -> bytes:
    """PNG bytes of a matplotlib figure (closes it)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def _cell(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.3g}"
    return html.escape(str(v))


def table_html(header: list[str], rows: list[list[Any]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_cell(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def table_markdown(header: list[str], rows: list[list[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(_cell(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:2em auto;max-width:1150px;
color:#222;line-height:1.45}h1{font-size:1.6em}
h2{border-bottom:1px solid #ddd;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}figure{display:inline-block;margin:.5em;
vertical-align:top}figure img{max-width:100%;border:1px solid #ddd}figcaption{font-size:.85em;color:#555}
.note{color:#555;font-size:.9em}
"""


def html_page(title: str, sections: list[Section], *, subtitle: str = "") -> str:
    """One self-contained HTML file (figures embedded as base64 PNG)."""
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
        f"<style>{_CSS}</style></head><body><h1>{html.escape(title)}</h1>"
    ]
    if subtitle:
        parts.append(f"<p class='note'>{html.escape(subtitle)}</p>")
    for s in sections:
        parts.append(f"<h2>{html.escape(s.title)}</h2>")
        parts += [f"<p>{html.escape(p)}</p>" for p in s.paragraphs]
        parts += [table_html(h, r) for h, r in s.tables]
        for caption, png in s.figures:
            b64 = base64.b64encode(png).decode()
            parts.append(
                f"<figure><img src='data:image/png;base64,{b64}'><figcaption>{html.escape(caption)}"
                "</figcaption></figure>"
            )
        parts.append(s.raw_html)
    parts.append("</body></html>")
    return "\n".join(parts)


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
