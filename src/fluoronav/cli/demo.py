"""``fluoronav demo``: the navigation loop on the built-in phantom, no files needed.

See :mod:`fluoronav.simulation.navigation.demo`. Writes the simulated case to ``DIR/case/`` and the truth to
``DIR/truth.json``, runs the navigation pipeline on those files, and writes ``DIR/results.json``,
``DIR/navigation.json``, ``DIR/slicer/`` and ``DIR/report.html``; prints errors and timings.
"""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from fluoronav.cli.common import DEVICE_OPTION, SEED_OPTION
from fluoronav.cli.config import SETTINGS_OPTION, navigation_config
from fluoronav.cli.navigate import EXIT_REFUSED, IGTL_OPTION, stage_progress


def run(
    out: Path,
    *,
    seed: int,
    device: str,
    image_size: int,
    oracle_landmarks: bool,
    igtl: str | None = None,
    world: str = "ideal",
    verify_views: int = 2,
    settings_file: Path | None = None,
) -> int:
    """Run the demo, print its table, write its files; returns the exit status (3: refused). With
    ``igtl`` (``HOST:PORT``) the navigation is streamed live to that OpenIGTLink server (3D Slicer);
    with ``settings_file`` a site's settings override the navigation's defaults."""
    from fluoronav.device import resolve_device  # heavy: torch
    from fluoronav.navigation.outputs.igtl import IGTLinkStreamer, chain_stage_callbacks  # lazy: fast --help
    from fluoronav.navigation.pipeline import STAGES, VERIFY_STAGES  # lazy: fast --help
    from fluoronav.simulation.navigation.demo import (  # lazy: fast --help
        ERROR_ROWS,
        ordered_timings,
        run_demo,
        write_demo_outputs,
    )
    from fluoronav.simulation.navigation.loop import (  # lazy: fast --help
        SIMULATION_STAGES,
        SimulatedNavigationConfig,
    )
    from fluoronav.simulation.world import load_world  # lazy: fast --help

    link = IGTLinkStreamer(igtl) if igtl is not None else None  # a malformed address is bad input
    console = Console(stderr=True)
    cfg = SimulatedNavigationConfig(
        seed=seed,
        image_size=image_size,
        device=str(resolve_device(device)),
        oracle_landmarks=oracle_landmarks,
        world=load_world(world),
        verify_views=verify_views,
    )
    # the site's settings (None: the loop's defaults, from the simulation's device and seed)
    navigation = (
        None if settings_file is None else navigation_config(settings_file, device=cfg.device, seed=seed)
    )
    total = len(SIMULATION_STAGES) + len(STAGES) + len(VERIFY_STAGES)
    with stage_progress(total, "demo") as progress, link or nullcontext():
        run_ = run_demo(
            cfg,
            out=out,
            navigation=navigation,
            on_stage=chain_stage_callbacks(progress, link.on_stage if link is not None else None),
            on_event=link.on_event if link is not None else None,
        )
    write_demo_outputs(run_, out)

    table = Table(title=f"fluoronav demo (seed {seed}): errors against the simulated truth")
    for col in ("quantity", "value", "unit", "paper"):
        table.add_column(col)
    for label, key, unit, paper in ERROR_ROWS:
        if key in run_.errors:
            table.add_row(label, f"{run_.errors[key]:.3g}", unit, paper)
    console.print(table)
    times = Table(title="seconds per stage")
    times.add_column("stage")
    times.add_column("s", justify="right")
    timings = ordered_timings(run_)
    for name, secs in timings.items():
        times.add_row(name, f"{secs:.1f}")
    times.add_row("total", f"{sum(timings.values()):.1f}")
    console.print(times)
    case_file = out / "case" / "navigation.json"
    typer.echo(f"case: {case_file} (run it again: fluoronav navigate {case_file} --out DIR)")
    if run_.status != "ok":
        console.print(f"[bold red]REFUSED: {run_.reason}[/bold red] (no robot command was given)")
        typer.echo(f"wrote {out / 'results.json'} and {out / 'report.html'}")
        return EXIT_REFUSED
    typer.echo(
        f"wrote {out / 'results.json'}, {out / 'navigation.json'}, {out / 'slicer'} and {out / 'report.html'}"
    )
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
        igtl: str | None = IGTL_OPTION,
        world: str = typer.Option(
            "ideal",
            "--world",
            help="The simulated world's error sources: ideal, realistic, or a JSON file of magnitudes.",
        ),
        verify_views: int = typer.Option(
            2,
            "--verify-views",
            min=1,
            max=3,
            help="Verification images after the move (1, 2 or 3): by default the two orbits.",
        ),
        settings_file: Path | None = SETTINGS_OPTION,
    ) -> None:
        """Simulated navigation on the built-in phantom: a simulated case written to files, then the
        navigate pipeline on them (detection → registration → robot command), the move, verification
        and one correction; writes case/, truth.json, results.json, navigation.json, slicer/ and
        report.html to --out. Exit status 3 when the navigation refused."""
        code = run(
            out,
            seed=seed,
            device=device,
            image_size=image_size,
            oracle_landmarks=oracle_landmarks,
            igtl=igtl,
            world=world,
            verify_views=verify_views,
            settings_file=settings_file,
        )
        raise typer.Exit(code)
