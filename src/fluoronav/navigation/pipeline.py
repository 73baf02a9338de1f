"""The navigation pipeline: from a navigation case to a robot command (``fluoronav navigate``).

Stages, each timed and recorded with its diagnostics (:class:`StageRecord`):

1. ``detect``: per view, the CM mask, landmarks A and B and centreline: the shipped detector, or the
   landmarks (and mask) the case gives for that view.
2. ``pelvis``: the pelvis registered to each view alone; each view's ``camera_from_ct`` follows, and
   with it the views' relative geometry (§II-C). The CM and its shaft are left out of the bone
   similarity.
3. ``femur``: the femur registered to all views (rotation about the femoral head) →
   ``ct_from_femur``, the femur's pose relative to where the CT shows it.
4. ``cm``: the landmarks triangulated over the views, a scan of the roll about them scored by the
   centrelines (multi-view centreline initialisation), then multi-view CM registration (pose and
   shape) in the CT frame from the best one or two roll minima.
5. ``plan``: the planned CM pose in the femur frame, with the CM's registered shape where the plan
   gives none. Where the plan leaves the CM's roll free, the roll whose command turns the joints
   least (:func:`~fluoronav.navigation.targeting.least_motion_target`).
6. ``robot``: eqs. 7–8 and inverse kinematics near the joints read while imaging →
   ``rbase_from_ee_target``, ``joints_target_deg``; the command measured and bounded
   (:mod:`fluoronav.navigation.commands`).

With verification views (the images after the move, one to three): ``verify_joints`` (the joints
read with them against the command), ``verify_detect``, ``verify_pelvis``, ``verify_femur``,
``verify_cm`` and ``correct``. Where the case says which first view's C-arm position each view was
taken from and how the C-arm moved since (``CaseView.moved_from``), each camera starts from that
view's registered camera moved by it and the bones need only their local levels; where no C-arm
moved and the bones' images agree with the first ones, the first registration's bones are kept
(:mod:`~fluoronav.registration.view_set.unmoved`). The CM is registered from the robot's kinematic
prediction, the views' checks judging it (with one view only where its landmarks agree with the
prediction), else from the images' own starts; its tip is then fused with the prediction, each
weighted by its stated uncertainty (:mod:`~fluoronav.navigation.kinematic_prior`,
:mod:`~fluoronav.registration.view_set.fusion`), where the two are consistent. ``correct``: the
registered CM compared with the robot's kinematics (a disagreement is refused or, where the images
are unambiguous, overruled with a warning: :mod:`~fluoronav.navigation.checks.safety`), then one
corrective command from the verification joints that slides the registered CM so that its tip
meets the plan (:func:`~fluoronav.navigation.targeting.tip_correction_target`), measured and
bounded as the first move is.

Stages 2–4 are :func:`~fluoronav.registration.view_set.register_view_set`, for the verification
with the first registration and the robot's kinematics as its prior
(:class:`~fluoronav.registration.view_set.ViewSetPrior`).

A stage that cannot go on (fewer than two views with a CM, the target out of the robot's reach, a
command beyond a bound of :class:`~fluoronav.navigation.checks.safety.SafetyConfig`) ends the run with
status ``"refused"`` and a reason naming the stage, the view and the check; no robot command is
given then.

Frames: ``ct`` (LPS, mm) throughout; ``femur`` is the CT frame moved with the femur
(``ct_from_femur``), the frame the plan is drawn in; ``carm_k`` is view k's C-arm camera frame.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
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
)
from fluoronav.navigation.detect import detect_views
from fluoronav.navigation.kinematic_prior import prediction_sigma_mm
from fluoronav.navigation.planning import Plan, planned_femur_from_cm
from fluoronav.navigation.result import (
    NavigationConfig,
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
from fluoronav.registration.stages import StageRecorder
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


class _Stages:
    """Times stages into ``result.stages`` and reports them to callbacks (progress displays and
    listeners); a listener that fails is logged and never stops the navigation."""

    def __init__(
        self,
        result: NavigationResult,
        on_stage: Callable[[str, str], None] | None,
        on_event: EventCallback | None = None,
    ) -> None:
        self.result, self.on_stage, self.on_event = result, on_stage, on_event

    def emit(self, kind: str, **data: Any) -> None:
        if self.on_event is None:
            return
        try:
            self.on_event(kind, data)
        except Exception:  # a listener must not cost the navigation its result
            log.exception("navigation listener failed on %r", kind)

    @contextmanager
    def __call__(self, name: str) -> Iterator[StageRecord]:
        rec = self.result.stages.setdefault(name, StageRecord())
        if self.on_stage is not None:
            self.on_stage(name, "start")
        t0 = time.perf_counter()
        try:
            yield rec
        finally:
            rec.seconds = time.perf_counter() - t0
            if self.on_stage is not None:
                self.on_stage(name, "done")

    def within(self, prefix: str) -> StageRecorder:
        """The recorder of a registration's stages, named ``prefix + stage``."""
        return lambda name: self(prefix + name)


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
        log.warning("navigation refused: %s", exc)
        res.refuse(exc)
        stage.emit("status", status=res.status, reason=res.reason)
        return res
    torch.manual_seed(abs(int(cfg.seed)) % 2**63)
    kin = CMKinematics(case.cm_config)
    cp0 = (
        np.zeros(case.cm_config.n_control_points)
        if case.fbg_control_points_deg is None
        else np.asarray(case.fbg_control_points_deg, np.float64)
    )
    try:
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
        res.first = first
        with stage("plan") as rec:
            plan = case.plan
            if plan.control_points_deg is None:  # the CM keeps the shape it has now
                plan = dataclasses.replace(plan, control_points_deg=np.asarray(first.cm.control_points_deg))
            res.plan = plan
            rec.diagnostics["tip_target_ct_mm"] = plan.tip_target_world_mm.tolist()
            rec.diagnostics["roll_free"] = plan.roll_free
            if plan.roll_free:
                chosen = _least_motion_roll(case, first, plan, kin, cfg)
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
        with stage("robot") as rec:
            target, q = _command(case, first, case.joints_deg, res.femur_from_cm_target, cfg, "robot")
            res.rbase_from_ee_target, res.joints_target_deg = target, q
            assert plan.control_points_deg is not None
            motion = measure_command(
                case.robot,
                case.joints_deg,
                q,
                ee_from_cm=case.ee_from_cm,
                tip_cm_mm=_tip_cm(kin, first.cm.control_points_deg),
                femur_from_cm_from=femur_from_cm_registered(first.ct_from_femur, first.ct_from_cm),
                femur_from_cm_to=res.femur_from_cm_target,
                tip_to_cm_mm=_tip_cm(kin, plan.control_points_deg),
            )
            rec.diagnostics.update(motion.diagnostics())
            check_first_move(motion, cfg.safety, plan_name=plan.target_name)
    except NavigationRefused as exc:
        log.warning("navigation refused: %s", exc)
        res.refuse(exc)
        stage.emit("status", status=res.status, reason=res.reason)
        return res
    if case.verification is not None:
        return verify(case, res, on_stage=on_stage, on_event=on_event)
    stage.emit("status", status=res.status, reason=res.reason)
    return res


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
    cfg = result.config
    stage = _Stages(result, on_stage, on_event)
    plan = result.plan
    assert plan is not None
    target = result.femur_from_cm_target
    first = result.first
    # where the robot's kinematics say the CM went: one start among the images' own, then compared
    predicted = predicted_femur_from_cm(
        case.robot,
        case.joints_deg,
        case.verification.joints_deg,
        ee_from_cm=case.ee_from_cm,
        femur_from_cm=femur_from_cm_registered(first.ct_from_femur, first.ct_from_cm),
    )
    vcfg = cfg.verification
    sigma = None
    if vcfg.fuse_kinematics:
        sigma = prediction_sigma_mm(
            case.robot,
            case.joints_deg,
            case.verification.joints_deg,
            ee_from_cm=case.ee_from_cm,
            uncertainty=vcfg.uncertainty,
        )
    prior = ViewSetPrior(first.ct_from_femur, target, predicted, cfg.safety.max_motion_tip_mm, sigma)
    kin = CMKinematics(case.cm_config)
    try:
        with stage("verify_joints") as rec:
            if result.joints_target_deg is not None:
                dq = joint_motion_deg(result.joints_target_deg, case.verification.joints_deg)
                rec.diagnostics["reading_minus_command_deg"] = [float(x) for x in dq]
                check_joint_readings(dq, cfg.safety)
        views = _detect(stage, case.verification.views, cfg, prefix="verify_", need=1)
        views, local = moved_cameras(views, case.verification.views, first)
        ver = register_verification(
            views,
            case,
            result,
            prior,
            local=local and vcfg.local_bones,
            seed=_stage_seed(cfg.seed, 1),
            recorder=stage.within("verify_"),
        )
        stage.emit("registration", prefix="verify_", registration=ver)
        result.verification = ver
        with stage("correct") as rec:
            cm_diag = result.stages["verify_cm"].diagnostics
            rec.diagnostics["kinematics_disagreement_mm"] = float(cm_diag["motion_tip_mm"])
            verdict = judge_kinematics(cm_diag, ver.left_out, cfg.safety)
            if verdict.images_overrule:
                result.warnings.append(verdict.warning)
                rec.diagnostics["images_overrule"] = True
            tip_cm = _tip_cm(kin, ver.cm.control_points_deg)
            femur_from_cm_ver = femur_from_cm_registered(ver.ct_from_femur, ver.ct_from_cm)
            corr = tip_correction_target(femur_from_cm_ver, tip_cm, plan.tip_target_world_mm)
            result.correction_femur_from_cm_target = corr
            q_now = np.asarray(case.verification.joints_deg, np.float64)
            T, q = _command(case, ver, q_now, corr, cfg, "correct")
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
                cfg.safety,
                plan_name=plan.target_name,
                predicted_tip_error_mm=predicted_error,
                images_overrule=verdict.images_overrule,
            )
    except NavigationRefused as exc:
        log.warning("verification refused: %s", exc)
        result.refuse(exc)
    stage.emit("status", status=result.status, reason=result.reason)
    return result
