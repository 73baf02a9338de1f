"""``fluoronav bench``: performance figures, each measured next to its baseline in the same run."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING, Any

import typer
from rich.console import Console
from rich.table import Table

from fluoronav import __version__
from fluoronav.errors import InputError

if TYPE_CHECKING:
    from fluoronav.bench import collect

__all__ = ["collect", "register"]  # collect: re-exported for callers of the CLI module

#: :data:`fluoronav.bench.BENCH_STAGES`, named here so that the CLI starts without importing the
#: benchmarks (torch); tests/cli/test_startup.py holds the two equal
BENCH_STAGES = ("rendering", "simulation", "detection", "registration", "navigation")


def __getattr__(name: str) -> Any:
    """``collect`` of :mod:`fluoronav.bench`, imported on its first use."""
    if name == "collect":
        from fluoronav.bench import collect  # lazy: torch and the benchmarks

        return collect
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


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
        from fluoronav.bench import collect  # lazy: torch and the benchmarks

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
