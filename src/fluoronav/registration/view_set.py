"""One set of C-arm views registered: the bones, then the CM, in the CT frame (§II-C).

The chain that the navigation (its first images and its verification after the move) and the
multi-view study share, :func:`register_view_set`, in three stages:

1. ``pelvis``: the pelvis registered to each view alone, with the CM and its shaft left out of the
   similarity (:func:`bone_views`); each view's ``camera_from_ct`` follows, and with it the views'
   relative geometry. After a move (:class:`ViewSetPrior`), each view's pelvis again with the
   femur's footprint (the femur where the earlier registration put it) left out as well. Each
   view's pelvis is checked (:mod:`fluoronav.registration.bone.checks`); a view that fails (a
   mirrored image, a wrong camera) is left out of every later stage.
2. ``femur``: the femur (rotation about its head) registered to the views in the CT frame →
   ``ct_from_femur``, checked view by view; a view that fails is left out and the femur
   registered again without it.
3. ``cm``: the CM's landmarks triangulated over the views and its roll scanned against the
   centrelines (:func:`~fluoronav.registration.centerline.centerline_initialize_multiview`), then
   the CM registered (pose and shape) from the best roll minima and checked view by view
   (:mod:`fluoronav.registration.cm.checks`). After a move the images' own starts are screened
   together with the kinematic prediction, the plan's pose is the fallback, and the result is
   compared with the prediction (reported, not judged).

:func:`register_view_set_bones` and :func:`register_view_set_cm` are the two halves, for workflows
that keep their own CM registration or know their cameras. What differs in a later registration of
the same anatomy is data (:class:`ViewSetPrior`), not code. Each stage is timed and its diagnostics
recorded through a :data:`~fluoronav.registration.stages.StageRecorder`.

Frames: ``ct`` (LPS, mm) is the world frame of the registered views; ``femur`` is the CT frame
moved with the femur (``ct_from_femur``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from fluoronav.anatomy.volume import Volume
from fluoronav.detection.instrument import instrument_masks
from fluoronav.errors import RegistrationRefused
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.registration.bone import (
    PELVIS_PRESET,
    PELVIS_REFINE_PRESET,
    BoneRegistrationConfig,
    BoneRegistrationResult,
    BoneView,
    bone_footprints,
    femur_config,
    register_femur,
    register_pelvis_per_view,
    views_in_ct_frame,
)
from fluoronav.registration.bone.checks import BoneCheckConfig, judge_pelvis_views, register_femur_checked
from fluoronav.registration.centerline import (
    MultiViewInitResult,
    centerline_initialize_multiview,
    multiview_start_poses,
)
from fluoronav.registration.cm import CMRegistrationConfig, CMRegistrationResult, CMView
from fluoronav.registration.cm.checks import (
    MAX_MOTION_TIP_MM,
    CMCheckConfig,
    PredictedCMPose,
    motion_agreement,
    register_cm_checked,
)
from fluoronav.registration.cm.multistart import register_cm_multistart
from fluoronav.registration.stages import StageRecorder, unrecorded

__all__ = [
    "FluoroView",
    "ViewDetection",
    "ViewSetBones",
    "ViewSetPrior",
    "ViewSetRegistration",
    "ViewSetSeeds",
    "ViewSetSettings",
    "bone_views",
    "register_view_set",
    "register_view_set_bones",
    "register_view_set_cm",
]


@dataclass(frozen=True, eq=False)
class ViewDetection:
    """The CM found in one view.

    Attributes:
        landmarks_px: (2, 2) A, B (u, v) in the view's pixels.
        centerline_px: (P, 2) ordered A → B.
        mask: (rows, cols) bool CM region.
        confidence: (2,) the detector's confidence of A and B (1 for given landmarks).
        source: where it came from ("detector", "case", "oracle").
    """

    landmarks_px: np.ndarray
    centerline_px: np.ndarray
    mask: np.ndarray
    confidence: np.ndarray
    source: str


@dataclass(frozen=True, eq=False)
class FluoroView:
    """One C-arm image of a view set.

    Attributes:
        name: unique within its set; names the view in diagnostics and refusals.
        image: (rows, cols) float log image (bright = attenuating).
        camera: intrinsics and the initial ``camera_from_world`` (world = CT: an estimate the
            pelvis registration replaces).
        detection: the CM found in it, or None where none is usable.
    """

    name: str
    image: np.ndarray
    camera: Camera
    detection: ViewDetection | None = None


@dataclass(frozen=True)
class ViewSetSettings:
    """Settings of a view-set registration.

    Attributes:
        device: torch device of every renderer and similarity; it replaces the ``device`` of the
            sub-configs below.
        pelvis: the per-view pelvis registration's levels.
        femur: the femur registration's levels; None: the preset for the number of views
            (:func:`~fluoronav.registration.bone.presets.femur_config`).
        pelvis_refine: after a move (:attr:`ViewSetPrior.ct_from_femur`), each view's second pelvis
            registration, from the first, with the femur's footprint left out of the similarity;
            None: none.
        femur_margin_mm: how far around the femur's footprint that second registration leaves out,
            in mm at the femur (the femur's and the camera's errors, and a leg that moved a little).
        cm: the CM registration's settings (its ``cm_config`` is replaced by the CM's).
        max_cm_starts: roll minima of the centreline initialisation the CM registration starts from.
        cm_checks: thresholds of the CM registration's per-view checks
            (:mod:`~fluoronav.registration.cm.checks`); None: the CM is registered unchecked, from
            the first starts only.
        bone_checks: thresholds of the pelvis's and the femur's per-view checks
            (:mod:`~fluoronav.registration.bone.checks`); None: the bones are not checked.
    """

    device: str = "cpu"
    pelvis: BoneRegistrationConfig = PELVIS_PRESET
    femur: BoneRegistrationConfig | None = None
    pelvis_refine: BoneRegistrationConfig | None = PELVIS_REFINE_PRESET
    femur_margin_mm: float = 3.0
    cm: CMRegistrationConfig = field(default_factory=CMRegistrationConfig)
    max_cm_starts: int = 2
    cm_checks: CMCheckConfig | None = field(default_factory=CMCheckConfig)
    bone_checks: BoneCheckConfig | None = field(default_factory=BoneCheckConfig)


@dataclass(frozen=True)
class ViewSetSeeds:
    """The optimisers' seeds of the stages (each CMA-ES run takes its own)."""

    pelvis: int
    femur: int
    pelvis_refine: int
    cm: int

    @classmethod
    def from_seed(cls, seed: int) -> ViewSetSeeds:
        """Each stage's seed from one."""
        return cls(pelvis=seed + 2, femur=seed + 3, pelvis_refine=seed + 4, cm=seed + 5)


@dataclass(frozen=True, eq=False)
class ViewSetPrior:
    """What an earlier registration of the same anatomy gives a later one: the verification after
    the robot moved the CM.

    Attributes:
        ct_from_femur: (4, 4) the earlier femur: the femur starts there, and each view's pelvis is
            registered a second time with the femur's footprint left out
            (:attr:`ViewSetSettings.pelvis_refine`).
        femur_from_cm_start: (4, 4) the CM's start in the frame of the femur registered anew (the
            plan's pose, where the robot was sent).
        femur_from_cm_predicted: (4, 4) where another account (the robot's kinematics) puts the CM
            in the femur frame, or None: one start among the images' own, and the pose the
            registration is compared with afterwards (the CM stage's ``motion_tip_mm``,
            ``motion_rotation_deg``). It is not a gate: the CM is found where the images show it,
            and what a disagreement means is for the caller to judge.
        max_motion_tip_mm: the tolerance of that comparison the caller applies.
    """

    ct_from_femur: np.ndarray
    femur_from_cm_start: np.ndarray
    femur_from_cm_predicted: np.ndarray | None = None
    max_motion_tip_mm: float = MAX_MOTION_TIP_MM


@dataclass(frozen=True, eq=False)
class ViewSetBones:
    """The bones registered in a view set.

    Attributes:
        pelvis: per-view pelvis registrations (the last of each view's) of the views that passed
            their checks.
        cameras: those views' cameras, placed by their pelvis registrations in the CT frame (or as
            given, see :func:`register_view_set_bones`).
        femur: the femur registration (``world_from_bone`` = ``ct_from_femur``).
        kept: the indices (into the given views) of those views; None: every view.
        left_out: the views left out by the checks, name → why (the pelvis's or the femur's).
    """

    pelvis: tuple[BoneRegistrationResult, ...]
    cameras: tuple[Camera, ...]
    femur: BoneRegistrationResult
    kept: tuple[int, ...] | None = None
    left_out: dict[str, str] = field(default_factory=dict)


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


def bone_views(views: Sequence[FluoroView]) -> list[BoneView]:
    """The views for the bone registrations, the CM and its shaft (where detected) left out of the
    similarity (:func:`~fluoronav.detection.instrument.instrument_masks`)."""
    detections = [v.detection for v in views]
    instruments = instrument_masks(
        [None if d is None else d.mask for d in detections],
        [None if d is None else d.centerline_px for d in detections],
        [v.image for v in views],
    )
    return [
        BoneView(np.asarray(v.image, np.float32), v.camera, None if m is None else ~np.asarray(m, dtype=bool))
        for v, m in zip(views, instruments, strict=True)
    ]


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
    bones = register_view_set_bones(
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
    if bones.kept is not None:
        views = [views[k] for k in bones.kept]
    with record("cm") as rec:
        try:
            cm, init = register_view_set_cm(
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
    return ViewSetRegistration(
        views=tuple(views),
        pelvis=bones.pelvis,
        cameras_ct=bones.cameras,
        femur=bones.femur,
        cm=cm,
        cm_init=init,
        left_out=dict(bones.left_out),
    )


def register_view_set_bones(
    views: Sequence[BoneView],
    volume: Volume,
    *,
    side: str,
    settings: ViewSetSettings,
    seeds: ViewSetSeeds,
    names: Sequence[str] | None = None,
    prior_ct_from_femur: np.ndarray | None = None,
    initial_world_from_pelvis: np.ndarray | None = None,
    in_ct_frame: bool = True,
    recorder: StageRecorder | None = None,
) -> ViewSetBones:
    """The pelvis per view, then the femur (stages "pelvis" and "femur" of :func:`register_view_set`).

    Args:
        views: the bone views (:func:`bone_views`).
        volume, side: as :func:`register_view_set`.
        settings, seeds: the settings (``pelvis``, ``femur``, ``pelvis_refine``,
            ``femur_margin_mm``, ``device``) and the stages' seeds.
        names: the views' names in the diagnostics (default ``view<k>``).
        prior_ct_from_femur: (4, 4) an earlier femur: the femur starts there, and each view's pelvis
            is registered again with that femur's footprint left out (``settings.pelvis_refine``).
        initial_world_from_pelvis: (4, 4) the pelvis's start in every view (default identity).
        in_ct_frame: True: each view's camera placed by its own pelvis registration and the femur
            registered in the CT frame (the multi-view geometry, §II-C); False (one view whose
            camera is known in the world frame): the femur registered in that frame, relative to the
            registered pelvis, and the camera kept.
        recorder: as :func:`register_view_set`.

    Raises:
        ValueError: ``in_ct_frame`` is False with more than one view.
        RegistrationRefused: (stage "pelvis", "femur") too few views passed their checks
            (``settings.bone_checks``).
    """
    if not in_ct_frame and len(views) != 1:
        raise ValueError(f"the world frame of the cameras takes one view, got {len(views)}")
    record = recorder or unrecorded
    names = list(names) if names is not None else [f"view{k}" for k in range(len(views))]
    W0 = np.eye(4) if initial_world_from_pelvis is None else initial_world_from_pelvis
    with record("pelvis") as rec:
        pelvis = register_pelvis_per_view(
            views,
            volume,
            initial_world_from_patient=W0,
            config=replace(settings.pelvis, device=settings.device),
            seed=seeds.pelvis,
        )
        rec.diagnostics["views"] = {
            n: {"cost": float(r.cost), "converged": bool(r.converged), "reason": r.reason}
            for n, r in zip(names, pelvis, strict=True)
        }
        if prior_ct_from_femur is not None and settings.pelvis_refine is not None:
            pelvis = _pelvis_without_femur(
                views, volume, side, pelvis, prior_ct_from_femur, settings, seeds, rec.diagnostics["views"]
            )
        kept, left_out = list(range(len(views))), dict[str, str]()
        if settings.bone_checks is not None:
            try:
                kept, left_out = judge_pelvis_views(
                    views,
                    volume,
                    pelvis,
                    names,
                    settings.bone_checks,
                    initial_world_from_patient=W0,
                    pelvis_config=replace(settings.pelvis, device=settings.device),
                    seed=seeds.pelvis,
                    record=rec.diagnostics["views"],
                )
            except RegistrationRefused:
                rec.passed = False
                raise
            if left_out:
                rec.diagnostics["left_out"] = dict(left_out)
    views, pelvis, names = [views[k] for k in kept], [pelvis[k] for k in kept], [names[k] for k in kept]
    if in_ct_frame:
        femur_views = views_in_ct_frame(views, pelvis)
        world_from_pelvis = np.eye(4)
    else:
        femur_views, world_from_pelvis = list(views), pelvis[0].world_from_bone

    def femur_of(fviews: Sequence[BoneView]) -> BoneRegistrationResult:
        return register_femur(
            fviews,
            volume,
            side=side,
            world_from_patient=world_from_pelvis,
            config=replace(settings.femur or femur_config(views=len(fviews)), device=settings.device),
            seed=seeds.femur,
            initial_world_from_femur=prior_ct_from_femur,
        )

    with record("femur") as rec:
        femur_kept = list(range(len(femur_views)))
        if settings.bone_checks is None:
            femur = femur_of(femur_views)
        else:
            try:
                femur, femur_kept = register_femur_checked(
                    femur_views, names, femur_of, volume, side, settings.bone_checks, rec.diagnostics
                )
            except RegistrationRefused:
                rec.passed = False
                raise
            left_out.update(rec.diagnostics.get("left_out", {}))
        rec.diagnostics.update(cost=float(femur.cost), converged=bool(femur.converged), reason=femur.reason)
    return ViewSetBones(
        tuple(pelvis[k] for k in femur_kept),
        tuple(femur_views[k].camera for k in femur_kept),
        femur,
        kept=None if not left_out else tuple(kept[k] for k in femur_kept),
        left_out=left_out,
    )


def _pelvis_without_femur(
    views: Sequence[BoneView],
    volume: Volume,
    side: str,
    pelvis: Sequence[BoneRegistrationResult],
    ct_from_femur: np.ndarray,
    settings: ViewSetSettings,
    seeds: ViewSetSeeds,
    record: dict[str, Any],
) -> list[BoneRegistrationResult]:
    """Each view's pelvis again, from its first result, with the femur's footprint (the femur at
    ``ct_from_femur``, seen through that result's camera) left out of the similarity; ``record``
    (per view name) gets what was left out and the cost without it."""
    assert settings.pelvis_refine is not None
    cams = [r.camera_from_bone[0] for r in pelvis]
    head = np.asarray(volume.landmarks_world[f"femoral_head_{side}"], np.float64)
    femur = bone_footprints(
        [v.camera for v in views],
        volume,
        f"femur_{side}",
        np.stack([c @ ct_from_femur for c in cams]),
        margin_mm=settings.femur_margin_mm,
        center_bone_mm=head,
    )
    masked = [
        BoneView(v.image, v.camera, ~f if v.mask is None else (np.asarray(v.mask, dtype=bool) & ~f))
        for v, f in zip(views, femur, strict=True)
    ]
    again = register_pelvis_per_view(
        masked,
        volume,
        initial_world_from_patient=np.stack([r.world_from_bone for r in pelvis]),
        config=replace(settings.pelvis_refine, device=settings.device),
        seed=seeds.pelvis_refine,
    )
    for name, f, r in zip(record, femur, again, strict=True):
        record[name].update(
            femur_left_out=float(f.mean()), cost_without_femur=float(r.cost), reason_without_femur=r.reason
        )
    return again


def register_view_set_cm(
    views: Sequence[FluoroView],
    cameras: Sequence[Camera],
    *,
    cm_config: CMConfig,
    initial_control_points_deg: np.ndarray,
    settings: ViewSetSettings,
    seed: int,
    prior: ViewSetPrior | None = None,
    ct_from_femur: np.ndarray | None = None,
    name: str = "",
    diagnostics: dict[str, Any] | None = None,
) -> tuple[CMRegistrationResult, MultiViewInitResult | None]:
    """The CM in a view set whose cameras are known in one frame (stage "cm" of
    :func:`register_view_set`): the multi-view centreline initialisation where two views have a
    CM, then the (checked) CM registration from its best roll minima or from the prior's start.

    Args:
        views: as :func:`register_view_set` (their cameras are replaced by ``cameras``).
        cameras: each view's camera in the frame of the registration (the CT frame).
        cm_config, initial_control_points_deg, settings, prior, name: as :func:`register_view_set`.
        seed: the CM registration's seed.
        ct_from_femur: (4, 4) the registered femur; needed with a prior (its poses are relative
            to the femur).
        diagnostics: filled in place (JSON-ready): ``init_cost_px``, ``landmarks_replaced``, the
            registration's (:func:`~fluoronav.registration.cm.checks.register_cm_checked`) and, with
            a prediction, its agreement with it
            (:func:`~fluoronav.registration.cm.checks.motion_agreement`).

    Returns:
        The CM registration (world frame of ``cameras``) and the initialisation (None with fewer
        than two views with a CM).

    Raises:
        RegistrationRefused: see :func:`register_view_set`.
    """
    diag = diagnostics if diagnostics is not None else {}
    init, lm_views = _initialize(views, cameras, cm_config, initial_control_points_deg, diag)
    image_starts = [] if init is None else multiview_start_poses(init, max_starts=settings.max_cm_starts)
    predicted: PredictedCMPose | None = None
    if prior is None:
        if not image_starts:
            seen = sum(v.detection is not None for v in views)
            raise RegistrationRefused(
                "cm", "views_with_cm", f"the CM was found in {seen} of {len(views)} views, 2 needed"
            )
        tries = [image_starts]
    else:
        if ct_from_femur is None:
            raise ValueError("a prior's poses need the registered ct_from_femur")
        tries, predicted = _prior_tries(prior, ct_from_femur, image_starts)
    tag = f" ({name})" if name else ""
    cm_views = [
        CMView(np.asarray(v.image, np.float32), c, landmarks_px=lm, name=f"{v.name}{tag}")
        for v, c, lm in zip(views, cameras, lm_views, strict=True)
    ]
    cm_settings = settings.cm.with_(device=settings.device, cm_config=cm_config)
    if settings.cm_checks is None:
        cm = register_cm_multistart(
            cm_views,
            tries[0],
            initial_control_points_deg=initial_control_points_deg,
            config=cm_settings,
            seed=seed,
        )
        diag.update(cost=float(cm.cost), converged=bool(cm.converged), reason=cm.reason)
        return cm, init
    cm = register_cm_checked(
        cm_views,
        lm_views,
        tries,
        diag,
        initial_control_points_deg=initial_control_points_deg,
        config=cm_settings,
        checks=settings.cm_checks,
        seed=seed,
    )
    if predicted is not None:  # reported, not judged here: the caller knows what a disagreement means
        diag.update(motion_agreement(predicted, cm, cm_config))
    return cm, init


def _prior_tries(
    prior: ViewSetPrior, ct_from_femur: np.ndarray, image_starts: list[np.ndarray]
) -> tuple[list[list[np.ndarray]], PredictedCMPose | None]:
    """The starts of a registration after a move, in the order they are tried: the images' own
    (the multi-view initialisation's roll minima) together with the kinematic prediction, screened
    as one multi-start; then the prior's start (the plan) where those fail their checks. Without
    two views with a CM: the prior's start, then the prediction."""
    start = ct_from_femur @ prior.femur_from_cm_start
    predicted = None
    if prior.femur_from_cm_predicted is not None:
        predicted = PredictedCMPose(ct_from_femur, prior.femur_from_cm_predicted, prior.max_motion_tip_mm)
    if image_starts:
        first = [*image_starts, start if predicted is None else predicted.world_from_cm]
        return [first, [start]], predicted
    tries = [[start]] + ([] if predicted is None else [[predicted.world_from_cm]])
    return tries, predicted


def _initialize(
    views: Sequence[FluoroView],
    cameras: Sequence[Camera],
    cm_config: CMConfig,
    initial_control_points_deg: np.ndarray,
    diag: dict[str, Any],
) -> tuple[MultiViewInitResult | None, list[np.ndarray | None]]:
    """The multi-view centreline initialisation where two views have a CM, and each view's landmarks
    for the registration (the detected ones, or the consensus where they disagreed)."""
    lm_views: list[np.ndarray | None] = [
        None if v.detection is None else v.detection.landmarks_px for v in views
    ]
    seen = [(k, v.detection) for k, v in enumerate(views) if v.detection is not None]
    if len(seen) < 2:
        return None, lm_views
    # landmarks triangulated over the views; one that disagrees with the others (a detection of A
    # where the CM leaves the image, say) gives way to the consensus, in the registration's ROI and
    # landmark prior as in its start
    init = centerline_initialize_multiview(
        [cameras[k] for k, _ in seen],
        np.stack([d.landmarks_px for _, d in seen]),
        [d.centerline_px for _, d in seen],
        initial_control_points_deg,
        config=cm_config,
        landmark_confidence=np.stack([d.confidence for _, d in seen]),
    )
    for i, (k, _) in enumerate(seen):
        lm_views[k] = init.landmarks_px[i]
    diag["init_cost_px"] = float(init.cost_px)
    diag["landmarks_replaced"] = int((~np.asarray(init.landmark_inliers)).sum())
    return init, lm_views
