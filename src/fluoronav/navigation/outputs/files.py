"""What ``fluoronav navigate`` writes: ``navigation.json``, ``slicer/`` and ``report.html``.

``navigation.json`` follows the navigation contract (docs/data-formats.md): the status and reason,
every stage with its seconds, checks and diagnostics, the registered poses in the CT frame (LPS, mm)
and the robot command (only when the status is "ok"). ``slicer/`` is a folder 3D Slicer loads
directly (:mod:`fluoronav.navigation.outputs.slicer`): the registered CM and femur as transforms and as
surface models in CT coordinates, the plan and the landmarks as markups.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fluoronav.geometry import se3
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.navigation.case.model import NavigationCase
from fluoronav.navigation.outputs.report import write_report
from fluoronav.navigation.outputs.slicer import cm_surface, femur_surface, write_slicer_folder
from fluoronav.navigation.pipeline import NavigationResult

log = logging.getLogger(__name__)

__all__ = ["write_navigation_json", "write_outputs", "write_slicer"]


def write_navigation_json(
    result: NavigationResult, out: Path, *, extra: Mapping[str, Any] | None = None
) -> Path:
    """``out/navigation.json`` (written whole at once: a reader never sees half a file)."""
    out.mkdir(parents=True, exist_ok=True)
    d = result.to_json()
    if extra:
        d.update(extra)
    path = out / "navigation.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(d, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    tmp.replace(path)
    return path


def write_slicer(result: NavigationResult, case: NavigationCase, out: Path) -> list[Path]:
    """``out/slicer/``: transforms, surface models, plan and landmarks (nothing without a registration)."""
    first = result.first
    if first is None:
        return []
    reg = result.verification or first
    kin = CMKinematics(case.cm_config)
    cp = np.asarray(reg.cm.control_points_deg, np.float64)
    cm_v, cm_f = cm_surface(case.cm_config, cp)
    fem_v, fem_f = femur_surface(case.volume, f"femur_{case.side}")
    fem_v = se3.apply(reg.ct_from_femur, fem_v)
    plan_points: dict[str, np.ndarray] = {}
    if result.plan is not None:
        # the plan moves with the femur: drawn in the CT's femur, shown on the registered one
        plan = result.plan
        # a line from the entry point along the insertion direction, 10 mm past the tip target
        plan_points = {
            "entry": se3.apply(reg.ct_from_femur, plan.entry_point_world_mm),
            "target": se3.apply(reg.ct_from_femur, plan.tip_target_world_mm + 10.0 * plan.direction_world),
        }
    ab = kin.landmarks_cm(torch.as_tensor(cp, dtype=torch.float64)).numpy()
    landmarks = {name: np.asarray(p, np.float64) for name, p in case.volume.landmarks_world.items()}
    landmarks.update(
        {
            "CM_A": se3.apply(reg.ct_from_cm, ab[0]),
            "CM_B": se3.apply(reg.ct_from_cm, ab[1]),
            "CM_tip": np.asarray(reg.tip_ct_mm, np.float64),
        }
    )
    extra: dict[str, np.ndarray] = {}
    if result.verification is not None:
        extra["ct_from_cm_before_move"] = first.ct_from_cm
    return write_slicer_folder(
        out / "slicer",
        ct_from_cm=reg.ct_from_cm,
        ct_from_femur=reg.ct_from_femur,
        cm_vertices_cm=cm_v,
        cm_faces=cm_f,
        femur_vertices_ct=fem_v,
        femur_faces=fem_f,
        plan_points=plan_points,
        landmarks=landmarks,
        extra_transforms=extra or None,
    )


def write_outputs(
    result: NavigationResult,
    case: NavigationCase,
    out: Path,
    *,
    extra: Mapping[str, Any] | None = None,
    report_title: str = "fluoronav navigate",
    report_description: str = "",
    timings_s: Mapping[str, float] | None = None,
    error_rows: Sequence[Sequence[Any]] = (),
    true_landmarks_px: Sequence[np.ndarray] | None = None,
    true_ct_from_cm: Mapping[str, np.ndarray] | None = None,
) -> list[Path]:
    """``navigation.json`` first (the result is safe before any picture is drawn), then ``slicer/``
    and ``report.html``; returns the paths written."""
    written = [write_navigation_json(result, out, extra=extra)]
    try:
        written += write_slicer(result, case, out)
    except Exception:  # the files for a viewer must not cost the run its report
        log.exception("the slicer/ folder could not be written")
    written.append(
        write_report(
            result,
            case,
            out,
            title=report_title,
            description=report_description,
            timings_s=timings_s,
            error_rows=error_rows,
            true_landmarks_px=true_landmarks_px,
            true_ct_from_cm=true_ct_from_cm,
        )
    )
    return written
