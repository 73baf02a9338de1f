"""``fluoronav demo``: the navigation loop on the built-in phantom, in simulation, through files.

The demo simulates a navigation case (:mod:`fluoronav.simulation.navigation.loop`), writes it to
``DIR/case/navigation.json`` with its files and the truth to ``DIR/truth.json``, reads it back and runs
the same pipeline as ``fluoronav navigate`` on it; the true robot moves, the verification images
join the case, and the pipeline registers them and commands one correction. Everything is measured
against the truth: ``DIR/results.json`` (``status``, ``reason``, ``errors``), ``DIR/report.html``,
and the pipeline's own ``DIR/navigation.json`` and ``DIR/slicer/``.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fluoronav import __version__
from fluoronav.navigation.config import NavigationConfig
from fluoronav.navigation.outputs.files import write_outputs
from fluoronav.navigation.pipeline import STAGES, VERIFY_STAGES, EventCallback
from fluoronav.simulation.navigation.loop import (
    SimulatedNavigation,
    SimulatedNavigationConfig,
    run_simulated_navigation,
)

__all__ = ["ERROR_ROWS", "run_demo", "write_demo_outputs"]

#: (label, key in the errors, unit, the paper's figure for comparison or "")
ERROR_ROWS = (
    (
        "CM landmark detection (mean of A, B over the views)",
        "landmark_mm_at_detector",
        "mm at detector",
        "0.449",
    ),
    ("pelvis rotation (mean over views)", "pelvis_rotation_deg", "deg", ""),
    ("pelvis centre (mean over views)", "pelvis_center_mm", "mm", ""),
    ("femur rotation", "femur_rotation_deg", "deg", ""),
    ("femur entry point", "femur_entry_mm", "mm", ""),
    ("CM tip after centreline initialisation", "cm_init_tip_mm", "mm", ""),
    ("CM tip (multi-view registration)", "cm_tip_mm", "mm", "0.59 (multi-view)"),
    ("CM tip relative to the femur entry point", "cm_relative_mm", "mm", "0.63 (multi-view)"),
    ("CM base translation", "cm_base_translation_mm", "mm", "0.52"),
    ("CM base rotation", "cm_base_rotation_deg", "deg", "1.38"),
    ("CM notch rotation (mean)", "cm_notch_rotation_deg", "deg", "0.22"),
    ("repositioning: true tip to plan", "reposition_tip_mm", "mm", "2.86 ± 0.80 (cadaver)"),
    ("repositioning: CM axis to plan", "reposition_axis_deg", "deg", ""),
    ("repositioning with true registrations (robot and hand-eye only)", "reposition_robot_mm", "mm", ""),
    ("verification: registered tip error", "verify_tip_error_mm", "mm", "0.59 (multi-view)"),
    ("verification: registered tip to plan (what the images say)", "verify_tip_to_plan_mm", "mm", ""),
    ("after one corrective move: true tip to plan", "corrected_tip_mm", "mm", "2.86 ± 0.80 (cadaver)"),
    ("after one corrective move: CM axis to plan", "corrected_axis_deg", "deg", ""),
)


def run_demo(
    config: SimulatedNavigationConfig | None = None,
    *,
    out: Path,
    navigation: NavigationConfig | None = None,
    on_stage: Callable[[str, str], None] | None = None,
    on_event: EventCallback | None = None,
) -> SimulatedNavigation:
    """Simulate a case into ``out/case``, navigate on its files, move, verify, correct.

    ``navigation``: the pipeline's settings (a site's settings file; None: the defaults, with the
    simulation's device and seed)."""
    return run_simulated_navigation(
        config, case_dir=out / "case", navigation=navigation, on_stage=on_stage, on_event=on_event
    )


def results_json(run: SimulatedNavigation) -> dict[str, Any]:
    """``results.json``: status, reason, errors against the truth, where it refused the cause the
    simulation knows against the one named (``causes``), timings, config, the simulated world,
    version."""
    errors: dict[str, float | None] = {
        k: (float(v) if math.isfinite(v) else None) for k, v in run.errors.items()
    }
    errors.setdefault("reposition_tip_mm", None)
    errors.setdefault("corrected_tip_mm", None)
    timings = dict(run.timings_s)
    if run.result is not None:
        timings.update({k: v.seconds for k, v in run.result.stages.items()})
    return {
        "version": __version__,
        "status": run.status,
        "reason": run.reason,
        "config": dataclasses.asdict(run.config),
        "world": run.config.world.to_dict(),
        "errors": errors,
        **({"causes": run.causes} if run.causes else {}),
        "timings_s": timings,
    }


def ordered_timings(run: SimulatedNavigation) -> dict[str, float]:
    """The loop's and the pipeline's stage times in the order they ran."""
    stages = run.result.stages if run.result is not None else {}
    order = [
        "anatomy",
        "scene",
        "simulate",
        *STAGES,
        "move",
        "verify_simulate",
        *VERIFY_STAGES,
        "correct_move",
    ]
    out = {}
    for name in order:
        if name in run.timings_s:
            out[name] = run.timings_s[name]
        elif name in stages:
            out[name] = stages[name].seconds
    return out


def write_demo_outputs(run: SimulatedNavigation, out: Path) -> list[Path]:
    """``out/results.json``, and where the pipeline ran: ``navigation.json``, ``slicer/`` and
    ``report.html`` with the errors against the truth."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / "results.json"
    path.write_text(json.dumps(results_json(run), indent=2) + "\n", encoding="utf-8")
    written = [path]
    A = run.artifacts
    if run.result is None or "case" not in A:
        return written
    cfg = run.config
    rows = [
        [label, run.errors[key], unit, paper] for label, key, unit, paper in ERROR_ROWS if key in run.errors
    ]
    true_cm = {"CM (true, first images)": np.asarray(run.truth["ct_from_cm"])}
    description = (
        f"Simulated navigation on the built-in hip phantom (seed {cfg.seed}): {len(A['images'])} "
        f"physics-simulated C-arm views at {cfg.image_size}² (the 1536² CIOS Fusion detector binned) → "
        "detection → pelvis per view → femur → multi-view centreline initialisation → CM registration → "
        "plan → robot command (eqs. 7–8, UR-10 with joint and calibration errors, hand-eye error "
        f"{cfg.handeye_error_deg}° / {cfg.handeye_error_mm} mm) → move → verification images, their "
        "registration → one corrective move. The case the pipeline read is in case/; errors are "
        "against the simulated truth (truth.json); the paper's figures are its simulation means and "
        "cadaver repositioning."
    )
    written += write_outputs(
        run.result,
        A["case"],
        out,
        extra={"case": str(out / "case" / "navigation.json")},
        report_title="fluoronav demo: simulated fluoroscopic navigation",
        report_description=description,
        timings_s=ordered_timings(run),
        error_rows=rows,
        true_landmarks_px=[im.landmarks_px for im in A["images"]],
        true_ct_from_cm=true_cm,
    )
    return written
