"""``fluoronav demo``: the whole navigation pipeline on the built-in phantom, no files needed.

See :mod:`fluoronav.navigation.demo` for the stages. Writes ``DIR/results.json`` and a self-contained
``DIR/report.html``; prints a table of errors and timings per stage.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import typer

from fluoronav.cli.common import DEVICE_OPTION, SEED_OPTION

log = logging.getLogger(__name__)

STAGE_LABELS = {
    "anatomy": "building the hip phantom and the X-ray simulator",
    "scene": "placing robot, CM, pelvis, femur and C-arm",
    "simulate": "simulating three C-arm X-rays (physics)",
    "detect": "detecting the CM (mask, landmarks, centreline)",
    "pelvis": "registering the pelvis in each view",
    "femur": "registering the femur",
    "cm": "initialising and registering the CM (multi-view)",
    "plan": "planning the target pose",
    "robot": "computing the robot command (eqs. 7-8, IK)",
    "move": "moving the robot",
    "verify": "verification images and registration",
    "correct": "corrective move from the verification",
}


def run(out: Path, *, seed: int, device: str, image_size: int, oracle_landmarks: bool) -> int:
    """Run the demo, print its table, write results.json and report.html; returns the exit code."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
    from rich.table import Table

    from fluoronav.device import resolve_device
    from fluoronav.navigation.demo import STAGES, DemoConfig, run_demo, write_case, write_results
    from fluoronav.navigation.demo_report import ERROR_ROWS, write_report

    console = Console(stderr=True)
    cfg = DemoConfig(
        seed=seed,
        image_size=image_size,
        device=str(resolve_device(device)),
        oracle_landmarks=oracle_landmarks,
    )
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total} stages"),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    ) as progress:
        task = progress.add_task("demo", total=len(STAGES))

        started: dict[str, float] = {}

        def on_stage(name: str, event: str) -> None:
            if event == "start":
                started[name] = time.perf_counter()
                progress.update(task, description=STAGE_LABELS.get(name, name))
            else:
                progress.advance(task)
                if not console.is_terminal:  # a log file gets one line per stage instead of a bar
                    console.print(f"{name}: done in {time.perf_counter() - started[name]:.1f} s")

        result = run_demo(cfg, on_stage=on_stage)
        progress.update(task, description="writing the report")
        write_results(result, out)
        case = write_case(result, out)
        report = write_report(result, out)

    table = Table(title=f"fluoronav demo (seed {seed}): errors against the simulated truth")
    for col in ("quantity", "value", "unit", "paper"):
        table.add_column(col)
    for label, key, unit, paper in ERROR_ROWS:
        if key in result.errors:
            table.add_row(label, f"{result.errors[key]:.3g}", unit, paper)
    console.print(table)
    times = Table(title="seconds per stage")
    times.add_column("stage")
    times.add_column("s", justify="right")
    for s in STAGES:
        if s in result.timings_s:
            times.add_row(s, f"{result.timings_s[s]:.1f}")
    times.add_row("total", f"{sum(result.timings_s.values()):.1f}")
    console.print(times)
    if result.status != "ok":
        console.print(f"[red]demo failed: {result.reason}[/red]")
        typer.echo(f"wrote {out / 'results.json'} and {report} (partial)")
        return 1
    typer.echo(f"wrote {out / 'results.json'} and {report}")
    if case is not None:
        typer.echo(f"the three views as a case file: fluoronav register {case} --out DIR")
    return 0


def register(app: typer.Typer) -> None:
    @app.command("demo")
    def demo(
        out: Path = typer.Option(Path("demo_out"), "--out", help="Output directory."),
        seed: int = SEED_OPTION,
        device: str = DEVICE_OPTION,
        image_size: int = typer.Option(
            768, "--image-size", min=256, max=1536, help="Simulated image size (the 1536² detector binned)."
        ),
        oracle_landmarks: bool = typer.Option(
            False, "--oracle-landmarks", help="True landmarks + U(-3, 3) px instead of the detector."
        ),
    ) -> None:
        """Simulated navigation on the built-in phantom: X-rays → detection → registration → robot
        command → move → verification; writes report.html and results.json to --out."""
        code = run(out, seed=seed, device=device, image_size=image_size, oracle_landmarks=oracle_landmarks)
        raise typer.Exit(code)
