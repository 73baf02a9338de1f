"""The DeepFluoro study in ``fluoronav report``: its table beside the published figures (light: no
torch, so that the report command stays quick)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

__all__ = ["ANCHORS", "WORKFLOW", "deepfluoro_table"]

WORKFLOW = "deepfluoro"
#: the published figures on the same data (only what was checked; see docs/real-data.md)
ANCHORS: dict[str, dict[str, Any]] = {
    "xReg (Grupp et al., IJCARS 15(5):759-769, 2020)": {
        "within_1deg": 0.86,
        "seconds": 7.0,
        "start": "landmarks found by a network, then intensity-based (GPU)",
        "images": 366,
    },
    "intensity-only, no manual initialisation (same paper)": {"within_1deg": 0.18, "images": 366},
    "DiffPose (Gopalakrishnan et al., CVPR 2024)": {
        "note": "mTRE computed with a spurious 0.194 mm/px factor, acknowledged by its maintainer "
        "(eigenvivek/DiffPose issue #27): not comparable in mm; figures not reproduced here",
    },
    "xvr (Gopalakrishnan et al., 2025)": {
        "note": "reports mTRE in 3D (mm) on this data; its figures were not checked for this page",
    },
}


def _percent(v: Any) -> str:
    return "–" if v is None else f"{100.0 * float(v):.0f} %"


def deepfluoro_table(study_dirs: list[Path]) -> tuple[list[str], list[list[Any]]]:
    """The DeepFluoro rows of ``fluoronav report``: each study (its ``summary.json``) and the
    :data:`ANCHORS` that give the same figures."""
    header = ["source", "images", "within 1°", "mTRE < 1 mm", "mTRE < 10 mm", "median rotation (°)"]
    header += ["median mTRE (mm)", "median s", "checks passed"]
    rows: list[list[Any]] = []
    for d in study_dirs:
        s = json.loads((Path(d) / "summary.json").read_text(encoding="utf-8"))
        m, w = s.get("metrics", {}), s.get("within_mtre_mm", {})
        rows.append(
            [
                f"fluoronav {s.get('version', '')} ({Path(d).name})",
                f"{s['completed'] - s['failed']}/{s['trials']}",
                _percent(s.get("within_1deg")),
                _percent(w.get("1")),
                _percent(w.get("10")),
                f"{m['rotation_deg']['median']:.3g}" if "rotation_deg" in m else "–",
                f"{m['mtre_mm']['median']:.3g}" if "mtre_mm" in m else "–",
                f"{s['seconds_per_trial']['median']:.3g}"
                if s.get("seconds_per_trial", {}).get("median")
                else "–",
                s.get("checks", {}).get("passed", "–"),
            ]
        )
    for name, a in ANCHORS.items():
        if "within_1deg" in a:
            secs = f"{a['seconds']:g} (GPU)" if "seconds" in a else "–"
            rows.append(
                [name, a.get("images", "–"), _percent(a["within_1deg"]), "–", "–", "–", "–", secs, "–"]
            )
    return header, rows
