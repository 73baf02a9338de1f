"""Trials of the ``hand-eye`` and ``navigation`` studies: config, metrics, one trial each.

Both work in the simulated robot scene of :mod:`fluoronav.simulation.robot_scene`. Hand-eye trial: M CM poses
about the working pose with one shape for all, bent in one plane by ``calibration_bend_deg`` (the roll of the
hand-eye about the CM axis shows only through the bend); the image-based calibration
(:func:`~fluoronav.calibration.image_handeye.calibrate_hand_eye_from_images`) for each M of ``poses``
(nested), and the tracker baseline (AX = XB, Tsai) with its eq. 9 tip on the same poses. Navigation trial: the
simulated navigation loop (:mod:`fluoronav.simulation.navigation.loop`) with a hand-eye of documented error;
rows ``reposition_open_loop_mm`` (the first move's tip error against the plan), ``reposition_tip_mm`` (the
final one) and ``reposition_registered_mm`` (what the verification images say). The trials' settings and rows:
docs/robot-and-calibration.md ("Hand-eye and navigation studies").
"""

from __future__ import annotations

import functools
import logging
import math
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from fluoronav.calibration.handeye import (
    calibrate_hand_eye,
    tip_rbase_tracker_chain,
    transform_error,
)
from fluoronav.calibration.image_handeye import (
    ImageHandEyeConfig,
    ImageHandEyeResult,
    calibrate_hand_eye_from_images,
)
from fluoronav.calibration.results import HandEyeFailure
from fluoronav.calibration.tracker import DEFAULT_BODY, OpticalTracker
from fluoronav.errors import FluoronavError
from fluoronav.geometry import se3
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.navigation.config import NavigationConfig
from fluoronav.registration.cm import CMView
from fluoronav.registration.metrics import cm_errors
from fluoronav.runner import finish_row, mark_failed, new_row
from fluoronav.simulation.articulated import anatomy_and_simulator
from fluoronav.simulation.navigation.causes import refused_at, refused_view
from fluoronav.simulation.navigation.faults import fault_outcome, get_fault
from fluoronav.simulation.navigation.loop import SimulatedNavigationConfig, run_simulated_navigation
from fluoronav.simulation.robot_scene import (
    HandEyeScenario,
    perturb_transform,
    random_rotation,
    sample_handeye_scenario,
    simulate_scenario_images,
)
from fluoronav.simulation.world import IDEAL, World

__all__ = [
    "CM_METRICS",
    "HANDEYE_DIAGNOSTICS",
    "HANDEYE_METRICS",
    "NAVIGATION_CAUSES",
    "NAVIGATION_CHECKS",
    "NAVIGATION_DIAGNOSTICS",
    "NAVIGATION_METRICS",
    "HandEyeStudyConfig",
    "axis_and_roll_deg",
    "detector_or_none",
    "navigation_row",
    "refusal_check",
    "run_handeye_trial",
    "run_navigation_trial",
    "tip_rbase",
]

log = logging.getLogger(__name__)

CM_METRICS = ("tip_mm", "base_translation_mm", "base_rotation_deg", "notch_rotation_deg")
HANDEYE_METRICS = (
    "handeye_translation_mm",
    "handeye_rotation_deg",
    "handeye_tip_mm",
    *CM_METRICS,
    "baseline_tip_mm",
    "baseline_translation_mm",
    "baseline_rotation_deg",
    "eq9_vs_eq10_mm",
)
#: the hand-eye rotation error split into the tilt of the CM axis and the roll about it (rows, summary)
HANDEYE_DIAGNOSTICS = ("handeye_axis_deg", "handeye_roll_deg")
NAVIGATION_METRICS = (
    "reposition_tip_mm",
    "reposition_open_loop_mm",
    "reposition_registered_mm",
    "tip_mm",
    "entry_mm",
    "relative_mm",
    "base_translation_mm",
    "base_rotation_deg",
    "notch_rotation_deg",
)
#: navigation rows' further summarised figures: the robot-only error of the first move, the CM axis
#: against the plan, and the verification registration's own errors against the truth
NAVIGATION_DIAGNOSTICS = (
    "femur_tip_mm",
    "femur_axis_deg",
    "cm_axis_deg",
    "reposition_robot_mm",
    "reposition_axis_deg",
    "reposition_open_loop_axis_deg",
    "verify_entry_mm",
    "verify_tip_mm",
    "verify_relative_mm",
)
#: navigation rows' causes of a refusal (or of bad input): the one the simulation knows, the one
#: named, whether they agree (:mod:`fluoronav.simulation.navigation.causes`); empty where it went on
NAVIGATION_CAUSES = ("true_cause", "named_cause", "cause_named_right")
#: navigation rows' registration checks (no truth needed: what the navigation itself can see)
NAVIGATION_CHECKS = (
    "cm_landmark_residual_mm",
    "cm_edge_ncc",
    "cm_fbg_departure_sigmas",
    "pelvis_cost",
    "femur_cost",
    "verify_cm_landmark_residual_mm",
    "verify_cm_edge_ncc",
    "verify_motion_tip_mm",
    "verify_motion_rotation_deg",
    "verify_pelvis_cost",
    "verify_femur_cost",
    "verify_views_used",
    "verify_from_prediction",
    "verify_fused",
    "verify_whole_ladders_retry",
)


class _TrialFailure(FluoronavError):
    pass


@dataclass(frozen=True)
class HandEyeStudyConfig:
    """Settings of a hand-eye or navigation study (recorded in ``DIR/config.json``).

    Attributes:
        workflow: "hand-eye" or "navigation".
        poses: hand-eye: numbers of robot poses M evaluated per trial (nested subsets of the largest).
        image_size: simulated image rows = cols (the 1536² detector binned).
        rotation_spread_deg, translation_spread_mm: hand-eye pose sampling about the working pose.
        init_rotation_deg, init_translation_mm: initial hand-eye = truth perturbed by exactly these.
        handeye_error_deg, handeye_error_mm: navigation: hand-eye used = truth perturbed by these.
        corrections: navigation: 1: verification images at the reached pose (bones and CM registered
            anew) and one corrective move; 0: the open-loop move only.
        tracker_sigma_mm: baseline tracker marker noise per axis.
        calibration_bend_deg: hand-eye: the CM's bend during calibration, degrees per control point
            (each + U(−0.5, 0.5), one sign); None: the protocol's random working shape (U(−5, 5)°).
        oracle_landmarks: use truth + U(−3, 3) px (and the true CM mask) instead of the detector.
        world: navigation: the simulated world's error sources (:mod:`fluoronav.simulation.world`).
        verify_views: navigation: how many verification images each case gives (1, 2 or 3).
        fault: navigation: an input fault of :data:`fluoronav.simulation.navigation.faults.FAULTS` injected
            into every trial's case (None: none); rows then carry ``fault``, ``fault_outcome`` and
            ``fault_handled``.
        navigation: navigation: the pipeline's settings (a site's settings file), each trial's
            with the study's device and the trial's seed; None: the defaults.
    """

    workflow: str
    trials: int
    seed: int
    ct: str = "phantom"
    poses: tuple[int, ...] = (4, 8, 15)
    image_size: int = 768
    device: str = "cpu"
    rotation_spread_deg: float = 25.0
    translation_spread_mm: float = 10.0
    init_rotation_deg: float = 10.0
    init_translation_mm: float = 10.0
    handeye_error_deg: float = 0.4
    handeye_error_mm: float = 0.5
    corrections: int = 1
    tracker_sigma_mm: float = 0.1
    calibration_bend_deg: float | None = 2.5
    oracle_landmarks: bool = False  # as the CLI: the detector
    fault: str | None = None
    world: World = IDEAL
    verify_views: int = 3
    navigation: NavigationConfig | None = None


# ----- per-process caches -------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def detector_or_none(device: str) -> Any:
    """The shipped detector, or None when no model is shipped (then oracle landmarks are used)."""
    from fluoronav.detection.detector import Detector  # heavy: monai; none shipped means oracle landmarks

    try:
        return Detector.load(None, device=device)
    except FluoronavError as exc:
        log.info("no detector model (%s): oracle landmarks", exc)
        return None


def _landmarks(
    images: list[Any], true_full_px: np.ndarray, rng: np.random.Generator, cfg: HandEyeStudyConfig
) -> tuple[list[np.ndarray], str]:
    """Landmarks per image (image px) and their source ("detector" or "oracle")."""
    det = None if cfg.oracle_landmarks else detector_or_none(cfg.device)
    out = []
    for im, lm_full in zip(images, true_full_px, strict=True):
        b = (
            max(1, round(1536 / im.camera.cols))
            if im.camera.pixel_spacing_mm is None
            else max(1, round(im.camera.pixel_spacing_mm / 0.194))
        )
        oracle = (lm_full + rng.uniform(-3.0, 3.0, (2, 2)) + 0.5) / b - 0.5
        if det is None:
            out.append(oracle)
            continue
        d = det.detect(im.image, pixel_spacing_mm=im.camera.pixel_spacing_mm)
        if not d.usable:
            raise _TrialFailure(f"detector: {d.unusable_reason} in a hand-eye image")
        out.append(np.asarray(d.landmarks_px, np.float64))
    return out, "oracle" if det is None else "detector"


def axis_and_roll_deg(ee_from_cm_est: np.ndarray, ee_from_cm_true: np.ndarray) -> dict[str, float]:
    """Split the hand-eye rotation error into the tilt of the CM axis (z) and the roll about it."""
    R = ee_from_cm_true[:3, :3].T @ ee_from_cm_est[:3, :3]  # error in the true CM frame
    tilt = math.degrees(math.acos(float(np.clip(R[2, 2], -1.0, 1.0))))
    # roll: the rotation left after aligning the estimated z axis with the true one
    z = R[:, 2]
    axis = np.cross(z, [0.0, 0.0, 1.0])
    n = float(np.linalg.norm(axis))
    align = np.eye(3) if n < 1e-12 else Rotation.from_rotvec(axis / n * math.asin(min(1.0, n))).as_matrix()
    if z[2] < 0 and n >= 1e-12:
        align = Rotation.from_rotvec(axis / n * (math.pi - math.asin(min(1.0, n)))).as_matrix()
    Rz = align @ R
    return {"handeye_axis_deg": tilt, "handeye_roll_deg": abs(math.degrees(math.atan2(Rz[1, 0], Rz[0, 0])))}


def tip_rbase(
    rbase_from_ee: np.ndarray, ee_from_cm: np.ndarray, cp: np.ndarray, kin: CMKinematics
) -> np.ndarray:
    T = rbase_from_ee @ ee_from_cm
    tip = kin.tip_cm(torch.as_tensor(np.asarray(cp, np.float64))).numpy()
    return np.einsum("...ij,j->...i", T[..., :3, :3], tip) + T[..., :3, 3]


def _tracker_baseline(
    sc: HandEyeScenario, rng: np.random.Generator, sigma_mm: float, kin: CMKinematics
) -> dict[str, Any]:
    """AX = XB (Tsai) on the shaft marker O_s and the eq. 9 tip through the tip-segment marker O_t."""
    tracker = OpticalTracker(marker_sigma_mm=sigma_mm)
    # O_s on the shaft 60 mm behind the CM base; the tracker ~1.5 m from the robot base
    cm_from_os = se3.make(random_rotation(rng, 30.0), [30.0, 0.0, -60.0])
    ee_from_os = sc.ee_from_cm @ cm_from_os
    rbase_from_tracker = se3.make(random_rotation(rng, 180.0), [1500.0, 0.0, 500.0])
    tracker_from_rbase = np.linalg.inv(rbase_from_tracker)
    rbase_ee_true = sc.true_robot.rbase_from_ee(sc.q_actual_deg)
    t_os = tracker.track(
        tracker_from_rbase @ rbase_ee_true @ ee_from_os, DEFAULT_BODY, rng=rng
    ).tracker_from_body
    # O_t on the last link (the tip segment), its frame offset 10 mm from the link frame
    link = kin.link_transforms(torch.as_tensor(sc.control_points_deg, dtype=torch.float64))[-1].numpy()
    cm_from_ot = link @ se3.make(np.eye(3), [15.0, 0.0, 0.0])
    tip_cm = kin.tip_cm(torch.as_tensor(sc.control_points_deg, dtype=torch.float64)).numpy()
    tip_ot = (np.linalg.inv(cm_from_ot) @ np.append(tip_cm, 1.0))[:3]
    t_ot = tracker.track(
        tracker_from_rbase @ rbase_ee_true @ sc.ee_from_cm @ cm_from_ot, DEFAULT_BODY, rng=rng
    ).tracker_from_body
    res = calibrate_hand_eye(sc.rbase_from_ee_reported, t_os, method="TSAI")
    if isinstance(res, HandEyeFailure):
        return {"baseline_reason": res.reason}
    X = res.ee_from_marker
    tip9 = tip_rbase_tracker_chain(sc.rbase_from_ee_reported, X, t_os, t_ot, tip_ot)
    tip_true = tip_rbase(rbase_ee_true, sc.ee_from_cm, sc.control_points_deg, kin)
    rot, trans = transform_error(X @ np.linalg.inv(cm_from_os), sc.ee_from_cm)
    return {
        "baseline_tip_mm": float(np.linalg.norm(tip9 - tip_true, axis=1).mean()),
        "baseline_rotation_deg": rot,
        "baseline_translation_mm": trans,
        "_tip9": tip9,
    }


def _record_largest_m(
    row: dict[str, Any],
    res: ImageHandEyeResult,
    sc: HandEyeScenario,
    m: int,
    tip_mm: float,
    rot: float,
    trans: float,
) -> None:
    """Into ``row``, the figures of the calibration from the largest number of poses ``m`` (the
    trial's metrics): its errors (``tip_mm``, ``rot`` degrees, ``trans`` mm), convergence, axis and
    roll, estimates and the CM's errors in the C-arm frame."""
    row.update(
        handeye_tip_mm=tip_mm,
        handeye_rotation_deg=rot,
        handeye_translation_mm=trans,
        n_poses=m,
        seconds_registration=res.seconds,
        converged=res.converged,
        mean_residual_px=float(np.nanmean(res.residuals_px)),
    )
    row.update(axis_and_roll_deg(res.ee_from_cm, sc.ee_from_cm))
    row["est_ee_from_cm"] = np.round(res.ee_from_cm, 5).tolist()
    row["est_control_points_deg"] = np.round(res.control_points_deg, 4).tolist()
    cam = sc.camera.camera_from_world
    row.update(
        {
            k: v
            for k, v in cm_errors(
                carm_from_cm_est=cam @ res.world_from_cm[0],
                carm_from_cm_true=cam @ sc.world_from_cm[0],
                control_points_est_deg=res.control_points_deg,
                control_points_true_deg=sc.control_points_deg,
            ).items()
            if k in CM_METRICS
        }
    )


def run_handeye_trial(trial_id: int, seed: int, *, cfg: HandEyeStudyConfig) -> dict[str, Any]:
    """One hand-eye trial → one ``trials.csv`` row (metrics of the largest M, plus per-M columns)."""
    t0 = time.perf_counter()
    torch.set_num_threads(1)
    rng = np.random.default_rng(seed)
    row = new_row(trial_id, seed, cfg.workflow)
    try:
        volume, simulator = anatomy_and_simulator(cfg.ct, 1000 * cfg.seed, cfg.image_size, cfg.device)
        kin = CMKinematics()
        m_max = max(cfg.poses)
        sc = sample_handeye_scenario(
            volume,
            rng,
            n_poses=m_max,
            rotation_spread_deg=cfg.rotation_spread_deg,
            translation_spread_mm=cfg.translation_spread_mm,
            bend_deg=cfg.calibration_bend_deg,
        )
        images = simulate_scenario_images(
            sc, simulator, seed=int(rng.integers(2**31)), image_size=cfg.image_size
        )
        lms, source = _landmarks(images, sc.landmarks_px, rng, cfg)
        row["landmarks"] = source
        X0 = perturb_transform(sc.ee_from_cm, rng, cfg.init_rotation_deg, cfg.init_translation_mm)
        cp0 = sc.control_points_deg + rng.uniform(-0.5, 0.5, 5)
        views = [
            CMView(s.image, s.camera, landmarks_px=lm, name=f"pose{m}")
            for m, (s, lm) in enumerate(zip(images, lms, strict=True))
        ]
        rbase_ee_true = sc.true_robot.rbase_from_ee(sc.q_actual_deg)
        tip_true = tip_rbase(rbase_ee_true, sc.ee_from_cm, sc.control_points_deg, kin)
        base = _tracker_baseline(sc, rng, cfg.tracker_sigma_mm, kin)
        tip9 = base.pop("_tip9", None)
        row.update(base)
        row["true_ee_from_cm"] = np.round(sc.ee_from_cm, 5).tolist()
        row["true_control_points_deg"] = np.round(sc.control_points_deg, 4).tolist()
        hcfg = ImageHandEyeConfig(device=cfg.device)
        cal_seed = int(rng.integers(2**31))
        for m in sorted(cfg.poses):
            res = calibrate_hand_eye_from_images(
                views[:m],
                sc.rbase_from_ee_reported[:m],
                initial_ee_from_cm=X0,
                initial_control_points_deg=cp0,
                config=hcfg,
                seed=cal_seed,
            )
            if isinstance(res, HandEyeFailure):
                row[f"reason_m{m}"] = res.reason
                if m == m_max:
                    raise _TrialFailure(f"hand-eye failed: {res.reason}")
                continue
            rot, trans = transform_error(res.ee_from_cm, sc.ee_from_cm)
            tip10 = tip_rbase(sc.rbase_from_ee_reported[:m], res.ee_from_cm, res.control_points_deg, kin)
            tip_mm = float(np.linalg.norm(tip10 - tip_true[:m], axis=1).mean())
            row[f"handeye_tip_mm_m{m}"] = tip_mm
            row[f"handeye_rotation_deg_m{m}"] = rot
            row[f"handeye_translation_mm_m{m}"] = trans
            row[f"seconds_m{m}"] = res.seconds
            if m == m_max:
                _record_largest_m(row, res, sc, m, tip_mm, rot, trans)
                if tip9 is not None:
                    row["eq9_vs_eq10_mm"] = float(np.linalg.norm(tip9[:m] - tip10, axis=1).mean())
    except Exception as exc:  # a failed trial is recorded with its reason, never dropped
        mark_failed(row, exc, trial_id)
    return finish_row(row, t0)


def navigation_row(run: Any, cfg: HandEyeStudyConfig) -> dict[str, Any]:
    """A ``trials.csv`` row's figures from a simulated navigation
    (:mod:`fluoronav.simulation.navigation.loop`).

    ``reposition_open_loop_mm`` is the first move's error, ``reposition_tip_mm`` the final one (after
    the correction when ``corrections`` is 1), ``reposition_registered_mm`` what the verification
    images say (registered tip to plan)."""
    E = run.errors
    row: dict[str, Any] = {"status": run.status, "reason": run.reason}
    pairs = {
        "tip_mm": "cm_tip_mm",
        "entry_mm": "femur_entry_mm",
        "relative_mm": "cm_relative_mm",
        "femur_tip_mm": "cm_femur_tip_mm",
        "femur_axis_deg": "cm_femur_axis_deg",
        "base_translation_mm": "cm_base_translation_mm",
        "base_rotation_deg": "cm_base_rotation_deg",
        "notch_rotation_deg": "cm_notch_rotation_deg",
        "reposition_open_loop_mm": "reposition_tip_mm",
        "reposition_open_loop_axis_deg": "reposition_axis_deg",
        "reposition_robot_mm": "reposition_robot_mm",
        "reposition_registered_mm": "verify_tip_to_plan_mm",
        "verify_entry_mm": "verify_femur_entry_mm",
        "verify_tip_mm": "verify_tip_error_mm",
        "verify_relative_mm": "verify_relative_mm",
        "joint_motion_deg": "joint_motion_deg",
    }
    row.update({k: E[v] for k, v in pairs.items() if v in E})
    if "cm_base_rx_deg" in E:
        row["cm_axis_deg"] = _cm_axis_deg(E)
    final = "corrected" if cfg.corrections else "reposition"
    if f"{final}_tip_mm" in E:
        row["reposition_tip_mm"] = E[f"{final}_tip_mm"]
        if f"{final}_axis_deg" in E:
            row["reposition_axis_deg"] = E[f"{final}_axis_deg"]
    if run.result is not None:
        row.update(run.result.flat_diagnostics())
        st = run.result.stages
        row["seconds_registration"] = st["cm"].seconds if "cm" in st else None
        row["seconds_bones"] = sum(st[k].seconds for k in ("pelvis", "femur") if k in st)
        row["seconds_verification"] = sum(v.seconds for k, v in st.items() if k.startswith("verify_"))
    input_error = run.artifacts.get("input_error")
    if input_error is not None:
        row.update(status="input_error", reason=input_error["reason"], check=input_error["check"])
    else:
        row["check"] = refusal_check(run.reason)[1]
    if cfg.fault is not None:
        row.update(_fault_fields(run, row, cfg.fault))
    causes = getattr(run, "causes", None) or {}
    row.update({k: causes[k] for k in NAVIGATION_CAUSES if k in causes})
    return row


def refusal_check(reason: str) -> tuple[str, str]:
    """(stage, check) of a refusal's reason (``stage X[, view V], check C: detail``); ("", "") else
    (:func:`~fluoronav.simulation.navigation.causes.refused_at`)."""
    return refused_at(reason)


def _cm_axis_deg(E: dict[str, float]) -> float:
    """The first registration's CM axis (z) against the true one, degrees, from the base rotation
    error's rotation vector (in the CM frame)."""
    rv = np.radians([E["cm_base_rx_deg"], E["cm_base_ry_deg"], E["cm_base_rz_deg"]])
    return math.degrees(math.acos(float(np.clip(Rotation.from_rotvec(rv).as_matrix()[2, 2], -1.0, 1.0))))


def _left_out(run: Any) -> tuple[str, ...]:
    """The first views the navigation left out: no CM found, or left out by the bones' or CM's checks."""
    if run.result is None:
        return ()
    out: set[str] = set()
    for name in ("detect", "pelvis", "femur", "cm"):
        st = run.result.stages.get(name)
        if st is None:
            continue
        out.update(st.diagnostics.get("left_out", {}))
        if name == "detect":
            out.update(v for v, d in st.diagnostics.get("views", {}).items() if not d.get("found", True))
    return tuple(sorted(out))


def _fault_fields(run: Any, row: dict[str, Any], name: str) -> dict[str, Any]:
    """``fault``, ``fault_outcome``, ``fault_handled`` and ``left_out`` of a fault trial's row."""
    fault = get_fault(name)
    assert fault is not None
    left_out = _left_out(run)
    names = run.artifacts.get("names") or []
    faulty_view = (
        names[fault.view_index] if fault.view_index is not None and fault.view_index < len(names) else None
    )
    stage = refusal_check(run.reason)[0] if run.result is not None else "preflight"
    outcome, handled = fault_outcome(
        fault,
        status=str(row["status"]),
        stage=stage,
        check=str(row.get("check") or ""),
        final_tip_mm=row.get("reposition_tip_mm"),
        first_tip_mm=row.get("tip_mm"),
        commanded="reposition_open_loop_mm" in row,
        left_out=left_out,
        faulty_view=faulty_view,
        refused_view=refused_view(run.reason) if run.result is not None else "",
    )
    return {"fault": name, "fault_outcome": outcome, "fault_handled": handled, "left_out": list(left_out)}


def run_navigation_trial(trial_id: int, seed: int, *, cfg: HandEyeStudyConfig) -> dict[str, Any]:
    """One navigation trial → one ``trials.csv`` row: the shared simulated navigation loop
    (:func:`fluoronav.simulation.navigation.loop.run_simulated_navigation`), the same pipeline as
    ``fluoronav navigate`` and the demo."""
    t0 = time.perf_counter()
    torch.set_num_threads(1)
    row = new_row(trial_id, seed, cfg.workflow)
    try:
        sim = SimulatedNavigationConfig(
            seed=seed,
            phantom_seed=1000 * cfg.seed,
            image_size=cfg.image_size,
            handeye_error_deg=cfg.handeye_error_deg,
            handeye_error_mm=cfg.handeye_error_mm,
            verify=cfg.corrections > 0,
            device=cfg.device,
            oracle_landmarks=cfg.oracle_landmarks,
            fault=cfg.fault,
            world=cfg.world,
            verify_views=cfg.verify_views,
        )
        row["landmarks"] = "oracle" if cfg.oracle_landmarks else "detector"
        nav = None if cfg.navigation is None else replace(cfg.navigation, device=cfg.device, seed=seed)
        row.update(navigation_row(run_simulated_navigation(sim, ct=cfg.ct, navigation=nav), cfg))
    except Exception as exc:  # a failed trial is recorded with its reason, never dropped
        mark_failed(row, exc, trial_id)
        if cfg.fault is not None:
            row.update(fault=cfg.fault, fault_outcome="failed", fault_handled=False)
    return finish_row(row, t0)


# ----- study --------------------------------------------------------------------------------------
