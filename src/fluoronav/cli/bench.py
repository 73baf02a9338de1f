"""``fluoronav bench``: performance figures, each measured next to its baseline in the same run."""

from __future__ import annotations

import importlib
import json
import logging
import platform
from typing import Any

import torch
import typer

from fluoronav import __version__
from fluoronav.device import resolve_device
from fluoronav.errors import InputError

log = logging.getLogger(__name__)

#: stages that provide ``fluoronav.<stage>.bench.run(quick: bool, device: str) -> dict[str, float]``
BENCH_STAGES = ("rendering", "simulation", "detection", "registration")


def collect(*, quick: bool = False, only: list[str] | None = None, device: str = "cpu") -> dict[str, Any]:
    """Run every stage's benchmarks on ``device`` (``cpu``, ``cuda`` or ``auto``) and merge their
    figures into one dict; each figure's baseline runs on the same device."""
    dev = str(resolve_device(device))
    figures: dict[str, Any] = {}
    for stage in BENCH_STAGES:
        if only and stage not in only:
            continue
        try:
            module = importlib.import_module(f"fluoronav.{stage}.bench")
        except ModuleNotFoundError as exc:
            if exc.name == f"fluoronav.{stage}.bench":
                continue
            raise
        log.info("benchmarking %s on %s", stage, dev)
        figures.update(module.run(quick=quick, device=dev))
    figures["machine"] = {
        "cpu_threads": torch.get_num_threads(),
        "platform": platform.platform(),
        "torch": torch.__version__,
        "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
        "device": dev,
    }
    figures["version"] = __version__
    return figures


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
        from rich.console import Console
        from rich.table import Table

        table = Table(title=f"fluoronav {__version__} benchmarks on {figures['machine']['device']}")
        for col in ("figure", "value", "baseline", "speed-up"):
            table.add_column(col, justify="right" if col != "figure" else "left")
        for key, value in figures.items():
            if key.endswith(("_baseline", "_speedup")) or not isinstance(value, int | float):
                continue
            base = figures.get(f"{key}_baseline")
            spd = figures.get(f"{key}_speedup")
            table.add_row(
                key,
                f"{value:.4g}",
                "" if base is None else f"{base:.4g}",
                "" if spd is None else f"{spd:.1f}×",
            )
        Console().print(table)
