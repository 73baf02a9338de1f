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
