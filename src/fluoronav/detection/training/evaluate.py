"""Accuracy of a detector on a simulate data set (held-out split or all samples).

Metrics: Dice of the mask at the input resolution (positives), landmark error in pixels and in mm at
the detector (``pixel_spacing_mm`` of each manifest record), the found rate on positives and the
false-positive rate on negatives. With ``field_frac`` each image is first cropped to a collimated
field of that fraction of its sides (a random place that keeps the whole CM; seeded per sample).
The summary splits the positives by how long the CM and its mounting shaft project and by what the
view shows of the CM (:func:`view_kind`: nearly end-on, over its own shaft, or clear), the views
that hold most gross landmark errors; ``per_sample`` writes one JSON line per scored image.
:func:`evaluate_models` scores several detectors on the same images and tabulates them side by side.
docs/detector.md ("What ``evaluate`` reports") lists every figure.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np
from tqdm import tqdm

from fluoronav.detection.detector import Detector
from fluoronav.detection.training.dataset import (
    Sample,
    collimate,
    load_sample,
    read_manifest,
    shaft_length_of,
    shaft_segment_px,
    split_of,
)
from fluoronav.manipulator.projection import angle_between_deg

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


#: upper edges (mm, true A–B distance on the detector) of the foreshortening classes of the summary:
#: nearly end-on, the paper's shortest quarter (< 33 mm), mid, and the rest
AB_CLASS_EDGES_MM = (17.0, 33.0, 50.0, math.inf)

#: a landmark further than this from the truth is counted as a gross error in the summary
GROSS_ERROR_MM = 3.0


#: upper edges (mm, projected length of the CM's mounting shaft on the detector) of the shaft classes
#: of the summary: a stub seen nearly along its axis (where the detector can take the stub for part of
#: the CM), short, and the rest (the 50 mm shaft across the view projects ~110 mm)
SHAFT_CLASS_EDGES_MM = (30.0, 60.0, math.inf)


#: a CM whose true A–B distance on the detector is under this (mm) is seen nearly end-on (the first
#: foreshortening class)
END_ON_MAX_AB_MM = AB_CLASS_EDGES_MM[0]

#: a CM whose chord A → B on the detector lies within this angle (degrees) of its projected mounting
#: shaft (A → the shaft's far end) lies over its own shaft in the image
OVER_SHAFT_MAX_DEG = 35.0

#: the view classes of the summary, in its order (:func:`view_kind`)
VIEW_KINDS = ("clear", "end-on", "over-shaft")

#: upper edges (degrees, :func:`shaft_angle_deg`) of the shaft-angle classes of the summary: the CM
#: over its shaft, a V of the two at A, a wide V, and the shaft going on behind the CM
SHAFT_ANGLE_CLASS_EDGES_DEG = (OVER_SHAFT_MAX_DEG, 55.0, 90.0, math.inf)


#: upper edges of the landmark-confidence classes of the summary: each found landmark by its own
#: confidence (the heatmap's peak mass; unsure, middling, sure)
CONFIDENCE_CLASS_EDGES = (0.2, 0.4, math.inf)


def projected_shaft_mm(record: dict[str, Any], shaft_length_mm: float) -> float | None:
    """Length (mm at the detector plane) of the projected mounting shaft of a manifest record.

    The shaft runs from the base origin A to ``shaft_length_mm`` behind it along −z of the CM's frame
    (:func:`~fluoronav.detection.training.dataset.shaft_segment_px`). None where the record lacks the camera,
    the pose ``world_from_cm`` or the pixel spacing, or ``shaft_length_mm`` is not positive.
    """
    segment = shaft_segment_px(record, shaft_length_mm)
    spacing_mm = record.get("camera", {}).get("pixel_spacing_mm") if segment is not None else None
    if segment is None or not isinstance(spacing_mm, (int, float)):
        return None
    return float(np.linalg.norm(segment[1] - segment[0]) * spacing_mm)


def shaft_angle_deg(record: dict[str, Any], landmarks_px: np.ndarray, shaft_length_mm: float) -> float | None:
    """Angle (degrees, 0–180) at A between the CM's chord A → B and its projected mounting shaft (A →
    the shaft's far end, :func:`~fluoronav.detection.training.dataset.shaft_segment_px`) on the detector, for
    the true landmarks (2, 2) (u, v) stored px of a manifest record: near 180 where the shaft goes on
    behind the CM, small where the CM lies over it. None where the shaft is unknown or either segment
    has no length."""
    segment = shaft_segment_px(record, shaft_length_mm)
    if segment is None:
        return None
    lm = np.asarray(landmarks_px, dtype=np.float64)
    angle = angle_between_deg(lm[1] - lm[0], segment[1] - segment[0])
    return None if math.isnan(angle) else angle


def view_kind(ab_mm: float | None, shaft_angle: float | None) -> str | None:
    """What a positive view shows of the CM, from its truth: ``end-on`` (true A–B distance on the
    detector under :data:`END_ON_MAX_AB_MM`), ``over-shaft`` (its chord within
    :data:`OVER_SHAFT_MAX_DEG` of its projected shaft), else ``clear``; None without the A–B distance
    in mm. A view whose shaft is unknown (``shaft_angle`` None) is not taken as over its shaft."""
    if ab_mm is None:
        return None
    if ab_mm < END_ON_MAX_AB_MM:
        return "end-on"
    if shaft_angle is not None and shaft_angle < OVER_SHAFT_MAX_DEG:
        return "over-shaft"
    return "clear"


def _confidence_classes(rows: list[dict[str, Any]], edges: tuple[float, ...]) -> list[dict[str, Any]]:
    """The found landmarks of the positives (rows of :func:`evaluate`'s per-sample records) grouped
    by their own confidence into ``[0, edges[0]), [edges[0], edges[1]), …``: how far off a landmark
    of that confidence is (mm at the detector)."""
    pairs = [
        (c, e)
        for r in rows
        if r["found"] and r["landmark_mm"] is not None
        for c, e in zip(r["confidence"], r["landmark_mm"], strict=True)
    ]
    out = []
    lo = 0.0
    for hi in edges:
        errs = [e for c, e in pairs if lo <= c < hi]
        out.append(
            {
                "confidence": [lo, None if math.isinf(hi) else hi],
                "landmarks": len(errs),
                "landmark_mm_mean": float(np.mean(errs)) if errs else None,
                "landmark_mm_median": float(np.median(errs)) if errs else None,
                "landmark_gross": sum(e > GROSS_ERROR_MM for e in errs),
            }
        )
        lo = hi
    return out


def _classes(rows: list[dict[str, Any]], key: str, edges: tuple[float, ...]) -> list[dict[str, Any]]:
    """Positives grouped by ``row[key]`` into ``[0, edges[0]), [edges[0], edges[1]), …`` (rows of
    :func:`evaluate`'s per-sample records; rows whose ``key`` is None are left out)."""
    out = []
    lo = 0.0
    for hi in edges:
        sel = [r for r in rows if r.get(key) is not None and lo <= r[key] < hi]
        out.append({key: [lo, None if math.isinf(hi) else hi]} | _group(sel))
        lo = hi
    return out


def _group(sel: list[dict[str, Any]]) -> dict[str, Any]:
    """Dice, found rate and landmark figures (mm at the detector) of a group of positives (rows of
    :func:`evaluate`'s per-sample records)."""
    found = [r for r in sel if r["found"]]
    errs = [e for r in found if r["landmark_mm"] is not None for e in r["landmark_mm"]]
    return {
        "positives": len(sel),
        "dice_mean": float(np.mean([r["dice"] for r in sel])) if sel else None,
        "found_rate": len(found) / len(sel) if sel else None,
        "landmark_mm_mean": float(np.mean(errs)) if errs else None,
        "landmark_mm_median": float(np.median(errs)) if errs else None,
        "landmark_gross": sum(e > GROSS_ERROR_MM for e in errs),
    }


def _row(
    detector: Detector, s: Sample, rec: dict[str, Any], shaft_length_mm: float, tag: dict[str, Any] | None
) -> dict[str, Any]:
    """The record of one image ``s`` (manifest record ``rec``) scored by ``detector`` (see
    :func:`evaluate`), ``tag``'s items first."""
    t0 = time.perf_counter()
    det = detector.detect(s.image, pixel_spacing_mm=s.pixel_spacing_mm)
    seconds = time.perf_counter() - t0
    sp = s.pixel_spacing_mm
    row: dict[str, Any] = dict(tag or {}) | {
        "id": s.id,
        "positive": s.landmarks_px is not None,
        "found": bool(det.found),
        "usable": det.usable,
        "confidence": [float(c) for c in det.landmark_confidence],
        "detect_ms": 1e3 * seconds,
    }
    if s.landmarks_px is not None:
        dice = dice_score(det.mask, s.mask) if det.found else 0.0
        ab_px = float(np.linalg.norm(s.landmarks_px[1] - s.landmarks_px[0]))
        row |= {"dice": dice, "ab_px": ab_px, "ab_mm": None if sp is None else ab_px * sp}
        row["shaft_mm"] = projected_shaft_mm(rec, shaft_length_mm)
        row["shaft_angle_deg"] = shaft_angle_deg(rec, s.landmarks_px, shaft_length_mm)
        row["view"] = view_kind(row["ab_mm"], row["shaft_angle_deg"])
        row |= {"landmark_px": None, "landmark_mm": None}
        if det.found and det.landmarks_px is not None:
            e = np.linalg.norm(det.landmarks_px - s.landmarks_px, axis=1)
            row["landmark_px"] = e.tolist()
            if sp is not None:
                row["landmark_mm"] = (e * sp).tolist()
    return row


def _score(
    detectors: Sequence[Detector],
    data_dir: str | Path,
    *,
    split: str,
    val_fraction: float,
    progress: bool,
    field_frac: float | None,
    seed: int,
    sink: TextIO | None,
    tags: Sequence[dict[str, Any] | None],
) -> list[list[dict[str, Any]]]:
    """One record per image of ``split`` (see :func:`evaluate`) for each detector (each image is read
    and cropped once and handed to every detector in turn), each also written to ``sink`` with its
    detector's ``tags`` items first as it is scored."""
    records = read_manifest(data_dir)
    shaft_length_mm = shaft_length_of(data_dir)
    if split != "all":
        records = [r for r in records if split_of(str(r["id"]), val_fraction) == split]
    rows: list[list[dict[str, Any]]] = [[] for _ in detectors]
    for i, rec in enumerate(tqdm(records, desc="evaluate", disable=not progress)):
        s = load_sample(data_dir, rec)
        if field_frac is not None:
            rng = np.random.default_rng([seed, i])
            s = collimate(s, rng, min_field_frac=field_frac, max_field_frac=field_frac)
        for detector, tag, out in zip(detectors, tags, rows, strict=True):
            row = _row(detector, s, rec, shaft_length_mm, tag)
            out.append(row)
            if sink is not None:
                sink.write(json.dumps(row) + "\n")
                sink.flush()
    return rows


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The accuracy figures of :func:`evaluate` from its per-image records (``positives`` …
    ``detect_ms``): records of several data sets pool into one summary."""
    positives = [r for r in rows if r["positive"]]
    negatives = [r for r in rows if not r["positive"]]
    found = [r for r in positives if r["landmark_px"] is not None]
    err_px = [e for r in found for e in r["landmark_px"]]
    err_mm = [e for r in found if r["landmark_mm"] is not None for e in r["landmark_mm"]]
    return {
        "positives": len(positives),
        "negatives": len(negatives),
        "dice": _stats([r["dice"] for r in positives]),
        "landmark_px": _stats(err_px),
        "landmark_mm": _stats(err_mm),
        "landmark_gross": {
            "threshold_mm": GROSS_ERROR_MM,
            "count": int(np.sum(np.asarray(err_mm) > GROSS_ERROR_MM)),
            "of": len(err_mm),
        },
        "landmark_gross_rate": (
            int(np.sum(np.asarray(err_mm) > GROSS_ERROR_MM)) / len(err_mm) if err_mm else None
        ),
        "by_projected_ab": _classes(positives, "ab_mm", AB_CLASS_EDGES_MM),
        "by_projected_shaft": _classes(positives, "shaft_mm", SHAFT_CLASS_EDGES_MM),
        "by_landmark_confidence": _confidence_classes(positives, CONFIDENCE_CLASS_EDGES),
        "by_view": [{"view": k} | _group([r for r in positives if r["view"] == k]) for k in VIEW_KINDS],
        "by_shaft_angle": _classes(positives, "shaft_angle_deg", SHAFT_ANGLE_CLASS_EDGES_DEG),
        "found_rate": len(found) / len(positives) if positives else None,
        "false_positive_rate": sum(r["found"] for r in negatives) / len(negatives) if negatives else None,
        "detect_ms": _stats([r["detect_ms"] for r in rows]),
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
    per_sample: str | Path | None = None,
) -> dict:
    """Run the detector on every sample of ``split`` (``train``/``val``/``all``) and summarise.

    ``field_frac`` in (0, 1]: crop each sample to a field of that fraction of its rows and columns
    first (None: whole images); the place of the ``i``-th sample's field (in manifest order) comes from
    ``Generator([seed, i])``.

    The landmark error is the Euclidean distance per landmark (A and B pooled) on positives where the
    CM was found; Dice is computed on every positive (0 where nothing was found).

    ``per_sample``: a JSON Lines file written as the images are scored (overwritten), one record per
    image: ``id``, ``positive``, ``found``, ``usable`` (:attr:`Detection.usable`), ``confidence``
    (A, B), ``detect_ms`` and, on positives, ``dice``, ``ab_px`` / ``ab_mm`` (the true projected A–B
    distance), ``shaft_mm`` (the true projected length of the mounting shaft, :func:`projected_shaft_mm`;
    None where unknown), ``shaft_angle_deg`` (:func:`shaft_angle_deg`; None where unknown), ``view``
    (:func:`view_kind`) and, where found, ``landmark_px`` / ``landmark_mm`` (A, B errors). mm values
    are None where the record has no pixel spacing.
    """
    summaries = evaluate_sets(
        detector,
        [data_dir],
        split=split,
        val_fraction=val_fraction,
        progress=progress,
        field_frac=field_frac,
        seed=seed,
        per_sample=per_sample,
    )
    return summaries["sets"][0]


def evaluate_sets(
    detector: Detector,
    data_dirs: Sequence[str | Path],
    *,
    split: str = "val",
    val_fraction: float = 1 / 11,
    progress: bool = True,
    field_frac: float | None = None,
    seed: int = 0,
    per_sample: str | Path | None = None,
) -> dict[str, Any]:
    """:func:`evaluate` on each of several data sets in turn, and on all their images pooled.

    Returns ``{"sets": [summary of each set, as evaluate], "pooled": summary}``; the pooled summary
    has ``data`` (the list of sets) and the figures of :func:`summarize` over every image. With
    several sets each ``per_sample`` record starts with ``data`` (its set's directory); with one set
    the records are :func:`evaluate`'s. ``field_frac`` fields are placed per set, as evaluate places
    them.
    """
    results = _evaluate(
        {"": detector},
        data_dirs,
        split=split,
        val_fraction=val_fraction,
        progress=progress,
        field_frac=field_frac,
        seed=seed,
        per_sample=per_sample,
        tag_models=False,
    )
    return results[""]


def evaluate_models(
    detectors: Mapping[str, Detector],
    data_dirs: Sequence[str | Path],
    *,
    split: str = "val",
    val_fraction: float = 1 / 11,
    progress: bool = True,
    field_frac: float | None = None,
    seed: int = 0,
    per_sample: str | Path | None = None,
) -> dict[str, Any]:
    """Several detectors, each under its label, scored on the same images of one or more data sets
    (each image read and cropped once): old and new models compared in one run.

    Returns ``{"models": {label: summary}, "comparison": rows}``: each summary is what
    :func:`evaluate` (one set) or :func:`evaluate_sets` (several) gives for that detector alone, and
    ``rows`` are :func:`comparison_rows` of them. Each ``per_sample`` record starts with ``model``
    (its detector's label), then is as :func:`evaluate_sets` writes it.
    """
    results = _evaluate(
        detectors,
        data_dirs,
        split=split,
        val_fraction=val_fraction,
        progress=progress,
        field_frac=field_frac,
        seed=seed,
        per_sample=per_sample,
        tag_models=True,
    )
    models = {label: r if len(data_dirs) > 1 else r["sets"][0] for label, r in results.items()}
    return {"models": models, "comparison": comparison_rows(models)}


def _evaluate(
    detectors: Mapping[str, Detector],
    data_dirs: Sequence[str | Path],
    *,
    split: str,
    val_fraction: float,
    progress: bool,
    field_frac: float | None,
    seed: int,
    per_sample: str | Path | None,
    tag_models: bool,
) -> dict[str, dict[str, Any]]:
    """:func:`evaluate_sets` of each labelled detector on the same images: ``{label: {"sets": …,
    "pooled": …}}``; with ``tag_models`` each ``per_sample`` record starts with ``model`` (its label)."""
    if field_frac is not None and not 0.0 < field_frac <= 1.0:
        raise ValueError(f"field_frac must be in (0, 1], got {field_frac}")
    if not data_dirs:
        raise ValueError("no data set to evaluate")
    if not detectors:
        raise ValueError("no detector to evaluate")
    metas: dict[str, dict[str, Any]] = {
        label: {
            "field_frac": field_frac,
            "seed": seed if field_frac is not None else None,
            "model": detector.source,
            "precision": detector.precision,
        }
        for label, detector in detectors.items()
    }
    sink = None
    if per_sample is not None:
        Path(per_sample).parent.mkdir(parents=True, exist_ok=True)
        sink = open(per_sample, "w", encoding="utf-8")  # noqa: SIM115 (closed in the finally below)
    sets: dict[str, list[dict[str, Any]]] = {label: [] for label in detectors}
    everything: dict[str, list[dict[str, Any]]] = {label: [] for label in detectors}
    try:
        for data_dir in data_dirs:
            tag = {"data": str(data_dir)} if len(data_dirs) > 1 else {}
            rows = _score(
                list(detectors.values()),
                data_dir,
                split=split,
                val_fraction=val_fraction,
                progress=progress,
                field_frac=field_frac,
                seed=seed,
                sink=sink,
                tags=[({"model": label} if tag_models else {}) | tag for label in detectors],
            )
            for label, model_rows in zip(detectors, rows, strict=True):
                everything[label].extend(model_rows)
                head = {"data": str(data_dir), "split": split, "samples": len(model_rows)}
                sets[label].append(head | summarize(model_rows) | metas[label])
    finally:
        if sink is not None:
            sink.close()
    results = {}
    for label, every in everything.items():
        pooled: dict[str, Any] = {"data": [str(d) for d in data_dirs], "split": split, "samples": len(every)}
        results[label] = {"sets": sets[label], "pooled": pooled | summarize(every) | metas[label]}
    return results


#: the columns of the comparison table (:func:`comparison_table`, :func:`comparison_markdown`)
COMPARISON_COLUMNS = (
    "data set",
    "model",
    "positives",
    "negatives",
    "found",
    "false positives",
    f"gross > {GROSS_ERROR_MM:g} mm",
    "gross rate",
    "median mm",
    "p95 mm",
    "Dice",
)


def _comparison_row(label: str, summary: dict[str, Any]) -> dict[str, Any]:
    """The row of :func:`comparison_rows` of one model's summary of one set (or of the pooled sets)."""
    gross = summary["landmark_gross"]
    return {
        "data": summary["data"] if isinstance(summary["data"], str) else "pooled",
        "model": label,
        "samples": summary["samples"],
        "positives": summary["positives"],
        "negatives": summary["negatives"],
        "found_rate": summary["found_rate"],
        "false_positive_rate": summary["false_positive_rate"],
        "landmark_gross": gross["count"],
        "landmarks": gross["of"],
        "landmark_gross_rate": gross["count"] / gross["of"] if gross["of"] else None,
        "landmark_mm_median": summary["landmark_mm"]["median"],
        "landmark_mm_p95": summary["landmark_mm"]["p95"],
        "dice_mean": summary["dice"]["mean"],
    }


def comparison_rows(models: Mapping[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The figures a reader compares across models: one row per data set and model, set by set (the
    pooled sets last, ``data`` "pooled", where the summaries hold several sets), the models in order.

    ``models``: each label's summary, as :func:`evaluate` or :func:`evaluate_sets` gives it (all of
    the same sets). A row holds ``data``, ``model``, ``samples``, ``positives``, ``negatives``,
    ``found_rate``, ``false_positive_rate``, ``landmark_gross`` (count) of ``landmarks`` (scored),
    ``landmark_gross_rate``, ``landmark_mm_median``, ``landmark_mm_p95`` and ``dice_mean``.
    """
    per_model = {
        label: [s] if "sets" not in s else [*s["sets"], s["pooled"]] if len(s["sets"]) > 1 else s["sets"]
        for label, s in models.items()
    }
    counts = {len(summaries) for summaries in per_model.values()}
    if len(counts) > 1:
        raise ValueError("the models' summaries are of different data sets")
    return [
        _comparison_row(label, summaries[i])
        for i in range(counts.pop() if counts else 0)
        for label, summaries in per_model.items()
    ]


def comparison_table(rows: Sequence[dict[str, Any]]) -> list[list[str]]:
    """The cells of :func:`comparison_rows` under :data:`COMPARISON_COLUMNS`: rates in %, landmark
    errors in mm, each data set named by its path below the folder all the sets share."""

    def pct(x: float | None, digits: int = 1) -> str:
        return "n/a" if x is None else f"{100 * x:.{digits}f}%"

    def num(x: float | None, digits: int) -> str:
        return "n/a" if x is None else f"{x:.{digits}f}"

    dirs = sorted({os.path.abspath(r["data"]) for r in rows if r["data"] != "pooled"})
    top = os.path.commonpath(dirs) if len(dirs) > 1 else os.path.dirname(dirs[0]) if dirs else ""
    return [
        [
            "pooled" if row["data"] == "pooled" else os.path.relpath(os.path.abspath(row["data"]), top),
            str(row["model"]),
            str(row["positives"]),
            str(row["negatives"]),
            pct(row["found_rate"]),
            pct(row["false_positive_rate"]),
            f"{row['landmark_gross']}/{row['landmarks']}",
            pct(row["landmark_gross_rate"], 2),
            num(row["landmark_mm_median"], 2),
            num(row["landmark_mm_p95"], 2),
            num(row["dice_mean"], 3),
        ]
        for row in rows
    ]


def comparison_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """A Markdown table of :func:`comparison_rows` (one line per data set and model)."""
    lines = [
        "| " + " | ".join(COMPARISON_COLUMNS) + " |",
        "|" + "|".join(["---", "---"] + ["---:"] * (len(COMPARISON_COLUMNS) - 2)) + "|",
    ]
    for cells in comparison_table(rows):
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join(lines) + "\n"
