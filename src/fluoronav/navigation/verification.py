"""The verification's view set: the images after the move registered with the first registration
and the robot's kinematics as their prior (stages ``verify_pelvis``, ``verify_femur``, ``verify_cm``).

Where the case says which first view's C-arm position each verification view was taken from and how
the C-arm moved since (``CaseView.moved_from``), each camera starts from that view's registered
camera moved by it (:func:`moved_cameras`); with ``VerificationConfig.local_bones`` the bones then
need only their local levels, and where no C-arm and no anatomy moved the first registration's
bones are kept (:mod:`~fluoronav.registration.view_set.unmoved`). Where the detections' CM lies far
from the kinematic prediction, the images decide which is wrong (:mod:`~.disagreement`): a wrong
detection is named (the CM registered at the prediction used where it passes every check), else the
kinematics are; one view says it cannot tell (:mod:`~fluoronav.navigation.commands`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fluoronav.errors import RegistrationRefused
from fluoronav.geometry.camera import Camera
from fluoronav.navigation.case.model import CaseView, NavigationCase
from fluoronav.navigation.commands import (
    at_prediction_said,
    name_kinematics_disagreement,
    name_one_view_disagreement,
    refuse_wrong_detection,
    view_check_warning,
    wrong_detection_warning,
)
from fluoronav.navigation.config import NavigationConfig
from fluoronav.navigation.disagreement import ImagesAtPrediction, images_side_with, register_at_prediction
from fluoronav.navigation.result import (
    NavigationRefused,
    NavigationResult,
    navigation_refusals,
)
from fluoronav.registration.cm.checks import PredictedCMPose
from fluoronav.registration.stages import StageRecorder
from fluoronav.registration.view_set import (
    FluoroView,
    ViewSetBones,
    ViewSetPrior,
    ViewSetRegistration,
    ViewSetSeeds,
    ViewSetSettings,
    bone_views,
    register_view_set,
    register_view_set_bones,
)
from fluoronav.registration.view_set.unmoved import unmoved_bones

log = logging.getLogger(__name__)

__all__ = ["moved_cameras", "register_verification"]

#: the refusals that name a cause no second registration of the bones changes
_FINAL_CHECKS = ("kinematics_disagree", "detection_disagrees", "detection_or_kinematics")
#: a view's checks of the CM registration, which a wrong detection in that view can fail
_VIEW_CHECKS = ("landmark_residual", "edge_ncc")
#: the CM registration's name of a verification view (``register_view_set``'s ``name``)
_TAG = " (verify)"


def register_verification(
    views: list[FluoroView],
    case: NavigationCase,
    result: NavigationResult,
    prior: ViewSetPrior,
    *,
    local: bool,
    seed: int,
    recorder: StageRecorder,
) -> ViewSetRegistration:
    """The verification's view set registered: with ``local``, the bones from the cameras moved by
    the C-arm's motion with their local levels (or kept, where nothing moved), and where that
    registration refuses, once more with the whole ladders; otherwise with the whole ladders.

    Notes:
        The local levels trust the C-arm's nominal motion and the first registration. Where a
        view's camera started off by more than they can recover, the failure shows in the CM's
        checks (or the bones'), not before; the whole ladders then decide, as without ``local``.
        A refusal that names a cause (the kinematics, a wrong detection, one view that cannot tell
        them apart: :func:`_cause_named`) is final: no bone registration changes where the robot
        put the CM or what the detector found. The first attempt's stages are kept as
        ``verify_local_*``.
    """
    assert case.verification is not None and result.first is not None
    cfg, first = result.config, result.first
    diag = result.stages["verify_detect"].diagnostics
    diag["cameras_from_carm_motion"] = local
    known = _unmoved(views, case.verification.views, first, cfg, result) if local else None

    def register(local_now: bool) -> ViewSetRegistration:
        settings = cfg.view_set_settings(verification=True, local=local_now, n_views=len(views))
        attempt = _Attempt(views, case, result, prior, settings, seed, known if local_now else None)
        try:
            with navigation_refusals("verify_"):
                reg = register_view_set(
                    views,
                    case.volume,
                    side=case.side,
                    cm_config=case.cm_config,
                    initial_control_points_deg=np.asarray(first.cm.control_points_deg),
                    settings=settings,
                    seed=seed,
                    prior=prior,
                    name="verify",
                    recorder=recorder,
                    known_bones=attempt.known,
                )
        except NavigationRefused as exc:
            return _cause_named(exc, attempt)
        return _detections_judged(reg, attempt)

    if not local:
        return register(False)
    try:
        return register(True)
    except NavigationRefused as exc:
        if exc.check in _FINAL_CHECKS:
            raise
        log.warning("the verification with local bones refused (%s): the whole ladders", exc)
        diag["local_bones_refused"] = str(exc)
        for name in ("pelvis", "femur", "cm"):
            if f"verify_{name}" in result.stages:
                result.stages[f"verify_local_{name}"] = result.stages.pop(f"verify_{name}")
        return register(False)


@dataclass(frozen=True, eq=False)
class _Attempt:
    """One registration of the verification's views: what it was given (``known``: the bones kept
    from the first registration, or None)."""

    views: list[FluoroView]
    case: NavigationCase
    result: NavigationResult
    prior: ViewSetPrior
    settings: ViewSetSettings
    seed: int
    known: ViewSetBones | None

    @property
    def cm_diagnostics(self) -> dict[str, Any]:
        return self.result.stages["verify_cm"].diagnostics

    def predicted(self, ct_from_femur: np.ndarray) -> PredictedCMPose | None:
        """The kinematic prediction placed by the verification's femur; None without one."""
        p = self.prior
        if p.femur_from_cm_predicted is None:
            return None
        return PredictedCMPose(ct_from_femur, p.femur_from_cm_predicted, p.max_motion_tip_mm)

    def at_prediction(
        self, views: Sequence[FluoroView], cameras: Sequence[Camera], predicted: PredictedCMPose
    ) -> ImagesAtPrediction:
        """The CM registered at the prediction on the images alone
        (:func:`~fluoronav.navigation.disagreement.register_at_prediction`), recorded in the
        ``verify_cm`` stage (``at_prediction``, with what the images side with)."""
        assert self.result.first is not None and self.settings.cm_checks is not None
        at = register_at_prediction(
            [dataclasses.replace(v, name=v.name + _TAG) for v in views],
            cameras,
            predicted,
            control_points_deg=np.asarray(self.result.first.cm.control_points_deg),
            cm_config=self.case.cm_config,
            settings=self.settings,
            seed=ViewSetSeeds.from_seed(self.seed).cm,
        )
        side = images_side_with(at, self.settings.cm_checks, self.result.config.safety)
        self.cm_diagnostics["at_prediction"] = {**at.to_dict(), "images_side_with": side}
        log.info("the CM registered at the kinematic prediction: the images side with %s", side)
        return at


def _cause_named(exc: NavigationRefused, attempt: _Attempt) -> ViewSetRegistration:
    """After the verification's CM refused: where its detections lie more than ``max_motion_tip_mm``
    from the kinematic prediction (``prediction_gap_mm``), one view cannot tell; otherwise the
    bones again (the same views, settings and seeds: the same bones) and the CM registered at the
    prediction decide. A wrong detection is refused naming it, or gone on with (the CM at the
    prediction, where it passed every check); else the kinematics are named where the views agree
    (:func:`~fluoronav.navigation.commands.name_kinematics_disagreement`) or ``exc`` stands. Where
    the detections agree with the prediction and a view's check refused: :func:`_view_check_judged`.

    Raises:
        NavigationRefused: the refusal, named.
    """
    safety = attempt.result.config.safety
    if exc.stage != "verify_cm" or "verify_cm" not in attempt.result.stages:
        raise exc
    if all(v.detection is None for v in attempt.views):  # no detection to disagree with
        raise exc
    diag = attempt.cm_diagnostics
    gap = float(diag.get("prediction_gap_mm", float("nan")))
    if gap <= safety.max_motion_tip_mm:
        return _view_check_judged(exc, attempt)
    if not gap > safety.max_motion_tip_mm:  # not measured
        raise exc
    if len(attempt.views) == 1:
        raise _named(name_one_view_disagreement(exc, diag, safety), exc)
    placed = _placed(attempt)
    if placed is None:  # as without the images' decision
        raise _named(name_kinematics_disagreement(exc, diag, safety), exc)
    if len(placed[2]) == 1:
        raise _named(name_one_view_disagreement(exc, diag, safety), exc)
    registration, at = _registered_at_prediction(attempt, *placed)
    if diag["at_prediction"]["images_side_with"] == "detection":
        return _go_on_at_prediction(registration, at, attempt, gap)
    evidence = ""
    if diag["at_prediction"]["images_side_with"] == "kinematics":
        assert attempt.settings.cm_checks is not None
        evidence = at_prediction_said(diag["at_prediction"], attempt.settings.cm_checks.min_edge_ncc)
    raise _named(name_kinematics_disagreement(exc, diag, safety, evidence=evidence), exc)


def _view_check_judged(exc: NavigationRefused, attempt: _Attempt) -> ViewSetRegistration:
    """After the verification's CM refused on a view's check (``landmark_residual``, ``edge_ncc``)
    where its detections agree with the kinematic prediction: the CM registered at the prediction
    on the images alone decides. Where it passes every view's check and stays at the prediction,
    the verification goes on with it (a wrong detection named, :func:`_go_on_at_prediction`);
    otherwise ``exc`` stands.

    Raises:
        NavigationRefused: ``exc``, or ``detection_disagrees`` where going on is switched off.
    """
    safety, checks = attempt.result.config.safety, attempt.settings.cm_checks
    assert checks is not None
    if exc.check not in _VIEW_CHECKS:
        raise exc
    placed = _placed(attempt)
    if placed is None or len(placed[2]) < safety.detection_check_min_views:
        raise exc
    registration, at = _registered_at_prediction(attempt, *placed)
    if at.motion_tip_mm > safety.max_motion_tip_mm or len(at.fitting(checks)) < len(at.edge_ncc):
        raise exc
    gap = float(attempt.cm_diagnostics["prediction_gap_mm"])
    return _go_on_at_prediction(registration, at, attempt, gap, failed=exc)


def _placed(attempt: _Attempt) -> tuple[ViewSetBones, PredictedCMPose, list[FluoroView]] | None:
    """The verification's bones (:func:`_bones`), the kinematic prediction placed by their femur and
    the views they kept; None where the bones refuse or there is no prediction."""
    bones = _bones(attempt)
    predicted = None if bones is None else attempt.predicted(bones.femur.world_from_bone)
    if bones is None or predicted is None:
        return None
    views = attempt.views if bones.kept is None else [attempt.views[k] for k in bones.kept]
    return bones, predicted, views


def _registered_at_prediction(
    attempt: _Attempt, bones: ViewSetBones, predicted: PredictedCMPose, views: list[FluoroView]
) -> tuple[ViewSetRegistration, ImagesAtPrediction]:
    """The registration of ``views`` in ``bones`` with the CM registered at ``predicted`` on their
    images alone (:meth:`_Attempt.at_prediction`), and that CM judged view by view."""
    at = attempt.at_prediction(views, bones.cameras, predicted)
    registration = ViewSetRegistration(
        views=tuple(views),
        pelvis=bones.pelvis,
        cameras_ct=bones.cameras,
        femur=bones.femur,
        cm=at.cm,
        left_out=dict(bones.left_out),
    )
    return registration, at


def _named(named: NavigationRefused, exc: NavigationRefused) -> NavigationRefused:
    """``named``, raised from ``exc`` where it is another refusal."""
    if named is not exc:
        named.__cause__ = exc
    return named


def _bones(attempt: _Attempt) -> ViewSetBones | None:
    """The bones the attempt's CM was registered in: the known ones, or registered again as
    ``register_view_set`` registered them (None where they refuse now)."""
    if attempt.known is not None:
        return attempt.known
    views = attempt.views
    try:
        return register_view_set_bones(
            bone_views(views),
            attempt.case.volume,
            side=attempt.case.side,
            names=[v.name for v in views],
            settings=attempt.settings,
            seeds=ViewSetSeeds.from_seed(attempt.seed),
            prior_ct_from_femur=attempt.prior.ct_from_femur,
        )
    except RegistrationRefused as exc:
        log.warning("the verification's bones registered again refused (%s)", exc)
        return None


def _detections_judged(reg: ViewSetRegistration, attempt: _Attempt) -> ViewSetRegistration:
    """The verification's registration, where its CM lies more than ``max_motion_tip_mm`` from the
    kinematic prediction in two or more views, judged against the CM registered at the prediction:
    a wrong detection is refused naming it, or gone on with (:func:`_go_on_at_prediction`); ``reg``
    otherwise (the kinematics are judged in the ``correct`` stage,
    :func:`~fluoronav.navigation.commands.judge_kinematics`)."""
    diag = attempt.cm_diagnostics
    tip_mm = float(diag.get("motion_tip_mm", float("nan")))
    predicted = attempt.predicted(reg.ct_from_femur)
    if not tip_mm > attempt.result.config.safety.max_motion_tip_mm or len(reg.views) < 2 or predicted is None:
        return reg
    at = attempt.at_prediction(reg.views, reg.cameras_ct, predicted)
    if diag["at_prediction"]["images_side_with"] != "detection":
        return reg
    return _go_on_at_prediction(dataclasses.replace(reg, cm=at.cm), at, attempt, tip_mm)


def _go_on_at_prediction(
    registration: ViewSetRegistration,
    at: ImagesAtPrediction,
    attempt: _Attempt,
    gap_mm: float,
    *,
    failed: NavigationRefused | None = None,
) -> ViewSetRegistration:
    """``registration`` (its CM the one at the prediction) where that CM passed every view's check
    and the settings allow (``VerificationConfig.go_on_at_prediction``): the ``verify_cm`` stage
    then records it (the detections' registration under ``from_detections``, the views whose
    detections are off under ``detection_disagrees``) and the result warns. Otherwise refused.
    ``failed``: the refusal of the detections' registration on a view's check, where the
    detections agree with the prediction (:func:`_view_check_judged`); it is said in the warning,
    and stands where no detection lies off.

    Raises:
        NavigationRefused: check ``detection_disagrees``, naming the views and how far off; or
            ``failed``.
    """
    result, checks = attempt.result, attempt.settings.cm_checks
    assert checks is not None
    off = at.detections_off(checks)
    diag = attempt.cm_diagnostics
    diag["detection_disagrees"] = off
    unfit = [n for n in at.edge_ncc if n not in at.fitting(checks)]
    why = ""
    if unfit:
        why = f"the CM there fails the edge check in {', '.join(unfit)}"
    elif not result.config.verification.go_on_at_prediction:
        why = "verification.go_on_at_prediction is off"
    if why and (off or failed is None):
        raise refuse_wrong_detection(off, gap_mm, result.config.safety, why=why, failed=failed)
    if why:
        assert failed is not None
        raise failed
    moved = ("views", "views_used", "tries", "left_out", "cost", "converged", "reason", "motion_tip_mm",
             "motion_rotation_deg", "image_motion_tip_mm")  # fmt: skip
    diag["from_detections"] = {k: diag.pop(k) for k in moved if k in diag}
    diag.update(
        views={n: {"landmark_residual_mm": None, "edge_ncc": ncc} for n, ncc in at.edge_ncc.items()},
        views_used=list(at.edge_ncc),
        motion_tip_mm=at.motion_tip_mm,
        motion_rotation_deg=at.motion_rotation_deg,
        cost=float(at.cm.cost),
        converged=bool(at.cm.converged),
        reason=at.cm.reason,
    )
    result.stages["verify_cm"].passed = True
    warning = (
        wrong_detection_warning(off, gap_mm, result.config.safety, failed=failed)
        if off or failed is None
        else view_check_warning(failed)
    )
    log.warning("%s", warning)
    result.warnings.append(warning)
    return registration


def moved_cameras(
    views: list[FluoroView], case_views: Sequence[CaseView], first: ViewSetRegistration
) -> tuple[list[FluoroView], bool]:
    """The verification views with each camera that the case relates to a first view
    (``CaseView.moved_from``) started from that view's registered camera moved by the C-arm's
    nominal motion; and whether every view was (its bones can then be registered locally)."""
    registered = {v.name: c for v, c in zip(first.views, first.cameras_ct, strict=True)}
    out, every = [], True
    for v, cv in zip(views, case_views, strict=True):
        cam = registered.get(cv.moved_from or "")
        if cam is None or cv.carm_motion is None:
            every = False
            out.append(v)
            continue
        pose = np.asarray(cv.carm_motion, np.float64) @ cam.camera_from_world
        out.append(dataclasses.replace(v, camera=v.camera.with_pose(pose)))
    return out, every


def _unmoved(
    views: list[FluoroView],
    case_views: Sequence[CaseView],
    first: ViewSetRegistration,
    cfg: NavigationConfig,
    result: NavigationResult,
) -> ViewSetBones | None:
    """The first registration's bones where every verification view was taken from a first view's
    C-arm position (no motion) and its anatomy did not move
    (:func:`~fluoronav.registration.view_set.unmoved.unmoved_bones`); None otherwise. The NCC of
    each pair is recorded in the ``verify_detect`` stage."""
    names = [v.name for v in first.views]
    if not all(
        cv.moved_from in names and cv.carm_motion is not None and np.array_equal(cv.carm_motion, np.eye(4))
        for cv in case_views
    ):
        return None
    same_as = [names.index(str(cv.moved_from)) for cv in case_views]
    min_ncc = cfg.view_set_settings(verification=True).min_unmoved_ncc
    bones, ncc = unmoved_bones(views, first, same_as, min_ncc=min_ncc)
    diag = result.stages["verify_detect"].diagnostics
    diag["unmoved_ncc"] = ncc
    diag["bones_from_first_registration"] = bones is not None
    if bones is None:
        log.warning("the anatomy moved since the first images (NCC %s): the bones are registered again", ncc)
    return bones
