"""The simulated navigation's estimates against the truth (:mod:`fluoronav.simulation.navigation.loop`).

Frames: ``world`` is the simulation's world (the CT frame before the patient moved); ``ct`` the CT
frame the pipeline works in. CM and femur errors are measured in the C-arm frame of the first kept
view (the AP view, as the paper's), repositioning in the world frame.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import torch

from fluoronav.geometry import se3
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.navigation.planning import planned_femur_from_cm
from fluoronav.navigation.result import NavigationResult
from fluoronav.navigation.targeting import robot_target
from fluoronav.registration.metrics import axis_error_deg, cm_errors
from fluoronav.simulation.robot_scene import HandEyeScenario

__all__ = ["first_registration_errors", "robot_only_error", "verification_errors"]


def _rotation_deg(R: np.ndarray) -> float:
    c = (np.trace(R[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def first_registration_errors(
    res: NavigationResult | None,
    E: dict[str, float],
    tip_ct_true_mm: np.ndarray,
    sc: HandEyeScenario,
    images_by_view: dict[str, Any],
    W_regi: np.ndarray,
    cp_true: np.ndarray,
    *,
    tip_cm_true: np.ndarray | None = None,
) -> None:
    """Errors of the first registration against the truth, in the C-arm frame of its first view (the
    AP view, as the paper's, unless the bones' checks left it out). ``tip_cm_true``: (3,) the tip
    of the instrument as built in its base frame, where it is not the model's."""
    tr = sc.trial
    if res is None or res.first is None:
        return
    first = res.first
    images = [images_by_view[v.name] for v in first.views]  # the views the registration kept
    det_err = [
        np.linalg.norm(d.landmarks_px - im.landmarks_px, axis=1)
        for d, im in zip(first.detections, images, strict=True)
        if d is not None
    ]
    if det_err:
        ps = images[0].camera.pixel_spacing_mm or float("nan")
        E["landmark_px"] = float(np.mean(det_err))
        E["landmark_mm_at_detector"] = float(np.mean(det_err) * ps)
    rot, cen = [], []
    for cam_est, im in zip(first.cameras_ct, images, strict=True):
        delta = np.linalg.inv(im.camera.camera_from_world @ tr.world_from_patient) @ cam_est.camera_from_world
        rot.append(_rotation_deg(delta))
        cen.append(float(np.linalg.norm(se3.apply(delta, tr.pelvis_center_ct) - tr.pelvis_center_ct)))
    E["pelvis_rotation_deg"], E["pelvis_center_mm"] = float(np.mean(rot)), float(np.mean(cen))
    carm = images[0].camera.camera_from_world
    carm_est = first.cameras_ct[0].camera_from_world
    entry_est = se3.apply(carm_est @ first.ct_from_femur, tr.entry_ct)
    entry_true = se3.apply(carm @ tr.world_from_femur, tr.entry_ct)
    E["femur_entry_mm"] = float(np.linalg.norm(entry_est - entry_true))
    E["femur_rotation_deg"] = _rotation_deg(
        np.linalg.inv(carm @ tr.world_from_femur) @ (carm_est @ first.ct_from_femur)
    )
    errs = cm_errors(
        carm_from_cm_est=carm_est @ first.ct_from_cm,
        carm_from_cm_true=carm @ W_regi,
        control_points_est_deg=first.cm.control_points_deg,
        control_points_true_deg=cp_true,
        config=sc.cm_config,
    )
    E.update({f"cm_{k}": float(v) for k, v in errs.items()})
    tip_cm = _tip(sc, cp_true) if tip_cm_true is None else tip_cm_true
    tip_true_c = se3.apply(carm @ W_regi, tip_cm)
    if tip_cm_true is not None:  # the instrument as built, not the model: its own tip
        E["cm_tip_mm"] = float(np.linalg.norm(se3.apply(carm_est, first.tip_ct_mm) - tip_true_c))
    E["cm_relative_mm"] = float(
        np.linalg.norm((se3.apply(carm_est, first.tip_ct_mm) - entry_est) - (tip_true_c - entry_true))
    )
    E["cm_tip_ct_mm"] = float(np.linalg.norm(first.tip_ct_mm - np.asarray(tip_ct_true_mm)))
    # what the first move acts on: the CM in the femur's frame (the plan's), where an error the
    # bones and the CM share (a camera's calibration) cancels
    femur_from_ct = np.linalg.inv(first.ct_from_femur)
    femur_from_cm_est = femur_from_ct @ first.ct_from_cm
    femur_from_cm_true = np.linalg.inv(tr.world_from_femur) @ W_regi
    E["cm_femur_tip_mm"] = float(
        np.linalg.norm(se3.apply(femur_from_ct, first.tip_ct_mm) - se3.apply(femur_from_cm_true, tip_cm))
    )
    E["cm_femur_axis_deg"] = axis_error_deg(femur_from_cm_est[:3, 2], femur_from_cm_true[:3, 2])
    if first.cm_init is not None:
        E["cm_init_tip_mm"] = float(
            np.linalg.norm(se3.apply(carm_est @ first.cm_init.world_from_cm, _tip(sc, cp_true)) - tip_true_c)
        )


def _tip(sc: HandEyeScenario, cp_deg: np.ndarray) -> np.ndarray:
    return CMKinematics(sc.cm_config).tip_cm(torch.as_tensor(cp_deg, dtype=torch.float64)).numpy()


def verification_errors(
    res: NavigationResult | None,
    E: dict[str, float],
    sc: HandEyeScenario,
    images_by_view: dict[str, Any],
    W_after: np.ndarray,
    *,
    moved_from_world: np.ndarray | None = None,
    tip_cm_true: np.ndarray | None = None,
) -> None:
    """Errors of the verification's registration against the truth, in the C-arm frame of its first
    kept view, with the patient moved by ``moved_from_world`` (4, 4) since the first images: the tip
    (``verify_tip_error_mm``), its distance from the plan as registered
    (``verify_tip_to_plan_mm``), the femur's entry point and the tip relative to it."""
    tr = sc.trial
    # the femur where the patient had moved to when the verification images were taken
    world_from_femur = (
        tr.world_from_femur if moved_from_world is None else moved_from_world @ tr.world_from_femur
    )
    if res is None or res.verification is None or res.plan is None:
        return
    ver = res.verification
    images2 = [images_by_view[v.name] for v in ver.views]  # the views the registration kept
    carm2 = images2[0].camera.camera_from_world
    carm2_est = ver.cameras_ct[0].camera_from_world
    tip_after = se3.apply(W_after, _tip(sc, sc.control_points_deg) if tip_cm_true is None else tip_cm_true)
    E["verify_tip_to_plan_mm"] = float(
        np.linalg.norm(ver.tip_ct_mm - se3.apply(ver.ct_from_femur, res.plan.tip_target_world_mm))
    )
    E["verify_tip_error_mm"] = float(
        np.linalg.norm(se3.apply(carm2_est, ver.tip_ct_mm) - se3.apply(carm2, tip_after))
    )
    entry_est = se3.apply(carm2_est @ ver.ct_from_femur, tr.entry_ct)
    entry_true = se3.apply(carm2 @ world_from_femur, tr.entry_ct)
    E["verify_femur_entry_mm"] = float(np.linalg.norm(entry_est - entry_true))
    E["verify_relative_mm"] = float(
        np.linalg.norm(
            (se3.apply(carm2_est, ver.tip_ct_mm) - entry_est) - (se3.apply(carm2, tip_after) - entry_true)
        )
    )


def robot_only_error(
    sc: HandEyeScenario,
    res: NavigationResult,
    q_regi: np.ndarray,
    W_regi: np.ndarray,
    ee_from_cm_used: np.ndarray,
    rng: np.random.Generator,
    tip_cm: np.ndarray,
) -> float:
    """The first move's error with true registrations (the robot's and the hand-eye's share)."""
    tr = sc.trial
    assert res.plan is not None
    plan_true = dataclasses.replace(res.plan, control_points_deg=sc.control_points_deg)
    # the roll the pipeline chose for a plan whose roll is free, so that the same move is measured
    roll_deg = float(res.stages["plan"].diagnostics.get("roll_deg", 0.0)) if "plan" in res.stages else 0.0
    target = planned_femur_from_cm(plan_true, kinematics=CMKinematics(sc.cm_config), roll_deg=roll_deg)
    _, q = robot_target(
        sc.nominal,
        q_regi,
        ee_from_cm=ee_from_cm_used,
        carm_from_femur=tr.world_from_femur,
        carm_from_cm=W_regi,
        femur_from_cm_target=target,
    )
    W = sc.execute(q, rng=np.random.default_rng(int(rng.integers(2**31))))
    return float(
        np.linalg.norm(se3.apply(W, tip_cm) - se3.apply(tr.world_from_femur, res.plan.tip_target_world_mm))
    )
