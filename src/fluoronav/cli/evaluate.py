"""``fluoronav evaluate``: accuracy of a detector on a ``simulate`` data set."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer

from fluoronav.cli.common import DEVICE_OPTION, PRECISION_OPTION
from fluoronav.errors import InputError


def evaluate_command(
    data: list[Path] = typer.Option(
        ...,
        "--data",
        help=(
            "Data set directory written by `fluoronav simulate`. Repeat it to score several sets: the "
            "summary then holds each set's figures and those of all their images pooled."
        ),
    ),
    model: Path | None = typer.Option(None, "--model", help="Model file (default: the shipped weights)."),
    out: Path | None = typer.Option(None, "--out", help="Write the summary JSON here."),
    split: str = typer.Option("val", "--split", help="train, val (held out by id hash) or all."),
    device: str = DEVICE_OPTION,
    precision: str = PRECISION_OPTION,
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar."),
    field_frac: float | None = typer.Option(
        None,
        "--field-frac",
        help="Crop each image to a collimated field of this fraction of its sides (keeping the CM) first.",
    ),
    seed: int = typer.Option(0, "--seed", help="Seed of the fields' places (with --field-frac)."),
    per_sample: Path | None = typer.Option(
        None,
        "--per-sample",
        help="Also write one JSON line per image here as it is scored (errors, Dice, confidences).",
    ),
) -> None:
    """Dice, landmark error (px, mm), found rate and false-positive rate of a detector on one or more
    data sets (several: each set's figures and the pooled ones)."""
    from fluoronav.detection.detector import Detector  # lazy: fast --help
    from fluoronav.detection.training.evaluate import evaluate, evaluate_sets  # lazy: fast --help

    if split not in ("train", "val", "all"):
        raise InputError("--split", f"unknown split {split!r}; use train, val or all")
    if field_frac is not None and not 0.0 < field_frac <= 1.0:
        raise InputError("--field-frac", f"must be in (0, 1], got {field_frac}")
    # fail before the run, not after it: both outputs must be writable (a probe file that did not
    # exist is removed again, so that a run failing later leaves no empty output behind)
    for path in (out, per_sample):
        if path is not None:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                existed = path.exists()
                with open(path, "a", encoding="utf-8"):
                    pass
                if not existed:
                    path.unlink()
            except OSError as exc:
                why = exc.strerror or str(exc)
                if exc.filename is not None and Path(exc.filename) != path:
                    why = f"{exc.filename}: {why}"
                raise InputError(path, f"cannot write here ({why})") from exc
    detector = Detector.load(model, device=device, precision=precision)
    options: dict[str, Any] = {
        "split": split,
        "progress": progress,
        "field_frac": field_frac,
        "seed": seed,
        "per_sample": per_sample,
    }
    summary = (
        evaluate(detector, data[0], **options) if len(data) == 1 else evaluate_sets(detector, data, **options)
    )
    text = json.dumps(summary, indent=1)
    if out is not None:
        out.write_text(text + "\n", encoding="utf-8")
    typer.echo(text)


def register(app: typer.Typer) -> None:
    app.command("evaluate")(evaluate_command)
