"""``fluoronav report DIR...``: the paper's Table I (Markdown and HTML) from study outputs."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from fluoronav.errors import InputError

if TYPE_CHECKING:
    from fluoronav.studies.report import Section


def register(app: typer.Typer) -> None:
    @app.command("report")
    def report(
        dirs: list[Path] = typer.Argument(..., help="Study output directories (each with summary.json)."),
        out: Path = typer.Option(
            Path("report"), "--out", help="Output directory for table_i.md and report.html."
        ),
    ) -> None:
        """Combine studies into the paper's Table I beside the paper's numbers, with their figures."""
        from fluoronav.studies.deepfluoro_report import WORKFLOW  # lazy: fast --help
        from fluoronav.studies.report import html_page  # lazy: fast --help

        _check_study_dirs(dirs)
        real = [
            d
            for d in dirs
            if json.loads((d / "summary.json").read_text(encoding="utf-8")).get("workflow") == WORKFLOW
        ]
        dirs = [d for d in dirs if d not in real]
        sections = _write_tables(dirs, real, out)
        sections += [_study_section(d) for d in [*dirs, *real]]
        (out / "report.html").write_text(
            html_page("fluoronav simulation studies", sections), encoding="utf-8"
        )
        typer.echo(f"wrote {out / 'table_i.md'} and {out / 'report.html'}")


def _check_study_dirs(dirs: list[Path]) -> None:
    """Each directory holds a ``summary.json`` that parses (else an :class:`InputError` naming it)."""
    for d in dirs:
        s = d / "summary.json"
        if not s.is_file():
            raise InputError(d, "not a study directory (no summary.json)")
        try:
            json.loads(s.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise InputError(s, f"summary.json does not parse ({exc.msg})") from None


def _write_tables(dirs: list[Path], real: list[Path], out: Path) -> list[Section]:
    """Table I and the outcomes of the simulation studies ``dirs``, and the DeepFluoro table of the
    ``real`` ones, into ``out/table_i.md`` → the HTML page's sections of them."""
    from fluoronav.studies.deepfluoro_report import deepfluoro_table  # lazy: fast --help
    from fluoronav.studies.report import (  # lazy: fast --help
        Section,
        outcome_table,
        table_i,
        table_markdown,
    )

    header, rows = table_i(dirs)
    out.mkdir(parents=True, exist_ok=True)
    note = (
        "Mean ± std (median). Columns: tip, relative (entry − tip), CM base translation and "
        "rotation, mean notch rotation, as the paper's Table I reports them."
    )
    o_header, o_rows = outcome_table(dirs)
    real_md, real_sections = "", []
    if real:
        r_header, r_rows = deepfluoro_table(real)
        r_note = "Pelvis registration on the DeepFluoro cadaver images, beside the published figures."
        real_md = f"\n## Real data: DeepFluoro\n\n{r_note}\n\n{table_markdown(r_header, r_rows)}\n"
        real_sections = [Section("Real data: DeepFluoro", paragraphs=[r_note], tables=[(r_header, r_rows)])]
    (out / "table_i.md").write_text(
        f"# Table I\n\n{note}\n\n{table_markdown(header, rows)}\n\n## Outcomes\n\n"
        f"{table_markdown(o_header, o_rows)}\n{real_md}",
        encoding="utf-8",
    )
    return [
        Section("Table I", paragraphs=[note], tables=[(header, rows)]),
        Section(
            "Outcomes: failures and refusals",
            paragraphs=[
                "A refused trial is one where the navigation found a registration failing its "
                "checks and gave no robot command; an unflagged gross failure is a trial that said "
                "ok and left the true tip more than 2 mm from the plan."
            ],
            tables=[(o_header, o_rows)],
        ),
        *real_sections,
    ]


def _study_section(d: Path) -> Section:
    """One study's section of the HTML page: its counts, speed, device and version, and its figures."""
    from fluoronav.studies.report import Section  # lazy: fast --help

    summ = json.loads((d / "summary.json").read_text(encoding="utf-8"))
    figs = [
        (f"{summ['workflow']}: {p.stem.replace('_', ' ')}", p.read_bytes())
        for p in sorted((d / "figures").glob("*.png"))
    ]
    info = (
        f"{summ['completed']} of {summ['trials']} trials completed, {summ['failed']} failed, "
        f"{summ.get('refused', 0)} refused; "
        f"median {summ['seconds_per_trial'].get('median') or float('nan'):.1f} s per trial; "
        f"device {summ.get('device')}; fluoronav {summ.get('version')}."
    )
    return Section(f"{summ['workflow']} ({d})", paragraphs=[info], figures=figs)
