"""Checked registrations: the CM registered, judged view by view and, after a move, against the
robot's kinematics (:mod:`fluoronav.navigation.safety`); views left out, a second start, or a refusal.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
import torch

from fluoronav.geometry import se3
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.navigation.case import NavigationCase
from fluoronav.navigation.navigate import femur_from_cm_registered
from fluoronav.navigation.result import NavigationRefused, Registration, StageRecord
from fluoronav.navigation.safety import SafetyConfig, ViewVerdict, judge_cm_views, judge_motion
from fluoronav.registration.cm import (
    CMRegistrationConfig,
    CMRegistrationResult,
    CMView,
    register_cm,
    register_cm_multistart,
)
from fluoronav.registration.cm.diagnostics import cm_view_diagnostics

log = logging.getLogger(__name__)

__all__ = ["motion_consistency", "predicted_femur_from_cm", "register_cm_checked"]


def register_cm_checked(
    cm_views: list[CMView],
    landmarks_px: list[np.ndarray | None],
    tries: list[list[np.ndarray]],
    rec: StageRecord,
    *,
    stage_name: str,
    initial_control_points_deg: np.ndarray,
    cm_config: CMRegistrationConfig,
    safety: SafetyConfig,
    seed: int,
    motion_check: Callable[[CMRegistrationResult], dict[str, float]] | None,
) -> CMRegistrationResult:
    """The CM registered and checked (:mod:`fluoronav.navigation.safety`).

    Each entry of ``tries`` is a list of start poses; the next is tried only where the previous
    failed its checks. Within a try, views that disagree with the registration are left out and the
    CM registered again from where it was, while ``safety.min_views`` views remain.

    Raises:
        NavigationRefused: no try passed; the reason names the view and the check that failed last.
    """
    names = [v.name for v in cm_views]
    spacing = [v.camera.pixel_spacing_mm for v in cm_views]
    left_out: dict[str, str] = {}
    last: ViewVerdict | None = None
    for t, starts in enumerate(tries):
        use = list(range(len(cm_views)))
        cm = register_cm_multistart(
            cm_views,
            starts,
            initial_control_points_deg=initial_control_points_deg,
            config=cm_config,
            seed=seed + t,
        )
        while True:
            diags = cm_view_diagnostics(cm, [landmarks_px[k] for k in use], [spacing[k] for k in use])
            verdicts = judge_cm_views([names[k] for k in use], [d.to_dict() for d in diags], safety)
            failed = [v for v in verdicts if not v.passed]
            motion = motion_check(cm) if motion_check is not None and not failed else None
            moved = None if motion is None else judge_motion(motion, safety)
            rec.diagnostics.update(
                cost=float(cm.cost),
                converged=bool(cm.converged),
                reason=cm.reason,
                views={names[k]: d.to_dict() for k, d in zip(use, diags, strict=True)},
                views_used=[names[k] for k in use],
                tries=t + 1,
                **(motion or {}),
            )
            if not failed and moved is None:
                if left_out:
                    rec.diagnostics["left_out"] = left_out
                return cm
            last = failed[0] if failed else moved
            if not failed or len(use) - len(failed) < safety.min_views:
                break
            for v in failed:
                left_out[v.view] = f"{v.check}: {v.detail}"
                log.warning("%s: view %s left out (%s: %s)", stage_name, v.view, v.check, v.detail)
            use = [k for k, v in zip(use, verdicts, strict=True) if v.passed]
            cm = register_cm(
                [cm_views[k] for k in use],
                initial_control_points_deg=cm.control_points_deg,
                initial_world_from_cm=cm.world_from_cm[0],
                config=cm_config,
                seed=seed + 17 + t,
            )
        if t + 1 < len(tries):
            log.warning(
                "%s: %s failed (%s); trying the next start",
                stage_name,
                last.check if last else "",
                last.detail if last else "",
            )
    assert last is not None
    rec.passed = False
    if left_out:
        rec.diagnostics["left_out"] = left_out
    raise NavigationRefused(stage_name, last.check, last.detail, view=last.view)


def predicted_femur_from_cm(
    case: NavigationCase, first: Registration, joints_after_deg: np.ndarray
) -> np.ndarray:
    """(4, 4) where the robot's kinematics say the CM is after the move, in the femur frame: the
    first registration moved by the nominal robot's motion between ``case.joints_deg`` and
    ``joints_after_deg`` (the femur and the robot base do not move relative to each other)."""
    rbase_from_cm_1 = case.robot.rbase_from_ee(case.joints_deg) @ case.ee_from_cm
    rbase_from_cm_2 = case.robot.rbase_from_ee(np.asarray(joints_after_deg, np.float64)) @ case.ee_from_cm
    femur_from_cm_1 = femur_from_cm_registered(first.ct_from_femur, first.ct_from_cm)
    return femur_from_cm_1 @ np.linalg.inv(rbase_from_cm_1) @ rbase_from_cm_2


def motion_consistency(
    case: NavigationCase, first: Registration, ct_from_femur: np.ndarray, cm: CMRegistrationResult
) -> dict[str, float]:
    """Agreement of the verification's CM (femur frame) with the kinematic prediction: ``motion_tip_mm``
    (tip distance) and ``motion_rotation_deg``. A verification registration that failed disagrees by
    far more than the robot's and the first registration's errors."""
    assert case.verification is not None
    pred = predicted_femur_from_cm(case, first, case.verification.joints_deg)
    reg = femur_from_cm_registered(ct_from_femur, cm.world_from_cm[0])
    kin = CMKinematics(case.cm_config)
    tip = kin.tip_cm(torch.as_tensor(cm.control_points_deg, dtype=torch.float64)).numpy()
    d = np.linalg.inv(pred) @ reg
    c = (np.trace(d[:3, :3]) - 1.0) / 2.0
    return {
        "motion_tip_mm": float(np.linalg.norm(se3.apply(reg, tip) - se3.apply(pred, tip))),
        "motion_rotation_deg": float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))),
    }
