"""``fluoronav evaluate``: accuracy of one or more detectors on ``simulate`` data sets."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich import box
from rich.console import Console
from rich.table import Table

from fluoronav.cli.common import DEVICE_OPTION, PRECISION_OPTION
from fluoronav.errors import InputError

if TYPE_CHECKING:
    from fluoronav.detection.detector import Detector

#: the ``--model`` value (and label) that names the shipped weights
SHIPPED = "shipped"


def _model_files(values: list[str]) -> dict[str, Path | None]:
    """Each ``--model`` value's label and file (None: the shipped weights), in order: ``shipped``, a
    file (labelled by its stem) or ``LABEL=FILE``; no value at all: the shipped weights."""
    models: dict[str, Path | None] = {}
    for value in values or [SHIPPED]:
        label, sep, file = value.partition("=")
        if not sep or Path(value).exists():  # a file whose name holds "=" is a file
            label, file = (SHIPPED if value == SHIPPED else Path(value).stem), value
        if not label or not file:
            raise InputError("--model", f"{value!r}: give a model file, {SHIPPED} or LABEL=FILE")
        if label in models:
            raise InputError("--model", f"two models are labelled {label!r}; label them with LABEL=FILE")
        models[label] = None if file == SHIPPED else Path(file)
    return models


def _check_writable(path: Path) -> None:
    """Fail before the run, not after it, where ``path`` cannot be written (a probe file that did not
    exist is removed again, so that a run failing later leaves no empty output behind)."""
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


def _score(
    detectors: dict[str, Detector], data: list[Path], options: dict[str, Any]
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The summary of the run and its comparison rows: one detector's summary as ever (of one set or
    of several), or, of several detectors, their summaries by label and the comparison."""
    from fluoronav.detection.training.evaluate import (  # lazy: fast --help
        comparison_rows,
        evaluate,
        evaluate_models,
        evaluate_sets,
    )

    if len(detectors) > 1:
        summary = evaluate_models(detectors, data, **options)
        return summary, summary["comparison"]
    ((label, detector),) = detectors.items()
    summary = (
        evaluate(detector, data[0], **options) if len(data) == 1 else evaluate_sets(detector, data, **options)
    )
    return summary, comparison_rows({label: summary})


def _print_comparison(rows: list[dict[str, Any]]) -> None:
    """The comparison table (one row per data set and model) on stderr: stdout holds the JSON."""
    from fluoronav.detection.training.evaluate import COMPARISON_COLUMNS, comparison_table  # lazy

    # few borders: eleven columns fit a narrow terminal
    table = Table(title="detectors compared on the same images", box=box.SIMPLE_HEAD, padding=(0, 0))
    for i, col in enumerate(COMPARISON_COLUMNS):
        table.add_column(col, justify="left" if i < 2 else "right")
    for cells in comparison_table(rows):
        table.add_row(*cells)
    Console(stderr=True).print(table)


def evaluate_command(
    data: list[Path] = typer.Option(
        ...,
        "--data",
        help=(
            "Data set directory written by `fluoronav simulate`. Repeat it to score several sets: the "
            "summary then holds each set's figures and those of all their images pooled."
        ),
    ),
    model: list[str] = typer.Option(
        None,
        "--model",
        help=(
            f"Model file, or {SHIPPED} (the shipped weights, the default). Repeat it to compare models on "
            "the same images; each is labelled by its file's stem, or LABEL=FILE."
        ),
    ),
    out: Path | None = typer.Option(None, "--out", help="Write the summary JSON here."),
    markdown: Path | None = typer.Option(
        None, "--markdown", help="Write the comparison table (each set and model) here as Markdown."
    ),
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
    data sets (several: each set's figures and the pooled ones); of several detectors side by side."""
    from fluoronav.detection.detector import Detector  # lazy: fast --help
    from fluoronav.detection.training.evaluate import comparison_markdown  # lazy: fast --help

    if split not in ("train", "val", "all"):
        raise InputError("--split", f"unknown split {split!r}; use train, val or all")
    if field_frac is not None and not 0.0 < field_frac <= 1.0:
        raise InputError("--field-frac", f"must be in (0, 1], got {field_frac}")
    files = _model_files(model)
    for path in (out, per_sample, markdown):
        if path is not None:
            _check_writable(path)
    # each model is loaded once, all before the run
    detectors = {
        label: Detector.load(file, device=device, precision=precision) for label, file in files.items()
    }
    options: dict[str, Any] = {
        "split": split,
        "progress": progress,
        "field_frac": field_frac,
        "seed": seed,
        "per_sample": per_sample,
    }
    summary, rows = _score(detectors, data, options)
    text = json.dumps(summary, indent=1)
    if out is not None:
        out.write_text(text + "\n", encoding="utf-8")
    if markdown is not None:
        markdown.write_text(comparison_markdown(rows), encoding="utf-8")
    if len(detectors) > 1:
        _print_comparison(rows)
    typer.echo(text)


def register(app: typer.Typer) -> None:
    app.command("evaluate")(evaluate_command)
