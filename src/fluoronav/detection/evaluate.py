"""Accuracy of a detector on a simulate data set (held-out split or all samples).

Metrics: Dice of the mask at the input resolution (positives), landmark error in pixels and in mm at
the detector plane (``pixel_spacing_mm`` of each manifest record), the found rate on positives and
the false-positive rate on negatives. With ``field_frac`` each image is first cropped to a collimated
field of that fraction of its sides (at a random place that keeps the whole CM; seeded per sample):
real fluoroscopy is often collimated, and then the image has no air around the body.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from fluoronav.detection.dataset import collimate, load_sample, read_manifest, split_of
from fluoronav.detection.detector import Detector

logger = logging.getLogger(__name__)


def dice_score(pred: np.ndarray, true: np.ndarray) -> float:
    """Dice of two boolean masks (1.0 when both are empty)."""
    p, t = np.asarray(pred, bool), np.asarray(true, bool)
    den = int(p.sum()) + int(t.sum())
    return 1.0 if den == 0 else 2.0 * float(np.logical_and(p, t).sum()) / den


def _stats(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"mean": None, "std": None, "median": None, "p95": None}
    a = np.asarray(values, dtype=np.float64)
    return {
        "mean": float(a.mean()),
        "std": float(a.std()),
        "median": float(np.median(a)),
        "p95": float(np.percentile(a, 95)),
    }


def evaluate(
    detector: Detector,
    data_dir: str | Path,
    *,
    split: str = "val",
    val_fraction: float = 1 / 11,
    progress: bool = True,
    field_frac: float | None = None,
    seed: int = 0,
) -> dict:
    """Run the detector on every sample of ``split`` (``train``/``val``/``all``) and summarise.

    ``field_frac`` in (0, 1]: crop each sample to a field of that fraction of its rows and columns
    first (None: whole images); the place of the ``i``-th sample's field (in manifest order) comes from
    ``Generator([seed, i])``.

    The landmark error is the Euclidean distance per landmark (A and B pooled) on positives where the
    CM was found; Dice is computed on every positive (0 where nothing was found).
    """
    if field_frac is not None and not 0.0 < field_frac <= 1.0:
        raise ValueError(f"field_frac must be in (0, 1], got {field_frac}")
    records = read_manifest(data_dir)
    if split != "all":
        records = [r for r in records if split_of(str(r["id"]), val_fraction) == split]
    dices, err_px, err_mm, seconds = [], [], [], []
    n_pos = n_neg = found_pos = found_neg = 0
    for i, rec in enumerate(tqdm(records, desc="evaluate", disable=not progress)):
        s = load_sample(data_dir, rec)
        if field_frac is not None:
            rng = np.random.default_rng([seed, i])
            s = collimate(s, rng, min_field_frac=field_frac, max_field_frac=field_frac)
        t0 = time.perf_counter()
        det = detector.detect(s.image, pixel_spacing_mm=s.pixel_spacing_mm)
        seconds.append(time.perf_counter() - t0)
        if s.landmarks_px is None:
            n_neg += 1
            found_neg += int(det.found)
            continue
        n_pos += 1
        dices.append(dice_score(det.mask, s.mask) if det.found else 0.0)
        if det.found and det.landmarks_px is not None:
            found_pos += 1
            e = np.linalg.norm(det.landmarks_px - s.landmarks_px, axis=1)
            err_px.extend(e.tolist())
            if s.pixel_spacing_mm is not None:
                err_mm.extend((e * s.pixel_spacing_mm).tolist())
    return {
        "data": str(data_dir),
        "split": split,
        "samples": len(records),
        "positives": n_pos,
        "negatives": n_neg,
        "dice": _stats(dices),
        "landmark_px": _stats(err_px),
        "landmark_mm": _stats(err_mm),
        "found_rate": found_pos / n_pos if n_pos else None,
        "false_positive_rate": found_neg / n_neg if n_neg else None,
        "detect_ms": _stats([1e3 * x for x in seconds]),
        "field_frac": field_frac,
        "seed": seed if field_frac is not None else None,
        "model": detector.source,
    }
