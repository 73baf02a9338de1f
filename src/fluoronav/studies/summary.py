"""``summary.json`` of a study from its ``trials.csv`` rows."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from fluoronav import __version__

__all__ = ["summarize", "write_summary"]


def _stats(values: list[float]) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    return {
        "mean": float(a.mean()),
        "std": float(a.std(ddof=1)) if len(a) > 1 else 0.0,
        "median": float(np.median(a)),
        "p95": float(np.percentile(a, 95)),
        "n": len(a),
    }


def _float(v: Any) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def summarize(
    workflow: str,
    rows: list[dict[str, Any]],
    metric_names: list[str],
    *,
    trials: int,
    device: str,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Study summary (``summary.json``): counts, per-metric mean/std/median/p95 over converged trials, timing.

    Failed trials (``status`` "failed") and trials whose navigation refused to act (``status``
    "refused") are counted, never dropped; their metrics are left out of the statistics, and the
    failure and refusal rates and reasons are reported.
    """
    ok = [r for r in rows if str(r.get("status", "ok")) == "ok"]
    failed = [r for r in rows if str(r.get("status", "ok")) not in ("ok", "refused")]
    refused = [r for r in rows if str(r.get("status", "ok")) == "refused"]
    metrics: dict[str, Any] = {}
    for name in metric_names:
        vals = [v for v in (_float(r.get(name)) for r in ok) if v is not None]
        if vals:
            metrics[name] = _stats(vals)
    secs = [v for v in (_float(r.get("seconds")) for r in rows) if v is not None]

    def count(group: list[dict[str, Any]]) -> dict[str, int]:
        out: dict[str, int] = {}
        for r in group:
            key = str(r.get("reason", "unknown"))[:120]
            out[key] = out.get(key, 0) + 1
        return out

    out = {
        "workflow": workflow,
        "trials": trials,
        "completed": len(rows),
        "failed": len(failed),
        "failure_rate": len(failed) / len(rows) if rows else 0.0,
        "failure_reasons": count(failed),
        "refused": len(refused),
        "refusal_reasons": count(refused),
        "metrics": metrics,
        "seconds_per_trial": {
            "median": float(np.median(secs)) if secs else None,
            "p95": float(np.percentile(secs, 95)) if secs else None,
        },
        "device": device,
        "version": __version__,
    }
    if extra:
        out.update(extra)
    return out


def write_summary(path: Path, summary: dict[str, Any]) -> None:
    path.write_text(json.dumps(summary, indent=2), encoding="utf-8")
