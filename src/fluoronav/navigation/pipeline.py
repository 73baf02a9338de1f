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
   gives none.
6. ``robot``: eqs. 7–8 and inverse kinematics near the joints read while imaging →
   ``rbase_from_ee_target``, ``joints_target_deg``.

With verification views (the images after the move): ``verify_detect``, ``verify_pelvis``,
``verify_femur``, ``verify_cm`` (the CM registered from the plan on the re-registered femur) and
``correct``: one corrective command from the verification joints that slides the registered CM so
that its tip meets the plan (:func:`~fluoronav.navigation.navigate.tip_correction_target`).

A stage that cannot go on (fewer than two views with a CM, the target out of the robot's reach)
ends the run with status ``"refused"`` and a reason naming the stage, the view and the check; no
robot command is given then.

Frames: ``ct`` (LPS, mm) throughout; ``femur`` is the CT frame moved with the femur
(``ct_from_femur``), the frame the plan is drawn in; ``carm_k`` is view k's C-arm camera frame.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from fluoronav.detection.centerline import extract_centerline
from fluoronav.detection.instrument import instrument_masks
from fluoronav.geometry import se3
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.manipulator.robot import wrap_deg
from fluoronav.navigation.case import CaseView, NavigationCase
from fluoronav.navigation.checks import motion_consistency, predicted_femur_from_cm, register_cm_checked
from fluoronav.navigation.navigate import (
    UnreachableTarget,
    femur_from_cm_registered,
    robot_target,
    tip_correction_target,
)
from fluoronav.navigation.planning import planned_femur_from_cm
from fluoronav.navigation.result import (
    NavigationConfig,
    NavigationRefused,
    NavigationResult,
    Registration,
    StageRecord,
    ViewDetection,
    navigation_cm_config,
)
from fluoronav.registration.bone import (
    BoneRegistrationResult,
    BoneView,
    bone_footprints,
    femur_config,
    register_femur,
    register_pelvis_per_view,
    views_in_ct_frame,
)
from fluoronav.registration.centerline import (
    MultiViewInitResult,
    centerline_initialize_multiview,
    multiview_start_poses,
)
from fluoronav.registration.cm import CMRegistrationResult, CMView

log = logging.getLogger(__name__)

__all__ = [
    "STAGES",
    "VERIFY_STAGES",
    "EventCallback",
    "NavigationConfig",
    "NavigationRefused",
    "NavigationResult",
    "Registration",
    "StageRecord",
    "ViewDetection",
    "navigate",
    "verify",
]

STAGES = ("detect", "pelvis", "femur", "cm", "plan", "robot")
VERIFY_STAGES = ("verify_detect", "verify_pelvis", "verify_femur", "verify_cm", "correct")


#: ``on_event(kind, data)``: what the pipeline tells a listener (e.g. a live link to a viewer) as
#: soon as it is known. Kinds and data: "views" (``prefix``, ``views``: the case's views of that
#: set), "registration" (``prefix``, ``registration``: a :class:`Registration`), "plan" (``plan``,
#: ``ct_from_femur``, ``femur_from_cm_target``), "status" (``status``, ``reason``; at the end of
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


@functools.lru_cache(maxsize=2)
def shipped_detector(device: str) -> Any:
    """The shipped CM detector on ``device`` (loaded once per process)."""
    from fluoronav.detection.detector import Detector

    return Detector.load(None, device=device)


def _band_mask(shape: tuple[int, int], ab: np.ndarray, half_width_px: float) -> np.ndarray:
    """(rows, cols) bool: pixels within ``half_width_px`` of the segment A–B."""
    rows, cols = shape
    v, u = np.mgrid[0:rows, 0:cols]
    p = np.stack([u, v], axis=-1).astype(np.float64)
    a, b = np.asarray(ab[0], np.float64), np.asarray(ab[1], np.float64)
    d = b - a
    t = np.clip(((p - a) @ d) / max(float(d @ d), 1e-12), 0.0, 1.0)
    return np.asarray(np.linalg.norm(p - (a + t[..., None] * d), axis=-1) <= half_width_px)


def _as_bool(x: np.ndarray) -> np.ndarray:
    return np.asarray(x, dtype=bool)


def detect_views(
    views: Sequence[CaseView], *, config: NavigationConfig
) -> tuple[list[ViewDetection | None], dict[str, Any]]:
    """Per view: the CM found (detector, or the case's landmarks), None where none is usable; and the
    per-view diagnostics (found, why not, confidence)."""
    out: list[ViewDetection | None] = []
    diag: dict[str, Any] = {}
    for v in views:
        if v.landmarks_px is not None:
            lm = np.asarray(v.landmarks_px, np.float64)
            if v.mask is not None:
                mask = _as_bool(v.mask)
            else:
                ps = v.camera.pixel_spacing_mm or 0.194
                mask = _band_mask(v.image.shape, lm, config.landmark_band_mm / ps)
            out.append(ViewDetection(lm, extract_centerline(mask, lm[0], lm[1]), mask, np.ones(2), "case"))
            diag[v.name] = {"found": True, "source": "case"}
            continue
        det = shipped_detector(config.device).detect(v.image, pixel_spacing_mm=v.camera.pixel_spacing_mm)
        if not det.usable or det.centerline_px is None:
            why = det.unusable_reason or "no centreline"
            log.warning("detector: %s in view %s; not used", why, v.name)
            out.append(None)
            diag[v.name] = {"found": False, "why": why}
            continue
        out.append(
            ViewDetection(
                np.asarray(det.landmarks_px, np.float64),
                np.asarray(det.centerline_px, np.float64),
                _as_bool(det.mask),
                np.asarray(det.landmark_confidence, np.float64),
                "detector",
            )
        )
        diag[v.name] = {
            "found": True,
            "source": "detector",
            "landmarks_px": np.asarray(det.landmarks_px).tolist(),
            "confidence": [float(c) for c in det.landmark_confidence],
        }
    return out, diag


def _bone_views(views: Sequence[CaseView], detections: Sequence[ViewDetection | None]) -> list[BoneView]:
    """The views for the bone registrations, the CM and its shaft left out of the similarity."""
    instruments = instrument_masks(
        [None if d is None else d.mask for d in detections],
        [None if d is None else d.centerline_px for d in detections],
        [v.image for v in views],
    )
    return [
        BoneView(np.asarray(v.image, np.float32), v.camera, None if m is None else ~_as_bool(m))
        for v, m in zip(views, instruments, strict=True)
    ]


def _cm_views(
    views: Sequence[CaseView], cameras_ct: Sequence[Camera], landmarks: Sequence[np.ndarray | None], tag: str
) -> list[CMView]:
    return [
        CMView(np.asarray(v.image, np.float32), c, landmarks_px=lm, name=f"{v.name}{tag}")
        for v, c, lm in zip(views, cameras_ct, landmarks, strict=True)
    ]


def _register(
    case: NavigationCase,
    views: Sequence[CaseView],
    stage: _Stages,
    config: NavigationConfig,
    *,
    prefix: str,
    seed: int,
    initial_ct_from_cm: Callable[[np.ndarray], np.ndarray] | None,
    initial_control_points_deg: np.ndarray,
    recovery_ct_from_cm: Callable[[np.ndarray], np.ndarray] | None = None,
    motion_check: Callable[[np.ndarray, CMRegistrationResult], dict[str, float]] | None = None,
    ct_from_femur_prior: np.ndarray | None = None,
    expected_ct_from_cm: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Registration:
    """Detection, pelvis per view, femur, CM in one set of views.

    ``initial_ct_from_cm``: None for the multi-view centreline initialisation, else a function of the
    registered ``ct_from_femur`` giving the CM start (verification: the plan on the new femur);
    ``recovery_ct_from_cm`` likewise, a second start tried where the first fails its checks;
    ``motion_check(ct_from_femur, cm)``: a further check of the CM against the robot's kinematics.
    ``ct_from_femur_prior``: the femur of an earlier registration (verification: the first); the
    femur starts there, and each view's pelvis is registered a second time with the femur's
    footprint left out (``config.verify_pelvis_refine``).
    ``expected_ct_from_cm``: a function of the registered ``ct_from_femur`` giving where the CM is
    expected (verification: where the robot's kinematics put it); detected landmarks far from its
    landmarks are left out of their triangulation.
    """
    with stage(f"{prefix}detect") as rec:
        stage.emit("views", prefix=prefix, views=tuple(views))
        detections, rec.diagnostics["views"] = detect_views(views, config=config)
        seen = [k for k, d in enumerate(detections) if d is not None]
        rec.diagnostics["views_detected"] = len(seen)
        need = config.min_views if initial_ct_from_cm is None else 1
        if len(seen) < need:
            missing = ", ".join(v.name for v, d in zip(views, detections, strict=True) if d is None)
            raise NavigationRefused(
                f"{prefix}detect",
                "views_with_cm",
                f"the CM was found in {len(seen)} of {len(views)} views, {need} needed",
                view=missing,
            )
    bone_views = _bone_views(views, detections)
    with stage(f"{prefix}pelvis") as rec:
        pelvis = register_pelvis_per_view(
            bone_views,
            case.volume,
            initial_world_from_patient=np.eye(4),
            config=replace(config.pelvis, device=config.device),
            seed=seed + 2,
        )
        rec.diagnostics["views"] = {
            v.name: {"cost": float(r.cost), "converged": bool(r.converged), "reason": r.reason}
            for v, r in zip(views, pelvis, strict=True)
        }
        if ct_from_femur_prior is not None and config.verify_pelvis_refine is not None:
            pelvis = _pelvis_without_femur(
                case, bone_views, pelvis, ct_from_femur_prior, config, seed=seed + 4, record=rec.diagnostics
            )
    views_ct = views_in_ct_frame(bone_views, pelvis)
    cams_ct = [bv.camera for bv in views_ct]
    with stage(f"{prefix}femur") as rec:
        femur = register_femur(
            views_ct,
            case.volume,
            side=case.side,
            world_from_patient=np.eye(4),
            config=replace(config.femur or femur_config(views=len(views_ct)), device=config.device),
            seed=seed + 3,
            initial_world_from_femur=ct_from_femur_prior,
        )
        rec.diagnostics.update(cost=float(femur.cost), converged=bool(femur.converged), reason=femur.reason)
    with stage(f"{prefix}cm") as rec:
        init: MultiViewInitResult | None = None
        lm_views: list[np.ndarray | None] = [None if d is None else d.landmarks_px for d in detections]
        if len(seen) >= 2:
            # landmarks triangulated over the views; one that disagrees with the others (a
            # detection of A where the CM leaves the image, say) gives way to the consensus, in the
            # registration's ROI and landmark prior as in its start
            init = centerline_initialize_multiview(
                [cams_ct[k] for k in seen],
                np.stack([detections[k].landmarks_px for k in seen]),  # type: ignore[union-attr]
                [detections[k].centerline_px for k in seen],  # type: ignore[union-attr]
                initial_control_points_deg,
                config=case.cm_config,
                landmark_confidence=np.stack([detections[k].confidence for k in seen]),  # type: ignore[union-attr]
                landmark_prior_world=None
                if expected_ct_from_cm is None
                else se3.apply(
                    expected_ct_from_cm(femur.world_from_bone),
                    CMKinematics(case.cm_config)
                    .landmarks_cm(torch.as_tensor(initial_control_points_deg, dtype=torch.float64))
                    .numpy(),
                ),
            )
            for i, k in enumerate(seen):
                lm_views[k] = init.landmarks_px[i]
            rec.diagnostics["init_cost_px"] = float(init.cost_px)
            rec.diagnostics["landmarks_replaced"] = int((~np.asarray(init.landmark_inliers)).sum())
        if initial_ct_from_cm is None:
            assert init is not None  # detection needs two views for the first registration
            tries = [multiview_start_poses(init, max_starts=config.max_cm_starts)]
        else:
            tries = [[initial_ct_from_cm(femur.world_from_bone)]]
        if recovery_ct_from_cm is not None:  # a second start, tried only where the first fails
            tries.append([recovery_ct_from_cm(femur.world_from_bone)])
        tag = f" ({prefix.rstrip('_')})" if prefix else ""
        verification = ct_from_femur_prior is not None
        cm_settings = (config.verify_cm if verification else config.cm) or navigation_cm_config()
        cm = register_cm_checked(
            _cm_views(views, cams_ct, lm_views, tag),
            lm_views,
            tries,
            rec,
            stage_name=f"{prefix}cm",
            initial_control_points_deg=initial_control_points_deg,
            cm_config=cm_settings.with_(device=config.device, cm_config=case.cm_config),
            safety=config.safety,
            seed=seed + 5,
            motion_check=None
            if motion_check is None
            else functools.partial(motion_check, femur.world_from_bone),
        )
    reg = Registration(
        views=tuple(views),
        detections=tuple(detections),
        pelvis=tuple(pelvis),
        cameras_ct=tuple(cams_ct),
        femur=femur,
        cm=cm,
        cm_init=init,
    )
    stage.emit("registration", prefix=prefix, registration=reg)
    return reg


def _pelvis_without_femur(
    case: NavigationCase,
    bone_views: Sequence[BoneView],
    pelvis: Sequence[BoneRegistrationResult],
    ct_from_femur: np.ndarray,
    config: NavigationConfig,
    *,
    seed: int,
    record: dict[str, Any],
) -> list[BoneRegistrationResult]:
    """Each view's pelvis again, from its first result, with the femur's footprint (the femur at
    ``ct_from_femur``, seen through that result's camera) left out of the similarity."""
    assert config.verify_pelvis_refine is not None
    cams = [r.camera_from_bone[0] for r in pelvis]
    head = np.asarray(case.volume.landmarks_world[f"femoral_head_{case.side}"], np.float64)
    femur = bone_footprints(
        [v.camera for v in bone_views],
        case.volume,
        f"femur_{case.side}",
        np.stack([c @ ct_from_femur for c in cams]),
        margin_mm=config.femur_margin_mm,
        center_bone_mm=head,
    )
    views = [
        BoneView(v.image, v.camera, ~f if v.mask is None else (_as_bool(v.mask) & ~f))
        for v, f in zip(bone_views, femur, strict=True)
    ]
    again = register_pelvis_per_view(
        views,
        case.volume,
        initial_world_from_patient=np.stack([r.world_from_bone for r in pelvis]),
        config=replace(config.verify_pelvis_refine, device=config.device),
        seed=seed,
    )
    for name, f, r in zip(record["views"], femur, again, strict=True):
        record["views"][name].update(
            femur_left_out=float(f.mean()), cost_without_femur=float(r.cost), reason_without_femur=r.reason
        )
    return again


def _stage_seed(seed: int, k: int) -> int:
    """Optimiser seed of registration set k from the user's seed (any size; CMA-ES takes < 2³²)."""
    return int(np.random.SeedSequence(abs(int(seed))).generate_state(k + 1)[k]) % 2**31


def _command(
    case: NavigationCase,
    reg: Registration,
    joints_deg: np.ndarray,
    femur_from_cm_target: np.ndarray,
    config: NavigationConfig,
    stage_name: str,
) -> tuple[np.ndarray, np.ndarray]:
    """Eqs. 7–8 + IK from the registration in its view 0; refuses an unreachable target."""
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
    torch.manual_seed(abs(int(cfg.seed)) % 2**63)
    kin = CMKinematics(case.cm_config)
    cp0 = (
        np.zeros(case.cm_config.n_control_points)
        if case.fbg_control_points_deg is None
        else np.asarray(case.fbg_control_points_deg, np.float64)
    )
    try:
        first = _register(
            case,
            case.views,
            stage,
            cfg,
            prefix="",
            seed=_stage_seed(cfg.seed, 0),
            initial_ct_from_cm=None,
            initial_control_points_deg=cp0,
        )
        res.first = first
        with stage("plan") as rec:
            plan = case.plan
            if plan.control_points_deg is None:  # the CM keeps the shape it has now
                plan = dataclasses.replace(plan, control_points_deg=np.asarray(first.cm.control_points_deg))
            res.plan = plan
            res.femur_from_cm_target = planned_femur_from_cm(plan, kinematics=kin)
            rec.diagnostics["tip_target_ct_mm"] = plan.tip_target_world_mm.tolist()
        stage.emit(
            "plan",
            plan=plan,
            ct_from_femur=first.ct_from_femur,
            femur_from_cm_target=res.femur_from_cm_target,
        )
        with stage("robot") as rec:
            target, q = _command(case, first, case.joints_deg, res.femur_from_cm_target, cfg, "robot")
            res.rbase_from_ee_target, res.joints_target_deg = target, q
            rec.diagnostics["joint_motion_deg"] = float(np.max(np.abs(wrap_deg(q - case.joints_deg))))
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

    The pelvis and femur are registered anew (the C-arm moved), the CM from the plan on the new
    femur; the correction slides the registered CM so that its tip meets the plan, from the joints
    read with the verification images.

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
    # where the robot's kinematics say the CM went: a second start, the gate of the detected landmarks
    # and a check of the verification
    predicted = predicted_femur_from_cm(case, first, case.verification.joints_deg)

    def kinematic_ct_from_cm(ct_from_femur: np.ndarray) -> np.ndarray:
        return ct_from_femur @ predicted

    kin = CMKinematics(case.cm_config)
    try:
        ver = _register(
            case,
            case.verification.views,
            stage,
            cfg,
            prefix="verify_",
            seed=_stage_seed(cfg.seed, 1),
            initial_ct_from_cm=lambda ct_from_femur: ct_from_femur @ target,
            initial_control_points_deg=np.asarray(result.first.cm.control_points_deg),
            recovery_ct_from_cm=kinematic_ct_from_cm,
            motion_check=functools.partial(motion_consistency, case, first),
            ct_from_femur_prior=first.ct_from_femur,
            expected_ct_from_cm=kinematic_ct_from_cm,
        )
        result.verification = ver
        with stage("correct") as rec:
            tip_cm = kin.tip_cm(torch.as_tensor(ver.cm.control_points_deg, dtype=torch.float64)).numpy()
            corr = tip_correction_target(
                femur_from_cm_registered(ver.ct_from_femur, ver.ct_from_cm), tip_cm, plan.tip_target_world_mm
            )
            result.correction_femur_from_cm_target = corr
            q_now = np.asarray(case.verification.joints_deg, np.float64)
            T, q = _command(case, ver, q_now, corr, cfg, "correct")
            result.rbase_from_ee_correction, result.joints_correction_deg = T, q
            rec.diagnostics["joint_motion_deg"] = float(np.max(np.abs(wrap_deg(q - q_now))))
    except NavigationRefused as exc:
        log.warning("verification refused: %s", exc)
        result.refuse(exc)
    stage.emit("status", status=result.status, reason=result.reason)
    return result
