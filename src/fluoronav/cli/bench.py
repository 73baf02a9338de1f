"""``fluoronav bench``: performance figures, each measured next to its baseline in the same run."""

from __future__ import annotations

import json

import typer
from rich.console import Console
from rich.table import Table

from fluoronav import __version__
from fluoronav.bench import BENCH_STAGES, collect
from fluoronav.errors import InputError

__all__ = ["collect", "register"]  # collect: re-exported for callers of the CLI module


def register(app: typer.Typer) -> None:
    @app.command("bench")
    def bench(
        json_out: bool = typer.Option(False, "--json", help="Print one JSON object instead of a table."),
        quick: bool = typer.Option(False, "--quick", help="Fewer repeats (for smoke tests)."),
        only: list[str] = typer.Option(
            None, "--only", help=f"Benchmark only these stages (of {', '.join(BENCH_STAGES)})."
        ),
        device: str = typer.Option(
            "cpu", "--device", help="cpu, cuda or auto: where every figure and its baseline run."
        ),
    ) -> None:
        """Measure speed figures (ms per DRR, samples/s, s per registration) against same-run baselines."""
        unknown = sorted(set(only or ()) - set(BENCH_STAGES))
        if unknown:
            raise InputError("--only", f"unknown stage {unknown[0]!r}; use {', '.join(BENCH_STAGES)}")
        figures = collect(quick=quick, only=only or None, device=device)
        if json_out:
            typer.echo(json.dumps(figures))
            return
        table = Table(title=f"fluoronav {__version__} benchmarks on {figures['machine']['device']}")
        for col in ("figure", "value", "baseline or 0.1.0 reference", "speed-up"):
            table.add_column(col, justify="right" if col != "figure" else "left")
        for key, value in figures.items():
            if key.endswith(("_baseline", "_reference", "_speedup")) or not isinstance(value, int | float):
                continue
            base = figures.get(f"{key}_baseline", figures.get(f"{key}_reference"))
            spd = figures.get(f"{key}_speedup")
            table.add_row(
                key,
                f"{value:.4g}",
                "" if base is None else f"{base:.4g}",
                "" if spd is None else f"{spd:.1f}×",
            )
        Console().print(table)
