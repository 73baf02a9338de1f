"""Evaluation metrics and the ``evaluate`` command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from det_synthetic import write_dataset
from test_det_detector import empty_net

from fluoronav.cli.main import main
from fluoronav.detection.detector import Detector
from fluoronav.detection.evaluate import dice_score, evaluate
from fluoronav.detection.train import save_model


def test_dice_score() -> None:
    a = np.zeros((10, 10), bool)
    b = a.copy()
    assert dice_score(a, b) == 1.0
    a[:5] = True
    b[:, :5] = True
    assert dice_score(a, b) == pytest.approx(2 * 25 / 100)


def test_evaluate_counts_found_and_false_positives(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "d", 8, size=48, seed=1, negative_every=4)
    summary = evaluate(Detector(empty_net(), device="cpu"), data, split="all", progress=False)
    assert summary["positives"] == 6 and summary["negatives"] == 2
    assert summary["found_rate"] == 0.0 and summary["false_positive_rate"] == 0.0
    assert summary["dice"]["mean"] == 0.0 and summary["landmark_px"]["mean"] is None

    model = tmp_path / "m.pt"
    save_model(model, empty_net(), extra={})
    out = tmp_path / "eval.json"
    main(
        [
            "evaluate",
            "--data",
            str(data),
            "--model",
            str(model),
            "--out",
            str(out),
            "--split",
            "all",
            "--device",
            "cpu",
            "--no-progress",
        ]
    )
    assert json.loads(out.read_text())["samples"] == 8


def test_evaluate_on_collimated_fields_crops_every_image_reproducibly(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "d", 6, size=96, seed=2, negative_every=3)
    images: list[np.ndarray] = []

    class Recording(Detector):
        def detect(self, image: np.ndarray, *, pixel_spacing_mm: float | None = None):  # type: ignore[no-untyped-def]
            images.append(image)
            return super().detect(image, pixel_spacing_mm=pixel_spacing_mm)

    det = Recording(empty_net(), device="cpu")
    summary = evaluate(det, data, split="all", progress=False, field_frac=0.5, seed=4)
    assert summary["field_frac"] == 0.5 and summary["seed"] == 4
    first = [im.copy() for im in images]
    # each side is half the image's unless the CM needs more; every crop is a part of the image
    assert all(im.shape[0] < 96 and im.shape[1] < 96 for im in first)
    assert sum(im.shape == (48, 48) for im in first) >= 3
    images.clear()
    evaluate(det, data, split="all", progress=False, field_frac=0.5, seed=4)
    assert all(np.array_equal(a, b) for a, b in zip(first, images, strict=True))
    images.clear()
    evaluate(det, data, split="all", progress=False, field_frac=0.5, seed=5)
    assert not all(np.array_equal(a, b) for a, b in zip(first, images, strict=True))
    with pytest.raises(SystemExit) as exc:
        main(["evaluate", "--data", str(data), "--field-frac", "1.5", "--no-progress"])
    assert exc.value.code != 0
