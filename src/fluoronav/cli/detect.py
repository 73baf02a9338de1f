"""``fluoronav detect``: CM mask, landmarks and centreline of X-ray images."""

from __future__ import annotations

from pathlib import Path

import typer

from fluoronav.cli.common import DEVICE_OPTION, PRECISION_OPTION


def detect_command(
    images: list[Path] = typer.Argument(..., help="Images: .npz (key image), .npy, PNG/TIFF, DICOM."),
    out: Path = typer.Option(..., "--out", help="Output directory (<stem>.json and <stem>_mask.png)."),
    model: Path | None = typer.Option(
        None, "--model", help="Model file from `fluoronav train` (default: the shipped weights)."
    ),
    device: str = DEVICE_OPTION,
    precision: str = PRECISION_OPTION,
) -> None:
    """Detect the CM in each image and write the detection files."""
    from fluoronav.detection.detector import Detector, load_image, write_detection  # lazy: fast --help

    detector = Detector.load(model, device=device, precision=precision)
    for path in images:
        image, spacing = load_image(path)
        det = detector.detect(image, pixel_spacing_mm=spacing)
        json_path = write_detection(det, out, path.stem)
        conf = ", ".join(f"{c:.2f}" for c in det.landmark_confidence)
        state = "found" if det.found else "no CM"
        if det.found and not det.usable:
            state += f"; {det.unusable_reason}"
        typer.echo(f"{path}: {state} (confidence {conf}) -> {json_path}")


def register(app: typer.Typer) -> None:
    app.command("detect")(detect_command)
