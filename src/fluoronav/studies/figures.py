"""The paper's study plots: error histograms (Fig. 10), per-axis box plots, tip vs depth error (Fig. 13)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["column", "study_figures"]

_LABELS = {
    "tip_mm": "CM tip error (mm)",
    "entry_mm": "femur entry point error (mm)",
    "relative_mm": "entry − tip relative error (mm)",
    "base_translation_mm": "CM base translation error (mm)",
    "base_rotation_deg": "CM base rotation error (°)",
    "notch_rotation_deg": "mean notch rotation error (°)",
    "depth_mm": "depth d_A error (mm)",
    "theta_deg": "θ error (°)",
    "handeye_translation_mm": "hand-eye translation error (mm)",
    "handeye_rotation_deg": "hand-eye rotation error (°)",
    "handeye_tip_mm": "hand-eye tip error (mm)",
    "reposition_tip_mm": "repositioning tip error (mm)",
}


def column(rows: list[dict[str, Any]], key: str) -> np.ndarray:
    out = []
    for r in rows:
        try:
            v = float(r.get(key, "nan"))
        except (TypeError, ValueError):
            v = math.nan
        out.append(v)
    a = np.asarray(out)
    return a[np.isfinite(a)]


def study_figures(rows: list[dict[str, Any]], out_dir: Path, *, workflow: str) -> list[Path]:
    """Write the study's PNG figures into ``out_dir``; returns their paths."""
    import matplotlib  # heavy: matplotlib, for the figures only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after use("Agg")

    out_dir.mkdir(parents=True, exist_ok=True)
    ok = [r for r in rows if str(r.get("status", "ok")) == "ok"]
    written: list[Path] = []
    keys = [k for k in _LABELS if len(column(ok, k))]
    if keys:
        n = len(keys)
        cols = min(3, n)
        nrows = (n + cols - 1) // cols
        fig, axes = plt.subplots(nrows, cols, figsize=(4.2 * cols, 3.2 * nrows), squeeze=False)
        for ax in axes.flat:
            ax.axis("off")
        for ax, k in zip(axes.flat, keys, strict=False):
            v = column(ok, k)
            ax.axis("on")
            ax.hist(v, bins=min(30, max(5, len(v) // 3)), color="steelblue", edgecolor="white")
            ax.axvline(float(np.mean(v)), color="crimson", linestyle="--", label=f"mean {np.mean(v):.2f}")
            ax.set_xlabel(_LABELS[k])
            ax.set_ylabel("trials")
            ax.legend(fontsize=8)
        fig.suptitle(f"{workflow}: error histograms (n = {len(ok)})")
        fig.tight_layout()
        p = out_dir / "error_histograms.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        written.append(p)
    axis_keys = [("base_tx_mm", "base_ty_mm", "base_tz_mm"), ("base_rx_deg", "base_ry_deg", "base_rz_deg")]
    if all(len(column(ok, k)) for k in axis_keys[0]):
        fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
        for ax, ks, unit in zip(axes, axis_keys, ("mm", "°"), strict=True):
            ax.boxplot([column(ok, k) for k in ks], showfliers=True)
            ax.set_xticks([1, 2, 3], ["X", "Y", "Z"])
            ax.axhline(0.0, color="grey", linewidth=0.5)
            ax.set_ylabel(f"CM base {'translation' if unit == 'mm' else 'rotation'} error ({unit})")
        fig.suptitle(f"{workflow}: per-axis CM base errors in the CM base frame")
        fig.tight_layout()
        p = out_dir / "per_axis_boxplots.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        written.append(p)
    tip, depth = column(ok, "tip_mm"), column(ok, "base_depth_mm")
    if len(tip) >= 3 and len(tip) == len(depth):
        r = float(np.corrcoef(tip, depth)[0, 1]) if np.std(tip) > 0 and np.std(depth) > 0 else float("nan")
        fig, ax = plt.subplots(figsize=(4.6, 4))
        ax.scatter(depth, tip, s=12)
        ax.set_xlabel("CM base depth error along the view axis (mm)")
        ax.set_ylabel("CM tip error (mm)")
        ax.set_title(f"{workflow}: tip vs depth error, r = {r:.2f}")
        fig.tight_layout()
        p = out_dir / "tip_vs_depth.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        written.append(p)
    return written
