"""Self-contained HTML pages: sections of paragraphs, tables and embedded PNG figures."""

from __future__ import annotations

import base64
import html
import io
from dataclasses import dataclass, field
from typing import Any

__all__ = ["Section", "cell_text", "figure_png", "html_page", "table_html"]


@dataclass
class Section:
    """One report section: a heading, paragraphs, tables (header + rows) and PNG figures."""

    title: str
    paragraphs: list[str] = field(default_factory=list)
    tables: list[tuple[list[str], list[list[Any]]]] = field(default_factory=list)
    figures: list[tuple[str, bytes]] = field(default_factory=list)  # (caption, PNG bytes)
    raw_html: str = ""
    #: shown right under the heading (e.g. a status banner)
    banner_html: str = ""


def figure_png(fig: Any, *, dpi: int = 100) -> bytes:
    """PNG bytes of a matplotlib figure (closes it)."""
    import matplotlib.pyplot as plt  # heavy: matplotlib, only where a page has figures

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def cell_text(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.3g}"
    return html.escape(str(v))


def table_html(header: list[str], rows: list[list[Any]]) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{cell_text(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


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
        parts.append(s.banner_html)
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
