"""Checks of a simulated data set against its contract (docs/data-formats.md): the manifest, the
samples' files and labels, the cameras."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from fluoronav.geometry.camera import Camera
from fluoronav.runner import JsonlLog

__all__ = ["MANIFEST_KEYS", "check_dataset"]


#: manifest keys every sample has (docs/simulation.md, "Data set format")
MANIFEST_KEYS = (
    "id",
    "file",
    "rows",
    "cols",
    "pixel_spacing_mm",
    "landmarks_px",
    "control_points_deg",
    "camera",
    "world_from_cm",
    "ct",
)


def _camera_problems(row: dict[str, Any], rows: int, cols: int, sdd_mm: float | None) -> list[str]:
    """A manifest row's camera against its size and the detector (none for a transposed sample's)."""
    if row["camera"] is None and (row.get("variation") or {}).get("image", {}).get("transpose"):
        return []
    cam = Camera.from_dict(row["camera"])
    problems = []
    if (cam.rows, cam.cols) != (rows, cols):
        problems.append("camera size differs from rows/cols")
    if sdd_mm is not None and not np.isclose(cam.K[0, 0], sdd_mm / row["pixel_spacing_mm"], rtol=1e-6):
        problems.append("fx != sdd / pixel_spacing_mm")
    return problems


def _flagged_out(row: dict[str, Any]) -> np.ndarray:
    """(2,) bool: the landmarks a partial field of view put outside the image on purpose."""
    inside = (row.get("variation") or {}).get("image", {}).get("landmarks_in_image")
    return np.zeros(2, bool) if inside is None else ~np.asarray(inside, bool)


def check_dataset(data_dir: Path, *, n: int | None = None) -> list[str]:
    """Problems of a data set against the contract (empty list = conforms).

    Checks: manifest keys, ids 0..n−1 exactly once, npz keys/dtypes/shapes at (rows, cols), the
    camera's size and ``fx = sdd / pixel_spacing`` consistent with the row (a transposed sample has
    no camera), landmarks inside the image (but those a partial field of view flags as outside) and
    equal to the npz's, empty mask and no landmarks for negatives.
    """
    data_dir = Path(data_dir)
    problems: list[str] = []
    rows_ = JsonlLog(data_dir / "manifest.jsonl").read()
    ids = sorted(int(r.get("id", -1)) for r in rows_)
    if n is not None and ids != list(range(n)):
        problems.append(f"manifest ids are not 0..{n - 1} exactly once")
    sdd = None
    meta = data_dir / "dataset.json"
    if meta.exists():
        sdd = json.loads(meta.read_text(encoding="utf-8")).get("sdd_mm")
    for r in rows_:
        tag = f"sample {r.get('id')}"
        missing = [k for k in MANIFEST_KEYS if k not in r]
        if missing:
            problems.append(f"{tag}: missing {missing}")
            continue
        h, w = int(r["rows"]), int(r["cols"])
        problems += [f"{tag}: {p}" for p in _camera_problems(r, h, w, sdd)]
        with np.load(data_dir / r["file"]) as z:
            keys = set(z.files)
            if not {"image", "mask", "landmarks_px"} <= keys:
                problems.append(f"{tag}: npz lacks image/mask/landmarks_px")
                continue
            img, mask, lm = z["image"], z["mask"], z["landmarks_px"]
        if img.dtype != np.float32 or img.shape != (h, w) or not np.all(np.isfinite(img)):
            problems.append(f"{tag}: image must be finite float32 ({h}, {w})")
        if mask.dtype != np.uint8 or mask.shape != (h, w) or not set(np.unique(mask)) <= {0, 1}:
            problems.append(f"{tag}: mask must be uint8 0/1 ({h}, {w})")
        if r["landmarks_px"] is None:
            if mask.any() or not np.all(np.isnan(lm)):
                problems.append(f"{tag}: a negative has mask pixels or landmarks")
            continue
        lm_row = np.asarray(r["landmarks_px"], dtype=np.float64)
        if lm_row.shape != (2, 2) or not np.allclose(lm_row, lm):
            problems.append(f"{tag}: landmarks_px differ between manifest and npz")
        elif not np.all(
            ((lm_row >= -0.5) & (lm_row <= np.array([w, h]) - 0.5)).all(axis=1) | _flagged_out(r)
        ):
            problems.append(f"{tag}: landmarks outside the image")
        if not mask.any():
            problems.append(f"{tag}: a positive has an empty mask")
    return problems
