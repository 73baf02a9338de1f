"""One set of C-arm views registered, bones then CM (:func:`register_view_set`), and what it gives
(:class:`ViewSetRegistration`).

Frames: ``ct`` (LPS, mm) is the world frame of the registered views; ``femur`` is the CT frame
moved with the femur (``ct_from_femur``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fluoronav.anatomy.volume import Volume
from fluoronav.errors import RegistrationRefused
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.registration.bone import BoneRegistrationResult
from fluoronav.registration.centerline import MultiViewInitResult
from fluoronav.registration.cm import CMRegistrationResult
from fluoronav.registration.stages import StageRecorder, unrecorded
from fluoronav.registration.view_set.bones import ViewSetBones, register_view_set_bones
from fluoronav.registration.view_set.cm import register_view_set_cm
from fluoronav.registration.view_set.settings import ViewSetPrior, ViewSetSeeds, ViewSetSettings
from fluoronav.registration.view_set.views import FluoroView, ViewDetection, bone_views

__all__ = [
    "ViewSetRegistration",
    "register_view_set",
]


@dataclass(frozen=True, eq=False)
class ViewSetRegistration:
    """Bones and CM registered in one set of views (the first images, or the verification's).

    Attributes:
        views: the views as given, less those the bones' checks left out (``left_out``).
        pelvis: per-view pelvis registrations; cameras_ct: each view's camera placed by it
            (``camera_from_world`` = ``carm_k_from_ct``).
        femur: the femur registration (``world_from_bone`` = ``ct_from_femur``).
        cm: the CM registration in the CT frame; cm_init: the multi-view centreline initialisation
            (None with fewer than two views with a CM).
        left_out: the views the bones' checks left out, name → why.
    """

    views: tuple[FluoroView, ...]
    pelvis: tuple[BoneRegistrationResult, ...]
    cameras_ct: tuple[Camera, ...]
    femur: BoneRegistrationResult
    cm: CMRegistrationResult
    cm_init: MultiViewInitResult | None = None
    left_out: dict[str, str] = field(default_factory=dict)

    @property
    def detections(self) -> tuple[ViewDetection | None, ...]:
        return tuple(v.detection for v in self.views)

    @property
    def ct_from_femur(self) -> np.ndarray:
        return np.asarray(self.femur.world_from_bone, np.float64)

    @property
    def ct_from_cm(self) -> np.ndarray:
        return np.asarray(self.cm.world_from_cm[0], np.float64)

    @property
    def tip_ct_mm(self) -> np.ndarray:
        return np.asarray(self.cm.tip_world[0], np.float64)

    def to_dict(self) -> dict[str, Any]:
        """The registered poses (CT frame, LPS mm) under the keys of ``navigation.json``."""
        return {
            "ct_from_cm": self.ct_from_cm.tolist(),
            "control_points_deg": np.asarray(self.cm.control_points_deg).tolist(),
            "tip_ct_mm": self.tip_ct_mm.tolist(),
            "ct_from_femur": self.ct_from_femur.tolist(),
            "carm_from_ct": {
                v.name: c.camera_from_world.tolist() for v, c in zip(self.views, self.cameras_ct, strict=True)
            },
        }


def register_view_set(
    views: Sequence[FluoroView],
    volume: Volume,
    *,
    side: str,
    cm_config: CMConfig,
    initial_control_points_deg: np.ndarray,
    settings: ViewSetSettings | None = None,
    seed: int | ViewSetSeeds = 0,
    prior: ViewSetPrior | None = None,
    initial_world_from_pelvis: np.ndarray | None = None,
    name: str = "",
    recorder: StageRecorder | None = None,
    known_bones: ViewSetBones | None = None,
) -> ViewSetRegistration:
    """Register the bones, then the CM, in one set of views (module docstring).

    Args:
        views: the images, their cameras (``camera_from_ct`` an initial estimate) and the CM
            detected in each; without a prior, two views need a detection.
        volume: labelled CT (labels ``pelvis``, ``femur_<side>``; landmark ``femoral_head_<side>``).
        side: the femur's side, "left" or "right".
        cm_config: the CM's geometry.
        initial_control_points_deg: (n_control_points,) the CM's shape before it is registered (the
            FBG reading; after a move, the earlier registration's).
        settings: default :class:`ViewSetSettings`; its ``device`` runs every stage.
        seed: an int gives each stage its seed (:meth:`ViewSetSeeds.from_seed`).
        prior: an earlier registration of the same anatomy (the verification); None: the first.
        initial_world_from_pelvis: (4, 4) the pelvis's start in every view, in the world frame of
            the given cameras (default identity: they give ``camera_from_ct``).
        name: the set's name, appended to its views' names in the CM registration's (e.g.
            "verify": view "AP" is "AP (verify)" there).
        recorder: times the stages "pelvis", "femur", "cm" and keeps their diagnostics.
        known_bones: the bones already known in these views (taken from the C-arm positions of an
            earlier registration whose anatomy did not move:
            :func:`~fluoronav.registration.view_set.unmoved.unmoved_bones`): no bone is registered
            (the stages "pelvis" and "femur" record ``known``).

    Returns:
        :class:`ViewSetRegistration`.

    Raises:
        RegistrationRefused: (stage "pelvis", "femur") too few views' bones passed their checks
            (:mod:`~fluoronav.registration.bone.checks`); (stage "cm") the CM failed its checks from
            every start (:func:`~fluoronav.registration.cm.checks.register_cm_checked`), or fewer
            than two views have a CM and there is no prior.
    """
    settings = settings or ViewSetSettings()
    seeds = seed if isinstance(seed, ViewSetSeeds) else ViewSetSeeds.from_seed(seed)
    record = recorder or unrecorded
    bones = _bones(
        views, volume, side, settings, seeds, prior, initial_world_from_pelvis, record, known_bones
    )
    if bones.kept is not None:
        views = [views[k] for k in bones.kept]
    cm, init = _cm(views, bones, cm_config, initial_control_points_deg, settings, seeds, prior, name, record)
    return ViewSetRegistration(
        views=tuple(views),
        pelvis=bones.pelvis,
        cameras_ct=bones.cameras,
        femur=bones.femur,
        cm=cm,
        cm_init=init,
        left_out=dict(bones.left_out),
    )


def _bones(
    views: Sequence[FluoroView],
    volume: Volume,
    side: str,
    settings: ViewSetSettings,
    seeds: ViewSetSeeds,
    prior: ViewSetPrior | None,
    initial_world_from_pelvis: np.ndarray | None,
    record: StageRecorder,
    known_bones: ViewSetBones | None,
) -> ViewSetBones:
    """Stages "pelvis" and "femur": ``known_bones`` where given (recorded as known), else registered."""
    if known_bones is not None:
        for stage in ("pelvis", "femur"):
            with record(stage) as rec:
                rec.diagnostics["known"] = True
        return known_bones
    return register_view_set_bones(
        bone_views(views),
        volume,
        side=side,
        names=[v.name for v in views],
        settings=settings,
        seeds=seeds,
        prior_ct_from_femur=None if prior is None else prior.ct_from_femur,
        initial_world_from_pelvis=initial_world_from_pelvis,
        recorder=record,
    )


def _cm(
    views: Sequence[FluoroView],
    bones: ViewSetBones,
    cm_config: CMConfig,
    initial_control_points_deg: np.ndarray,
    settings: ViewSetSettings,
    seeds: ViewSetSeeds,
    prior: ViewSetPrior | None,
    name: str,
    record: StageRecorder,
) -> tuple[CMRegistrationResult, MultiViewInitResult | None]:
    """Stage "cm": the CM in the views placed by the bones (:func:`register_view_set_cm`)."""
    with record("cm") as rec:
        try:
            return register_view_set_cm(
                views,
                bones.cameras,
                cm_config=cm_config,
                initial_control_points_deg=initial_control_points_deg,
                settings=settings,
                seed=seeds.cm,
                prior=prior,
                ct_from_femur=bones.femur.world_from_bone,
                name=name,
                diagnostics=rec.diagnostics,
            )
        except RegistrationRefused:
            rec.passed = False
            raise
