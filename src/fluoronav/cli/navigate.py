"""``fluoronav navigate CASE --out DIR``: the navigation loop on a user's own files.

Reads a navigation case (docs/data-formats.md), runs :func:`fluoronav.navigation.pipeline.navigate`
and writes ``DIR/navigation.json``, ``DIR/slicer/`` and ``DIR/report.html``. Exit status 0 when the
navigation gives a robot command, 3 when it refused (no command; the reason is printed and in
``navigation.json``), 2 for bad input.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from pathlib import Path

import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from fluoronav.cli.common import DEVICE_OPTION, SEED_OPTION
from fluoronav.cli.config import SETTINGS_OPTION, navigation_config

#: exit status of a navigation that refused to give a robot command
EXIT_REFUSED = 3

IGTL_OPTION = typer.Option(
    None,
    "--igtl",
    metavar="HOST:PORT",
    help=(
        "Stream the navigation live to 3D Slicer: the OpenIGTLink server of Slicer's OpenIGTLinkIF "
        "module (e.g. 127.0.0.1:18944). Sends the views as images, the CMToCT, FemurToCT and "
        "PlanToCT transforms and a Status text; without a server the navigation runs as without "
        "the option (one warning)."
    ),
)

STAGE_LABELS = {
    "detect": "detecting the CM in each view",
    "pelvis": "registering the pelvis in each view",
    "femur": "registering the femur",
    "cm": "initialising and registering the CM (multi-view)",
    "plan": "planning the target pose",
    "robot": "computing the robot command (eqs. 7-8, IK)",
    "verify_joints": "verification: the joint readings",
    "verify_detect": "verification: detecting the CM",
    "verify_pelvis": "verification: registering the pelvis",
    "verify_femur": "verification: registering the femur",
    "verify_cm": "verification: registering the CM",
    "correct": "computing the corrective command",
    "anatomy": "building the hip phantom and the X-ray simulator",
    "scene": "placing robot, CM, pelvis, femur and C-arm",
    "simulate": "simulating three C-arm X-rays (physics)",
    "move": "moving the robot",
    "verify_simulate": "simulating the verification X-rays",
    "correct_move": "corrective move",
}


@contextmanager
def stage_progress(total: int, description: str) -> Iterator[Callable[[str, str], None]]:
    """A progress display on stderr; yields the ``on_stage`` callback the pipelines take. Without a
    terminal (a log file), one line per finished stage."""
    console = Console(stderr=True)
    started: dict[str, float] = {}
    with Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total} stages"),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    ) as progress:
        task = progress.add_task(description, total=total)

        def on_stage(name: str, event: str) -> None:
            if event == "start":
                started[name] = time.perf_counter()
                progress.update(task, description=STAGE_LABELS.get(name, name))
            else:
                progress.advance(task)
                if not console.is_terminal:
                    console.print(f"{name}: done in {time.perf_counter() - started[name]:.1f} s")

        yield on_stage


def run(
    case_path: Path,
    out: Path,
    *,
    seed: int,
    device: str,
    igtl: str | None = None,
    settings_file: Path | None = None,
) -> int:
    """Navigate on a case file and write the outputs; returns the exit status. With ``igtl``
    (``HOST:PORT``) the navigation is streamed live to that OpenIGTLink server (3D Slicer); with
    ``settings_file`` a site's settings override the navigation's defaults."""
    from fluoronav.device import resolve_device  # heavy: torch
    from fluoronav.navigation.case.model import load_navigation_case  # lazy: fast --help
    from fluoronav.navigation.outputs.files import write_outputs  # lazy: fast --help
    from fluoronav.navigation.outputs.igtl import IGTLinkStreamer, chain_stage_callbacks  # lazy: fast --help
    from fluoronav.navigation.pipeline import (  # lazy: fast --help
        STAGES,
        VERIFY_STAGES,
        navigate,
    )

    link = IGTLinkStreamer(igtl) if igtl is not None else None  # a malformed address is bad input
    cfg = navigation_config(settings_file, device=str(resolve_device(device)), seed=seed)
    case = load_navigation_case(case_path)
    total = len(STAGES) + (len(VERIFY_STAGES) if case.verification is not None else 0)
    with stage_progress(total, "navigate") as progress, link or nullcontext():
        result = navigate(
            case,
            cfg,
            on_stage=chain_stage_callbacks(progress, link.on_stage if link is not None else None),
            on_event=link.on_event if link is not None else None,
        )
    write_outputs(
        result,
        case,
        out,
        extra={"case": str(case_path)},
        report_description=f"Navigation on {case_path} ({len(case.views)} views"
        + (f", {len(case.verification.views)} verification views)" if case.verification else ")"),
    )
    if result.status != "ok":
        typer.echo(f"refused: {result.reason}", err=True)
        typer.echo(f"no robot command; wrote {out / 'navigation.json'} and {out / 'report.html'}")
        return EXIT_REFUSED
    assert result.joints_target_deg is not None
    q = result.joints_correction_deg if result.joints_correction_deg is not None else result.joints_target_deg
    what = "corrective" if result.joints_correction_deg is not None else "target"
    typer.echo(f"{what} joints (deg): {' '.join(f'{v:.3f}' for v in q)}")
    typer.echo(f"wrote {out / 'navigation.json'}, {out / 'slicer'} and {out / 'report.html'}")
    return 0


def register(app: typer.Typer) -> None:
    @app.command("navigate")
    def navigate_command(
        case: Path = typer.Argument(..., help="Navigation case (JSON), see docs/data-formats.md."),
        out: Path = typer.Option(
            ..., "--out", help="Output directory (navigation.json, slicer/, report.html)."
        ),
        seed: int = SEED_OPTION,
        device: str = DEVICE_OPTION,
        igtl: str | None = IGTL_OPTION,
        settings_file: Path | None = SETTINGS_OPTION,
    ) -> None:
        """Navigation on your own files: detection → pelvis → femur → CM → plan → robot command
        (and, with verification views, their registration and one corrective command). Exit status
        3 when it refuses to give a command."""
        raise typer.Exit(run(case, out, seed=seed, device=device, igtl=igtl, settings_file=settings_file))
