"""``fluoronav study WORKFLOW``: the paper's simulation study for one workflow."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from fluoronav.cli.common import DEVICE_OPTION
from fluoronav.errors import InputError

_FAULT_OPTION = typer.Option(
    None,
    "--fault",
    help="navigation: inject an input fault (mirror_one, mirror_all, focal_10pct, verify_joints_3deg, "
    "handeye_10mm, verify_no_move, view_without_cm, labels_swapped, plan_inward_300, inverted, none).",
)
_HANDEYE_ERROR_MM_OPTION = typer.Option(
    None,
    "--handeye-error-mm",
    min=0.0,
    help="navigation: the case's hand-eye matrix is the truth moved by this (mm; default 0.5, "
    "10 with --fault handeye_10mm).",
)
_HANDEYE_ERROR_DEG_OPTION = typer.Option(
    None,
    "--handeye-error-deg",
    min=0.0,
    help="navigation: the case's hand-eye matrix is the truth turned by this (degrees; default 0.4).",
)


#: the studies that simulate their trials in a world (hand-eye and deepfluoro do not)
_WORLD_WORKFLOWS = ("navigation", "centerline", "single-view", "multi-view", "multi-cm")

_WORLD_OPTION = typer.Option(
    "ideal",
    "--world",
    help="navigation, centerline, single-view, multi-view, multi-cm: the simulated world's error "
    "sources: ideal, realistic, or a JSON file of magnitudes (docs/simulation.md).",
)


_VERIFY_VIEWS_OPTION = typer.Option(
    None,
    "--verify-views",
    min=1,
    max=3,
    help="navigation: verification images per case after the move (1, 2 or 3; default 3).",
)


def _navigation_options(
    workflow: str,
    fault: str | None,
    handeye_error_mm: float | None,
    handeye_error_deg: float | None,
    world: str,
    verify_views: int | None = None,
) -> dict[str, Any]:
    """The navigation study's own options and the world of the studies that take one, checked (an
    unknown fault or world, or one given to another study, is an :class:`InputError`)."""
    out: dict[str, Any] = {}
    if fault is not None or handeye_error_mm is not None or handeye_error_deg is not None:
        if workflow != "navigation":
            raise InputError("--fault", "--fault and --handeye-error-* are options of study navigation")
        from fluoronav.simulation.navigation.faults import get_fault  # lazy: fast --help

        get_fault(fault)
        out.update(fault=fault, handeye_error_mm=handeye_error_mm, handeye_error_deg=handeye_error_deg)
    if world != "ideal":
        if workflow not in _WORLD_WORKFLOWS:
            raise InputError(
                "--world", f"study {workflow} takes no simulated world; {', '.join(_WORLD_WORKFLOWS)} do"
            )
        from fluoronav.simulation.world import load_world  # lazy: fast --help

        out["world"] = load_world(world)
    if verify_views is not None:
        if workflow != "navigation":
            raise InputError("--verify-views", "--verify-views is an option of study navigation")
        out["verify_views"] = verify_views
    return out


def _echo_summary(workflow: str, summary: dict[str, Any]) -> None:
    m = summary.get("metrics", {})
    parts = [f"{k} {v['mean']:.3g}±{v['std']:.2g}" for k, v in m.items()]
    if summary.get("within_1deg") is not None:
        parts.append(f"within 1° {100 * summary['within_1deg']:.0f} %")
    typer.echo(
        f"{workflow}: {summary['completed']}/{summary['trials']} trials, {summary['failed']} failed; "
        + ", ".join(parts)
    )


def register(app: typer.Typer) -> None:
    @app.command("study")
    def study(
        workflow: str = typer.Argument(
            ..., help="centerline, single-view, multi-view, multi-cm, hand-eye, navigation or deepfluoro."
        ),
        trials: int = typer.Option(
            None, "--trials", min=1, help="Number of trials (deepfluoro: default one per image)."
        ),
        seed: int = typer.Option(..., "--seed", help="Run seed; each trial's seed derives from it."),
        out: Path = typer.Option(..., "--out", help="Output directory (rerun to resume)."),
        ct: str = typer.Option("phantom", "--ct", help="CT file/DICOM dir, or 'phantom'."),
        scheduler: str = typer.Option(None, "--scheduler", help="Address of an existing Dask scheduler."),
        workers: int = typer.Option(
            None, "--workers", min=0, help="Local worker processes (default: up to 2; 0 = in this process)."
        ),
        oracle_landmarks: bool = typer.Option(
            False,
            "--oracle-landmarks",
            help="Use the true landmarks + U(−3, 3) px noise (the authors' code) instead of the detector.",
        ),
        image_size: int = typer.Option(
            768, "--image-size", min=128, help="Simulated image size (the 1536² detector is binned to it)."
        ),
        phantoms: int = typer.Option(1, "--phantoms", min=1, help="Phantom anatomies to draw trials from."),
        init: str = typer.Option(
            "centerline",
            "--init",
            help="CM start: centerline (the paper) or perturbed (truth + 10°/10 mm, as the authors' code).",
        ),
        poses: list[int] = typer.Option(
            [4, 8, 15], "--poses", help="hand-eye: numbers of robot poses M to calibrate with (repeatable)."
        ),
        calibration_bend_deg: float = typer.Option(
            2.5,
            "--calibration-bend-deg",
            min=0.0,
            help="hand-eye: the CM's constant bend while calibrating, degrees per control point "
            "(each ± 0.5°; 2.5 ≈ a 70° C-bend, 0 ≈ straight).",
        ),
        corrections: int = typer.Option(
            1,
            "--corrections",
            min=0,
            max=1,
            help="navigation: 1: verification images after the move and one corrective move; 0: open loop.",
        ),
        fault: str = _FAULT_OPTION,
        world: str = _WORLD_OPTION,
        verify_views: int = _VERIFY_VIEWS_OPTION,
        handeye_error_mm: float = _HANDEYE_ERROR_MM_OPTION,
        handeye_error_deg: float = _HANDEYE_ERROR_DEG_OPTION,
        data: Path = typer.Option(None, "--data", help="deepfluoro: the DeepFluoro HDF5 file (yours)."),
        specimen: str = typer.Option(None, "--specimen", help="deepfluoro: one specimen (ID or 1–6)."),
        xreg_gt_correction: bool = typer.Option(
            False,
            "--xreg-gt-correction",
            help="deepfluoro: the truth −0.5 mm per CT axis, as xReg's samples.",
        ),
        device: str = DEVICE_OPTION,
    ) -> None:
        """Run (or resume) a study; writes trials.csv, summary.json and figures/."""
        from fluoronav.device import resolve_device  # heavy: torch

        navigation = _navigation_options(
            workflow, fault, handeye_error_mm, handeye_error_deg, world, verify_views
        )
        if workflow == "deepfluoro":
            summary = _deepfluoro(
                data, trials, seed, out, specimen, xreg_gt_correction, device, scheduler, workers
            )
        elif trials is None:
            raise InputError("--trials", f"study {workflow} needs --trials N")
        elif workflow in ("hand-eye", "navigation"):
            from fluoronav.studies.handeye_study import run_handeye_or_navigation_study  # lazy: fast --help

            summary = run_handeye_or_navigation_study(
                workflow,
                trials=trials,
                seed=seed,
                out=out,
                ct=ct,
                scheduler=scheduler,
                workers=workers,
                device=str(resolve_device(device)),
                poses=tuple(poses),
                image_size=image_size,
                corrections=corrections,
                # the hand-eye study has always used oracle landmarks; navigation the detector by default
                oracle_landmarks=oracle_landmarks or workflow == "hand-eye",
                calibration_bend_deg=calibration_bend_deg,
                **navigation,
            )
        else:
            from fluoronav.simulation.world import IDEAL
            from fluoronav.studies.pipeline import (  # lazy: fast --help
                STUDY_WORKFLOWS,
                StudyConfig,
                run_study,
            )

            if workflow not in STUDY_WORKFLOWS:
                raise InputError("WORKFLOW", f"unknown workflow {workflow!r}")
            cfg = StudyConfig(
                workflow=workflow,
                trials=trials,
                seed=seed,
                ct=ct,
                oracle_landmarks=oracle_landmarks,
                image_size=image_size,
                device=str(resolve_device(device)),
                n_phantoms=phantoms,
                init=init,
                world=navigation.get("world", IDEAL),  # the other options are refused above
            )
            summary = run_study(cfg, out, scheduler=scheduler, workers=workers)
        _echo_summary(workflow, summary)


def _deepfluoro(
    data: Path | None,
    trials: int | None,
    seed: int,
    out: Path,
    specimen: str | None,
    xreg_gt_correction: bool,
    device: str,
    scheduler: str | None,
    workers: int | None,
) -> dict[str, Any]:
    """``study deepfluoro`` (docs/real-data.md)."""
    from fluoronav.device import resolve_device  # heavy: torch
    from fluoronav.studies.deepfluoro import DeepFluoroStudyConfig, run_deepfluoro_study  # lazy: fast --help

    if data is None:
        raise InputError("--data", "study deepfluoro needs --data FILE.h5 (see docs/real-data.md)")
    cfg = DeepFluoroStudyConfig(
        data=str(data),
        seed=seed,
        trials=trials,
        specimen=specimen,
        device=str(resolve_device(device)),
        xreg_texture_correction=xreg_gt_correction,
    )
    return run_deepfluoro_study(cfg, out, scheduler=scheduler, workers=workers)
