"""``fluoronav train``: train the CM detector on a ``simulate`` data set."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from fluoronav.cli.common import DEVICE_OPTION, SEED_OPTION

if TYPE_CHECKING:
    from fluoronav.detection.training.config import TrainConfig

_DATA_OPTION = typer.Option(
    ...,
    "--data",
    help="Data set directory written by `fluoronav simulate` (repeatable, e.g. add a --no-cm set).",
)
_OUT_OPTION = typer.Option(
    ...,
    "--out",
    help="Model file to write (.pt); MODEL.json, MODEL.ckpt and MODEL.log.jsonl are written next to it.",
)
_INIT_OPTION = typer.Option(
    None,
    "--init",
    help="Start from the weights of this model file (fine-tuning; fresh optimiser and schedule).",
)
_KEEP_DECODING_OPTION = typer.Option(
    False,
    "--keep-decoding",
    help="With --init: keep that model's decoding settings (thresholds, passes, test-time "
    "augmentation) instead of this version's defaults.",
)
_STAGE_OPTION = typer.Option(
    ["coarse", "fine"],
    "--stage",
    help="Stage to train (repeatable: coarse, fine; or one alone: refine, the landmark refinement "
    "stage; ends, the mask-end stage; tube, the tube-mask stage; shaft, the shaft stage (needs "
    "--tube-shaft-prob); each added to an --init model without one); the others keep their weights "
    "and are not run.",
)
_REFINE_REPEATS_OPTION = typer.Option(
    5,
    "--refine-repeats",
    min=1,
    help="--stage refine, ends, tube or shaft: jittered patches per landmark and sample per epoch.",
)
_COLLIMATE_PROB_OPTION = typer.Option(
    0.0,
    "--collimate-prob",
    min=0.0,
    max=1.0,
    help="Probability of cropping a training sample to a random collimated field first.",
)
_PARTIAL_ROI_PROB_OPTION = typer.Option(
    0.0,
    "--partial-roi-prob",
    min=0.0,
    max=1.0,
    help="Probability of fitting a training sample's fine ROI to a part of its CM only (the CM runs "
    "out of the ROI, as after a coarse detection of part of it).",
)
_EDGE_NEGATIVE_PROB_OPTION = typer.Option(
    0.0,
    "--edge-negative-prob",
    min=0.0,
    max=1.0,
    help="Probability of centring a CM-free training sample's fine ROI on a strong edge of its image "
    "(bone rims, the joint: where false alarms start) instead of anywhere.",
)
_TUBE_SHAFT_PROB_OPTION = typer.Option(
    0.0,
    "--tube-shaft-prob",
    min=0.0,
    max=1.0,
    help="--stage tube or shaft: probability of centring a patch on the projected mounting shaft "
    "(labelled not-CM) instead of the CM's centreline, so that the stage tells a plain shaft from "
    "the CM.",
)
_MAX_STEPS_OPTION = typer.Option(
    None,
    "--max-steps-per-epoch",
    min=1,
    help="End each epoch after this many steps (default: one pass over the training split).",
)
_COARSE_SIZE_OPTION = typer.Option(
    None,
    "--coarse-size",
    min=32,
    help="Coarse stage working resolution in pixels (a multiple of 16), also against an --init "
    "model's: its coarse weights are trained on at the new scale (needs --stage coarse).",
)


def _checked_config(coarse_size: int | None, **settings: object) -> TrainConfig:
    """The training settings, their rules broken as a bad parameter (TrainConfig holds the rules:
    which --stage combinations train, ranges)."""
    from fluoronav.detection.training.train import TrainConfig, check_coarse_size  # lazy: fast --help

    try:
        config = TrainConfig(**settings)  # type: ignore[arg-type]
        check_coarse_size(coarse_size, config.stages)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    return config


def train_command(
    data: list[Path] = _DATA_OPTION,
    out: Path = _OUT_OPTION,
    epochs: int = typer.Option(10, "--epochs", min=1, help="Number of epochs (total, also with --resume)."),
    batch_size: int = typer.Option(16, "--batch-size", min=1, help="Samples per optimisation step."),
    lr: float = typer.Option(1e-3, "--lr", help="Initial Adam learning rate."),
    lr_step: int = typer.Option(
        10, "--lr-step", min=1, help="Multiply the learning rate by 0.1 every this many epochs."
    ),
    workers: int = typer.Option(0, "--workers", min=0, help="Data loader worker processes."),
    resume: bool = typer.Option(False, "--resume", help="Continue from the checkpoint MODEL.ckpt."),
    init: Path | None = _INIT_OPTION,
    keep_decoding: bool = _KEEP_DECODING_OPTION,
    stage: list[str] = _STAGE_OPTION,
    refine_repeats: int = _REFINE_REPEATS_OPTION,
    collimate_prob: float = _COLLIMATE_PROB_OPTION,
    partial_roi_prob: float = _PARTIAL_ROI_PROB_OPTION,
    edge_negative_prob: float = _EDGE_NEGATIVE_PROB_OPTION,
    tube_shaft_prob: float = _TUBE_SHAFT_PROB_OPTION,
    max_steps_per_epoch: int | None = _MAX_STEPS_OPTION,
    coarse_size: int | None = _COARSE_SIZE_OPTION,
    seed: int = SEED_OPTION,
    device: str = DEVICE_OPTION,
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar."),
) -> None:
    """Train the detector (segmentation + landmark heatmaps, or the landmark refinement) and write MODEL."""
    from fluoronav.detection.training.train import train  # lazy: fast --help

    config = _checked_config(
        coarse_size,
        epochs=epochs,
        batch_size=batch_size,
        lr=lr,
        lr_step_epochs=lr_step,
        seed=seed,
        device=device,
        workers=workers,
        stages=tuple(dict.fromkeys(stage)),
        collimate_prob=collimate_prob,
        partial_roi_prob=partial_roi_prob,
        edge_negative_prob=edge_negative_prob,
        refine_repeats=refine_repeats,
        tube_shaft_prob=tube_shaft_prob,
        max_steps_per_epoch=max_steps_per_epoch,
    )
    if keep_decoding and init is None:
        raise typer.BadParameter(
            "--keep-decoding keeps the decoding settings of an --init model: give --init"
        )
    metrics = train(
        data,
        out,
        config=config,
        resume=resume,
        init=init,
        keep_decoding=keep_decoding,
        coarse_size=coarse_size,
        progress=progress,
    )
    typer.echo(json.dumps(metrics))


def register(app: typer.Typer) -> None:
    app.command("train")(train_command)
