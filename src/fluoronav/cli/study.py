"""``fluoronav study WORKFLOW``: the paper's simulation studies, one sub-command per workflow.

``centerline``, ``single-view``, ``multi-view`` and ``multi-cm`` are the registration studies
(:mod:`fluoronav.studies.pipeline`), ``hand-eye`` and ``navigation`` the robot's
(:mod:`fluoronav.studies.handeye_study`), ``deepfluoro`` the pelvis on real images
(:mod:`fluoronav.studies.deepfluoro`). Each takes only its own options; the options several share
are defined once below.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from fluoronav.cli.common import DEVICE_OPTION
from fluoronav.cli.config import SETTINGS_OPTION, navigation_config
from fluoronav.errors import InputError

if TYPE_CHECKING:
    from fluoronav.simulation.world import World

# ----- options several studies take ---------------------------------------------------------------
_TRIALS_OPTION = typer.Option(..., "--trials", min=1, help="Number of trials.")
_SEED_OPTION = typer.Option(..., "--seed", help="Run seed; each trial's seed derives from it.")
_OUT_OPTION = typer.Option(..., "--out", help="Output directory (rerun to resume).")
_CT_OPTION = typer.Option("phantom", "--ct", help="CT file/DICOM dir, or 'phantom'.")
_SCHEDULER_OPTION = typer.Option(None, "--scheduler", help="Address of an existing Dask scheduler.")
_WORKERS_OPTION = typer.Option(
    None, "--workers", min=0, help="Local worker processes (default: up to 2; 0 = in this process)."
)
_IMAGE_SIZE_OPTION = typer.Option(
    768, "--image-size", min=128, help="Simulated image size (the 1536² detector is binned to it)."
)
_ORACLE_LANDMARKS_OPTION = typer.Option(
    False,
    "--oracle-landmarks",
    help="Use the true landmarks + U(−3, 3) px noise (the authors' code) instead of the detector.",
)
_WORLD_OPTION = typer.Option(
    "ideal",
    "--world",
    help="The simulated world's error sources: ideal, realistic, or a JSON file of magnitudes "
    "(docs/simulation.md).",
)

# ----- the registration studies' own ----------------------------------------------------------------
_PHANTOMS_OPTION = typer.Option(1, "--phantoms", min=1, help="Phantom anatomies to draw trials from.")
_INIT_OPTION = typer.Option(
    "centerline",
    "--init",
    help="CM start: centerline (the paper) or perturbed (truth + 10°/10 mm, as the authors' code).",
)

# ----- hand-eye's own -------------------------------------------------------------------------------
_POSES_OPTION = typer.Option(
    [4, 8, 15], "--poses", help="Numbers of robot poses M to calibrate with (repeatable)."
)
_CALIBRATION_BEND_OPTION = typer.Option(
    2.5,
    "--calibration-bend-deg",
    min=0.0,
    help="The CM's constant bend while calibrating, degrees per control point "
    "(each ± 0.5°; 2.5 ≈ a 70° C-bend, 0 ≈ straight).",
)

# ----- navigation's own -----------------------------------------------------------------------------
_CORRECTIONS_OPTION = typer.Option(
    1,
    "--corrections",
    min=0,
    max=1,
    help="1: verification images after the move and one corrective move; 0: open loop.",
)
_VERIFY_VIEWS_OPTION = typer.Option(
    None,
    "--verify-views",
    min=1,
    max=3,
    help="Verification images per case after the move (1, 2 or 3; default 3).",
)
_FAULT_OPTION = typer.Option(
    None,
    "--fault",
    help="Inject an input fault (mirror_one, mirror_all, focal_10pct, verify_joints_3deg, "
    "handeye_10mm, verify_no_move, view_without_cm, labels_swapped, plan_inward_300, inverted, "
    "labels_mirrored, labels_shifted_5mm, fbg_beyond_range, plan_other_femur, fbg_bent_3deg, "
    "fbg_other_shape, ct_spacing_110, ct_spacing_090, view_other_patient, none).",
)
_HANDEYE_ERROR_MM_OPTION = typer.Option(
    None,
    "--handeye-error-mm",
    min=0.0,
    help="The case's hand-eye matrix is the truth moved by this (mm; default 0.5, "
    "10 with --fault handeye_10mm).",
)
_HANDEYE_ERROR_DEG_OPTION = typer.Option(
    None,
    "--handeye-error-deg",
    min=0.0,
    help="The case's hand-eye matrix is the truth turned by this (degrees; default 0.4).",
)

# ----- deepfluoro's own -----------------------------------------------------------------------------
_DATA_OPTION = typer.Option(None, "--data", help="The DeepFluoro HDF5 file (yours).")
_DEEPFLUORO_TRIALS_OPTION = typer.Option(
    None, "--trials", min=1, help="Number of trials (default: one per image)."
)
_SPECIMEN_OPTION = typer.Option(None, "--specimen", help="One specimen (ID or 1–6).")
_XREG_GT_CORRECTION_OPTION = typer.Option(
    False, "--xreg-gt-correction", help="The truth −0.5 mm per CT axis, as xReg's samples."
)

study_app = typer.Typer(
    help="Run (or resume) one of the paper's studies; writes trials.csv, summary.json and figures/.",
    no_args_is_help=True,
)

#: the registration studies (:data:`fluoronav.studies.pipeline.STUDY_WORKFLOWS`) and their help
_REGISTRATION_STUDIES = {
    "centerline": "The centreline initialisation alone (one view): depth and roll of the CM's start.",
    "single-view": "Single-view registration: pelvis, femur and CM in one image.",
    "multi-view": "Multi-view registration: pelvis per view, femur and CM in three images.",
    "multi-cm": "Multiple-CM registration: the CM at four robot poses in one view.",
}


def register(app: typer.Typer) -> None:
    app.add_typer(study_app, name="study")


def _load_world(world: str) -> World:
    """The ``--world`` option's world (an unknown one is an :class:`InputError`)."""
    from fluoronav.simulation.world import IDEAL, load_world  # lazy: fast --help

    return IDEAL if world == "ideal" else load_world(world)


def _echo_summary(workflow: str, summary: dict[str, Any]) -> None:
    """The study's outcome in one line: trials done and failed, each metric's mean ± std."""
    m = summary.get("metrics", {})
    parts = [f"{k} {v['mean']:.3g}±{v['std']:.2g}" for k, v in m.items()]
    if summary.get("within_1deg") is not None:
        parts.append(f"within 1° {100 * summary['within_1deg']:.0f} %")
    typer.echo(
        f"{workflow}: {summary['completed']}/{summary['trials']} trials, {summary['failed']} failed; "
        + ", ".join(parts)
    )


def _registration_study(workflow: str) -> Callable[..., None]:
    """The sub-command of the registration study ``workflow``."""

    def command(
        trials: int = _TRIALS_OPTION,
        seed: int = _SEED_OPTION,
        out: Path = _OUT_OPTION,
        ct: str = _CT_OPTION,
        scheduler: str | None = _SCHEDULER_OPTION,
        workers: int | None = _WORKERS_OPTION,
        oracle_landmarks: bool = _ORACLE_LANDMARKS_OPTION,
        image_size: int = _IMAGE_SIZE_OPTION,
        phantoms: int = _PHANTOMS_OPTION,
        init: str = _INIT_OPTION,
        world: str = _WORLD_OPTION,
        device: str = DEVICE_OPTION,
    ) -> None:
        from fluoronav.device import resolve_device  # heavy: torch
        from fluoronav.studies.pipeline import StudyConfig, run_study  # lazy: fast --help

        simulated_world = _load_world(world)
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
            world=simulated_world,
        )
        _echo_summary(workflow, run_study(cfg, out, scheduler=scheduler, workers=workers))

    return command


for _workflow, _help in _REGISTRATION_STUDIES.items():
    study_app.command(_workflow, help=_help)(_registration_study(_workflow))


@study_app.command("hand-eye")
def hand_eye(
    trials: int = _TRIALS_OPTION,
    seed: int = _SEED_OPTION,
    out: Path = _OUT_OPTION,
    ct: str = _CT_OPTION,
    scheduler: str | None = _SCHEDULER_OPTION,
    workers: int | None = _WORKERS_OPTION,
    poses: list[int] = _POSES_OPTION,
    calibration_bend_deg: float = _CALIBRATION_BEND_OPTION,
    image_size: int = _IMAGE_SIZE_OPTION,
    device: str = DEVICE_OPTION,
) -> None:
    """Image-based hand-eye calibration (oracle landmarks): its error against the number of poses."""
    from fluoronav.device import resolve_device  # heavy: torch
    from fluoronav.studies.handeye_study import run_handeye_or_navigation_study  # lazy: fast --help

    summary = run_handeye_or_navigation_study(
        "hand-eye",
        trials=trials,
        seed=seed,
        out=out,
        ct=ct,
        scheduler=scheduler,
        workers=workers,
        device=str(resolve_device(device)),
        poses=tuple(poses),
        image_size=image_size,
        oracle_landmarks=True,  # the hand-eye study has always used oracle landmarks
        calibration_bend_deg=calibration_bend_deg,
    )
    _echo_summary("hand-eye", summary)


@study_app.command("navigation")
def navigation(
    trials: int = _TRIALS_OPTION,
    seed: int = _SEED_OPTION,
    out: Path = _OUT_OPTION,
    ct: str = _CT_OPTION,
    scheduler: str | None = _SCHEDULER_OPTION,
    workers: int | None = _WORKERS_OPTION,
    oracle_landmarks: bool = _ORACLE_LANDMARKS_OPTION,
    image_size: int = _IMAGE_SIZE_OPTION,
    corrections: int = _CORRECTIONS_OPTION,
    verify_views: int | None = _VERIFY_VIEWS_OPTION,
    world: str = _WORLD_OPTION,
    fault: str | None = _FAULT_OPTION,
    handeye_error_mm: float | None = _HANDEYE_ERROR_MM_OPTION,
    handeye_error_deg: float | None = _HANDEYE_ERROR_DEG_OPTION,
    device: str = DEVICE_OPTION,
    settings_file: Path | None = SETTINGS_OPTION,
) -> None:
    """The navigation loop per trial: register, move, verify, correct; the tip's error to the plan."""
    from fluoronav.device import resolve_device  # heavy: torch
    from fluoronav.simulation.navigation.faults import get_fault  # lazy: fast --help
    from fluoronav.studies.handeye_study import run_handeye_or_navigation_study  # lazy: fast --help

    get_fault(fault)  # an unknown fault is an InputError before anything runs
    simulated_world = _load_world(world)
    # without --verify-views the study's own default
    views: dict[str, Any] = {} if verify_views is None else {"verify_views": verify_views}
    # a site's settings file: the navigation's settings (each trial sets its own device and seed)
    site: dict[str, Any] = {} if settings_file is None else {"navigation": navigation_config(settings_file)}
    summary = run_handeye_or_navigation_study(
        "navigation",
        trials=trials,
        seed=seed,
        out=out,
        ct=ct,
        scheduler=scheduler,
        workers=workers,
        device=str(resolve_device(device)),
        image_size=image_size,
        corrections=corrections,
        oracle_landmarks=oracle_landmarks,
        fault=fault,
        handeye_error_mm=handeye_error_mm,
        handeye_error_deg=handeye_error_deg,
        world=simulated_world,
        **views,
        **site,
    )
    _echo_summary("navigation", summary)


@study_app.command("deepfluoro")
def deepfluoro(
    data: Path | None = _DATA_OPTION,
    trials: int | None = _DEEPFLUORO_TRIALS_OPTION,
    seed: int = _SEED_OPTION,
    out: Path = _OUT_OPTION,
    specimen: str | None = _SPECIMEN_OPTION,
    xreg_gt_correction: bool = _XREG_GT_CORRECTION_OPTION,
    scheduler: str | None = _SCHEDULER_OPTION,
    workers: int | None = _WORKERS_OPTION,
    device: str = DEVICE_OPTION,
) -> None:
    """The pelvis registration on the DeepFluoro cadaver images (docs/real-data.md)."""
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
    _echo_summary("deepfluoro", run_deepfluoro_study(cfg, out, scheduler=scheduler, workers=workers))
