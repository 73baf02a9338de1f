"""The verification's view set: the images after the move registered with the first registration
and the robot's kinematics as their prior (stages ``verify_pelvis``, ``verify_femur``, ``verify_cm``
of :mod:`fluoronav.navigation.pipeline`).

Where the case says which first view's C-arm position each verification view was taken from and how
the C-arm moved since (``CaseView.moved_from``), each camera starts from that view's registered
camera moved by it (:func:`moved_cameras`); with ``VerificationConfig.local_bones`` the bones then
need only their local levels, and where no C-arm and no anatomy moved the first registration's
bones are kept (:mod:`~fluoronav.registration.view_set.unmoved`). A refusal of the CM's registration
whose cause is the robot's kinematics (the images agree on a CM far from the prediction) is named
for them (:func:`~fluoronav.navigation.commands.name_kinematics_disagreement`).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import numpy as np

from fluoronav.navigation.case.model import CaseView, NavigationCase
from fluoronav.navigation.checks.safety import SafetyConfig
from fluoronav.navigation.commands import name_kinematics_disagreement
from fluoronav.navigation.config import NavigationConfig
from fluoronav.navigation.result import (
    NavigationRefused,
    NavigationResult,
    StageRecord,
    navigation_refusals,
)
from fluoronav.registration.stages import StageRecorder
from fluoronav.registration.view_set import (
    FluoroView,
    ViewSetBones,
    ViewSetPrior,
    ViewSetRegistration,
    register_view_set,
)
from fluoronav.registration.view_set.unmoved import unmoved_bones

log = logging.getLogger(__name__)

__all__ = ["moved_cameras", "register_verification"]


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
        A refusal that names the kinematics is final: no bone registration changes where the
        robot put the CM. The first attempt's stages are kept as ``verify_local_*``.
    """
    assert case.verification is not None and result.first is not None
    cfg, first = result.config, result.first
    diag = result.stages["verify_detect"].diagnostics
    diag["cameras_from_carm_motion"] = local
    known = _unmoved(views, case.verification.views, first, cfg, result) if local else None

    def register(local_now: bool) -> ViewSetRegistration:
        with _kinematics_named(result.stages, cfg.safety), navigation_refusals("verify_"):
            return register_view_set(
                views,
                case.volume,
                side=case.side,
                cm_config=case.cm_config,
                initial_control_points_deg=np.asarray(first.cm.control_points_deg),
                settings=cfg.view_set_settings(verification=True, local=local_now, n_views=len(views)),
                seed=seed,
                prior=prior,
                name="verify",
                recorder=recorder,
                known_bones=known if local_now else None,
            )

    if not local:
        return register(False)
    try:
        return register(True)
    except NavigationRefused as exc:
        if exc.check == "kinematics_disagree":
            raise
        log.warning("the verification with local bones refused (%s): the whole ladders", exc)
        diag["local_bones_refused"] = str(exc)
        for name in ("pelvis", "femur", "cm"):
            if f"verify_{name}" in result.stages:
                result.stages[f"verify_local_{name}"] = result.stages.pop(f"verify_{name}")
        return register(False)


@contextmanager
def _kinematics_named(stages: dict[str, StageRecord], safety: SafetyConfig) -> Iterator[None]:
    """The verification CM's refusal named for the kinematics where the images' CM is far from the
    prediction (:func:`~fluoronav.navigation.commands.name_kinematics_disagreement`)."""
    try:
        yield
    except NavigationRefused as exc:
        if exc.stage != "verify_cm" or "verify_cm" not in stages:
            raise
        named = name_kinematics_disagreement(exc, stages["verify_cm"].diagnostics, safety)
        if named is exc:
            raise
        raise named from exc


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
