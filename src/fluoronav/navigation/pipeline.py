"""The navigation pipeline: from a navigation case to a robot command (``fluoronav navigate``).

Stages, each timed and recorded with its diagnostics (:class:`StageRecord`): ``detect`` (per view:
the CM's mask, landmarks and centreline), ``pelvis``, ``femur`` and ``cm``
(:func:`~fluoronav.registration.view_set.register_view_set`), ``plan`` (the planned CM pose in the
femur frame; a free roll is the one whose command turns the joints least) and ``robot`` (eqs. 7–8,
inverse kinematics, the command measured and bounded: :mod:`fluoronav.navigation.commands`). With
verification views (:func:`verify`): the same on the images after the move, with the first
registration and the robot's kinematics as the prior, then ``correct`` (one corrective command).
A stage that cannot go on ends the run ``"refused"``, naming the stage, view and check, with no robot command
(docs/navigation.md, "Stages"). Frames: ``ct`` (LPS, mm); ``femur``: the CT frame moved with the femur.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.navigation.case.model import CaseView, NavigationCase
from fluoronav.navigation.checks.preflight import preflight, raise_for_input
from fluoronav.navigation.commands import (
    check_correction,
    check_first_move,
    check_joint_readings,
    judge_kinematics,
    measure_command,
    undetected_refused,
    undetected_warning,
)
from fluoronav.navigation.config import NavigationConfig
from fluoronav.navigation.detect import detect_views
from fluoronav.navigation.kinematic_prior import prediction_sigma_mm
from fluoronav.navigation.planning import Plan, planned_femur_from_cm
from fluoronav.navigation.result import (
    NavigationRefused,
    NavigationResult,
    StageRecord,
    ViewDetection,
    navigation_refusals,
)
from fluoronav.navigation.targeting import (
    LeastMotionTarget,
    UnreachableTarget,
    femur_from_cm_registered,
    joint_motion_deg,
    least_motion_target,
    predicted_femur_from_cm,
    robot_target,
    tip_correction_target,
)
from fluoronav.navigation.verification import moved_cameras, register_verification
from fluoronav.registration.stages import StageTimer
from fluoronav.registration.view_set import (
    FluoroView,
    ViewSetPrior,
    ViewSetRegistration,
    register_view_set,
)

log = logging.getLogger(__name__)

__all__ = [
    "STAGES",
    "VERIFY_STAGES",
    "EventCallback",
    "NavigationConfig",
    "NavigationRefused",
    "NavigationResult",
    "StageRecord",
    "ViewDetection",
    "navigate",
    "verify",
]

STAGES = ("preflight", "detect", "pelvis", "femur", "cm", "plan", "robot")
VERIFY_STAGES = ("verify_joints", "verify_detect", "verify_pelvis", "verify_femur", "verify_cm", "correct")


#: ``on_event(kind, data)``: what the pipeline tells a listener (e.g. a live link to a viewer) as
#: soon as it is known. Kinds and data: "views" (``prefix``, ``views``: the case's views of that
#: set), "registration" (``prefix``, ``registration``: a :class:`ViewSetRegistration`), "plan"
#: (``plan``, ``ct_from_femur``, ``femur_from_cm_target``), "status" (``status``, ``reason``; at the end of
#: :func:`navigate` and of :func:`verify`). ``prefix`` is "" for the first images and "verify_"
#: for the verification's.
EventCallback = Callable[[str, dict[str, Any]], None]


class _Stages(StageTimer):
    """Times stages into ``result.stages`` (:class:`StageTimer`, telling ``on_stage``) and tells
    listeners what the pipeline learns; a listener that fails is logged and never stops the navigation."""

    def __init__(
        self,
        result: NavigationResult,
        on_stage: Callable[[str, str], None] | None,
        on_event: EventCallback | None = None,
    ) -> None:
        super().__init__(result.stages, on_stage)
        self.result, self.on_event = result, on_event

    def emit(self, kind: str, **data: Any) -> None:
        if self.on_event is None:
            return
        try:
            self.on_event(kind, data)
        except Exception:  # a listener must not cost the navigation its result
            log.exception("navigation listener failed on %r", kind)


def _detect(
    stage: _Stages, views: Sequence[CaseView], config: NavigationConfig, *, prefix: str, need: int
) -> list[FluoroView]:
    """The ``detect`` stage of one set of views: each view with the CM found in it; refuses where
    fewer than ``need`` views have one."""
    with stage(f"{prefix}detect") as rec:
        stage.emit("views", prefix=prefix, views=tuple(views))
        detections, rec.diagnostics["views"] = detect_views(views, config=config)
        seen = [k for k, d in enumerate(detections) if d is not None]
        rec.diagnostics["views_detected"] = len(seen)
        if len(seen) < need:
            missing = ", ".join(v.name for v, d in zip(views, detections, strict=True) if d is None)
            raise NavigationRefused(
                f"{prefix}detect",
                "views_with_cm",
                f"the CM was found in {len(seen)} of {len(views)} views, {need} needed",
                view=missing,
            )
    return [FluoroView(v.name, v.image, v.camera, d) for v, d in zip(views, detections, strict=True)]


def _stage_seed(seed: int, k: int) -> int:
    """Optimiser seed of registration set k from the user's seed (any size; CMA-ES takes < 2³²)."""
    return int(np.random.SeedSequence(abs(int(seed))).generate_state(k + 1)[k]) % 2**31


def _command(
    case: NavigationCase,
    reg: ViewSetRegistration,
    joints_deg: np.ndarray,
    femur_from_cm_target: np.ndarray,
    config: NavigationConfig,
    stage_name: str,
) -> tuple[np.ndarray, np.ndarray]:
    """Eqs. 7–8 + IK from the registration; refuses an unreachable target. (The C-arm frame of the
    registration's first kept view cancels in eq. 7: any view's would give the same command.)"""
    carm_from_ct = reg.cameras_ct[0].camera_from_world
    try:
        return robot_target(
            case.robot,
            joints_deg,
            ee_from_cm=case.ee_from_cm,
            carm_from_femur=carm_from_ct @ reg.ct_from_femur,
            carm_from_cm=carm_from_ct @ reg.ct_from_cm,
            femur_from_cm_target=femur_from_cm_target,
            tol_mm=config.ik_tol_mm,
            tol_deg=config.ik_tol_deg,
        )
    except UnreachableTarget as exc:
        raise NavigationRefused(stage_name, "reachable", str(exc)) from None


def _least_motion_roll(
    case: NavigationCase,
    reg: ViewSetRegistration,
    plan: Plan,
    kin: CMKinematics,
    config: NavigationConfig,
) -> LeastMotionTarget:
    """A free-roll plan's roll whose command from the case's joints turns the joints least; refuses
    where no roll is reachable."""
    carm_from_ct = reg.cameras_ct[0].camera_from_world
    try:
        return least_motion_target(
            case.robot,
            case.joints_deg,
            lambda roll: planned_femur_from_cm(plan, kinematics=kin, roll_deg=roll),
            ee_from_cm=case.ee_from_cm,
            carm_from_femur=carm_from_ct @ reg.ct_from_femur,
            carm_from_cm=carm_from_ct @ reg.ct_from_cm,
            tol_mm=config.ik_tol_mm,
            tol_deg=config.ik_tol_deg,
        )
    except UnreachableTarget as exc:
        raise NavigationRefused("plan", "reachable", f"plan '{plan.target_name}': {exc}") from None


def _tip_cm(kin: CMKinematics, control_points_deg: np.ndarray) -> np.ndarray:
    return kin.tip_cm(torch.as_tensor(np.asarray(control_points_deg), dtype=torch.float64)).numpy()


def _preflight(case: NavigationCase, config: NavigationConfig, stage: _Stages) -> None:
    """The case's inputs and plan checked before any registration
    (:mod:`fluoronav.navigation.checks.preflight`).

    Raises:
        InputError: bad input (exit status 2), naming the case file and the first problem.
        NavigationRefused: the plan cannot be carried out (stage ``preflight``).
    """
    if config.preflight is None:
        return
    with stage("preflight") as rec:
        findings = preflight(case, config.preflight)
        rec.diagnostics["findings"] = [
            {"kind": f.kind, "check": f.check, "reason": f.reason} for f in findings
        ]
    raise_for_input(findings, str(case.source or "navigation case"))
    plan = [f for f in findings if f.kind == "plan"]
    if plan:
        more = f" (and {len(plan) - 1} more plan problem(s))" if len(plan) > 1 else ""
        raise NavigationRefused("preflight", plan[0].check, plan[0].reason + more)


def _refused(res: NavigationResult, stage: _Stages, exc: NavigationRefused, what: str) -> NavigationResult:
    """``res`` refused by ``exc`` (logged as ``what``), its listeners told."""
    log.warning("%s refused: %s", what, exc)
    res.refuse(exc)
    stage.emit("status", status=res.status, reason=res.reason)
    return res


def navigate(
    case: NavigationCase,
    config: NavigationConfig | None = None,
    *,
    on_stage: Callable[[str, str], None] | None = None,
    on_event: EventCallback | None = None,
) -> NavigationResult:
    """Run the pipeline (module docstring) on ``case``; with verification views, :func:`verify` too.

    Args:
        case: the navigation case.
        config: settings (default :class:`NavigationConfig`).
        on_stage: called with (stage name, "start" | "done") for progress displays.
        on_event: called as results become known (:data:`EventCallback`).

    Returns:
        :class:`NavigationResult`; status "refused" (and no robot command) where a stage could not
        go on.
    """
    cfg = config or NavigationConfig()
    res = NavigationResult(config=cfg)
    stage = _Stages(res, on_stage, on_event)
    try:
        _preflight(case, cfg, stage)
    except NavigationRefused as exc:
        return _refused(res, stage, exc, "navigation")
    torch.manual_seed(abs(int(cfg.seed)) % 2**63)
    kin = CMKinematics(case.cm_config)
    try:
        res.first = _register_first(case, cfg, stage)
        plan = _plan(case, res, kin, stage)
        _first_move(case, res, plan, kin, stage)
    except NavigationRefused as exc:
        return _refused(res, stage, exc, "navigation")
    if case.verification is not None:
        return verify(case, res, on_stage=on_stage, on_event=on_event)
    stage.emit("status", status=res.status, reason=res.reason)
    return res


def _register_first(case: NavigationCase, cfg: NavigationConfig, stage: _Stages) -> ViewSetRegistration:
    """Stages ``detect`` to ``cm``: the first images registered, the CM from the FBG reading's shape."""
    cp0 = (
        np.zeros(case.cm_config.n_control_points)
        if case.fbg_control_points_deg is None
        else np.asarray(case.fbg_control_points_deg, np.float64)
    )
    views = _detect(stage, case.views, cfg, prefix="", need=cfg.min_views)
    with navigation_refusals(""):
        first = register_view_set(
            views,
            case.volume,
            side=case.side,
            cm_config=case.cm_config,
            initial_control_points_deg=cp0,
            settings=cfg.view_set_settings(verification=False, fbg_sigma_deg=case.fbg_sigma_deg),
            seed=_stage_seed(cfg.seed, 0),
            recorder=stage.within(""),
        )
    stage.emit("registration", prefix="", registration=first)
    return first


def _plan(case: NavigationCase, res: NavigationResult, kin: CMKinematics, stage: _Stages) -> Plan:
    """Stage ``plan``: the plan as used (``res.plan``) and the CM's target in the femur frame
    (``res.femur_from_cm_target``; a free roll's turning the joints least)."""
    first = res.first
    assert first is not None
    with stage("plan") as rec:
        plan = case.plan
        if plan.control_points_deg is None:  # the CM keeps the shape it has now
            plan = dataclasses.replace(plan, control_points_deg=np.asarray(first.cm.control_points_deg))
        res.plan = plan
        rec.diagnostics["tip_target_ct_mm"] = plan.tip_target_world_mm.tolist()
        rec.diagnostics["roll_free"] = plan.roll_free
        if plan.roll_free:
            chosen = _least_motion_roll(case, first, plan, kin, res.config)
            res.femur_from_cm_target = chosen.femur_from_cm_target
            rec.diagnostics["roll_deg"] = chosen.roll_deg
        else:
            res.femur_from_cm_target = planned_femur_from_cm(plan, kinematics=kin)
    stage.emit(
        "plan",
        plan=plan,
        ct_from_femur=first.ct_from_femur,
        femur_from_cm_target=res.femur_from_cm_target,
    )
    return plan


def _first_move(
    case: NavigationCase, res: NavigationResult, plan: Plan, kin: CMKinematics, stage: _Stages
) -> None:
    """Stage ``robot``: the first move's command (eqs. 7–8, IK), measured and bounded."""
    first, target_cm = res.first, res.femur_from_cm_target
    assert first is not None and target_cm is not None
    with stage("robot") as rec:
        target, q = _command(case, first, case.joints_deg, target_cm, res.config, "robot")
        res.rbase_from_ee_target, res.joints_target_deg = target, q
        assert plan.control_points_deg is not None
        motion = measure_command(
            case.robot,
            case.joints_deg,
            q,
            ee_from_cm=case.ee_from_cm,
            tip_cm_mm=_tip_cm(kin, first.cm.control_points_deg),
            femur_from_cm_from=femur_from_cm_registered(first.ct_from_femur, first.ct_from_cm),
            femur_from_cm_to=target_cm,
            tip_to_cm_mm=_tip_cm(kin, plan.control_points_deg),
        )
        rec.diagnostics.update(motion.diagnostics())
        check_first_move(motion, res.config.safety, plan_name=plan.target_name)


def verify(
    case: NavigationCase,
    result: NavigationResult,
    *,
    on_stage: Callable[[str, str], None] | None = None,
    on_event: EventCallback | None = None,
) -> NavigationResult:
    """Register the verification views of ``case`` and command one correction (updates ``result``).

    The joint readings are checked against the command; the pelvis and femur are registered anew
    (the C-arm moved), the CM from the images' own starts and the kinematic prediction, then
    compared with the kinematics; the correction slides the registered CM so that its tip meets the
    plan, from the joints read with the verification images.

    Raises:
        ValueError: the case has no verification views, or ``result`` has no first registration.
    """
    if case.verification is None or result.first is None or result.femur_from_cm_target is None:
        raise ValueError("verify needs a case with verification views and a first registration")
    if result.status != "ok":
        return result
    stage = _Stages(result, on_stage, on_event)
    predicted, prior = _verification_prior(case, result)
    kin = CMKinematics(case.cm_config)
    try:
        _check_joint_readings(case, result, stage)
        ver = _register_verification(case, result, prior, stage)
        _correct(case, result, ver, predicted, kin, stage)
    except NavigationRefused as exc:
        log.warning("verification refused: %s", exc)
        result.refuse(exc)
    stage.emit("status", status=result.status, reason=result.reason)
    return result


def _verification_prior(case: NavigationCase, result: NavigationResult) -> tuple[np.ndarray, ViewSetPrior]:
    """Where the robot's kinematics say the CM went (femur frame; one start among the images' own,
    then compared), and the verification's prior with it (and its uncertainty where fused)."""
    assert case.verification is not None and result.first is not None
    assert result.femur_from_cm_target is not None
    cfg, first = result.config, result.first
    predicted = predicted_femur_from_cm(
        case.robot,
        case.joints_deg,
        case.verification.joints_deg,
        ee_from_cm=case.ee_from_cm,
        femur_from_cm=femur_from_cm_registered(first.ct_from_femur, first.ct_from_cm),
    )
    sigma = None
    if cfg.verification.fuse_kinematics:
        sigma = prediction_sigma_mm(
            case.robot,
            case.joints_deg,
            case.verification.joints_deg,
            ee_from_cm=case.ee_from_cm,
            uncertainty=cfg.verification.uncertainty,
        )
    target = result.femur_from_cm_target
    return predicted, ViewSetPrior(
        first.ct_from_femur, target, predicted, cfg.safety.max_motion_tip_mm, sigma
    )


def _check_joint_readings(case: NavigationCase, result: NavigationResult, stage: _Stages) -> None:
    """Stage ``verify_joints``: the joints read with the verification images against the command."""
    assert case.verification is not None
    with stage("verify_joints") as rec:
        if result.joints_target_deg is not None:
            dq = joint_motion_deg(result.joints_target_deg, case.verification.joints_deg)
            rec.diagnostics["reading_minus_command_deg"] = [float(x) for x in dq]
            check_joint_readings(dq, result.config.safety)


def _register_verification(
    case: NavigationCase, result: NavigationResult, prior: ViewSetPrior, stage: _Stages
) -> ViewSetRegistration:
    """Stages ``verify_detect`` to ``verify_cm``: the verification images registered
    (:func:`~fluoronav.navigation.verification.register_verification`)."""
    assert case.verification is not None and result.first is not None
    cfg = result.config
    undetected_ok = cfg.verification.register_undetected and prior.femur_from_cm_predicted is not None
    views = _detect(stage, case.verification.views, cfg, prefix="verify_", need=0 if undetected_ok else 1)
    views, local = moved_cameras(views, case.verification.views, result.first)
    undetected = all(v.detection is None for v in views)
    try:
        ver = register_verification(
            views,
            case,
            result,
            prior,
            local=local and cfg.verification.local_bones,
            seed=_stage_seed(cfg.seed, 1),
            recorder=stage.within("verify_"),
        )
    except NavigationRefused as exc:
        if not undetected:
            raise
        raise undetected_refused(views, exc) from exc
    if undetected:
        warning = undetected_warning(views)
        log.warning("%s", warning)
        result.warnings.append(warning)
    stage.emit("registration", prefix="verify_", registration=ver)
    result.verification = ver
    return ver


def _correct(
    case: NavigationCase,
    result: NavigationResult,
    ver: ViewSetRegistration,
    predicted: np.ndarray,
    kin: CMKinematics,
    stage: _Stages,
) -> None:
    """Stage ``correct``: the verification judged against the kinematics, then the corrective
    command from the verification joints, measured and bounded."""
    assert case.verification is not None and result.first is not None and result.plan is not None
    safety, plan, first = result.config.safety, result.plan, result.first
    with stage("correct") as rec:
        cm_diag = result.stages["verify_cm"].diagnostics
        rec.diagnostics["kinematics_disagreement_mm"] = float(cm_diag["motion_tip_mm"])
        verdict = judge_kinematics(cm_diag, ver.left_out, safety)
        if verdict.images_overrule:
            result.warnings.append(verdict.warning)
            rec.diagnostics["images_overrule"] = True
        tip_cm = _tip_cm(kin, ver.cm.control_points_deg)
        femur_from_cm_ver = femur_from_cm_registered(ver.ct_from_femur, ver.ct_from_cm)
        corr = tip_correction_target(femur_from_cm_ver, tip_cm, plan.tip_target_world_mm)
        result.correction_femur_from_cm_target = corr
        q_now = np.asarray(case.verification.joints_deg, np.float64)
        T, q = _command(case, ver, q_now, corr, result.config, "correct")
        result.rbase_from_ee_correction, result.joints_correction_deg = T, q
        motion = measure_command(
            case.robot,
            q_now,
            q,
            ee_from_cm=case.ee_from_cm,
            tip_cm_mm=tip_cm,
            femur_from_cm_from=femur_from_cm_ver,
            femur_from_cm_to=corr,
        )
        # how far the kinematics say the move left the tip from the plan (first registration's shape)
        predicted_tip = predicted[:3, :3] @ _tip_cm(kin, first.cm.control_points_deg) + predicted[:3, 3]
        predicted_error = float(np.linalg.norm(plan.tip_target_world_mm - predicted_tip))
        rec.diagnostics.update(motion.diagnostics())
        rec.diagnostics["predicted_tip_error_mm"] = predicted_error
        check_correction(
            motion,
            safety,
            plan_name=plan.target_name,
            predicted_tip_error_mm=predicted_error,
            images_overrule=verdict.images_overrule,
        )
