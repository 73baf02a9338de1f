"""The bones of a view set (stages ``pelvis`` and ``femur``): the pelvis per view, then the femur.

Each view's pelvis is registered alone (the CM and its shaft left out of the similarity), which
places its camera in the CT frame; after a move, again with the femur's footprint (where the
earlier registration put it) left out as well. A view whose pelvis fails its checks
(:mod:`fluoronav.registration.bone.checks`: a mirrored image, a wrong camera) is left out of every
later stage. The femur (rotation about its head) is then registered to the views in the CT frame →
``ct_from_femur``, checked view by view; a view that fails is left out and the femur registered
again without it. Frames: ``ct`` (LPS, mm) is the world frame of the registered views; ``femur``
is the CT frame moved with the femur (``ct_from_femur``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from fluoronav.anatomy.volume import Volume
from fluoronav.errors import RegistrationRefused
from fluoronav.geometry.camera import Camera
from fluoronav.registration.bone import (
    BoneRegistrationResult,
    BoneView,
    bone_footprints,
    femur_config,
    register_femur,
    register_pelvis_per_view,
    views_in_ct_frame,
)
from fluoronav.registration.bone.checks import judge_pelvis_views, register_femur_checked
from fluoronav.registration.stages import StageRecorder, unrecorded
from fluoronav.registration.view_set.settings import ViewSetSeeds, ViewSetSettings

__all__ = [
    "ViewSetBones",
    "register_view_set_bones",
]


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
    pelvis, kept, left_out = _pelvis_stage(
        views, volume, side, names, W0, prior_ct_from_femur, settings, seeds, record
    )
    views, pelvis, names = [views[k] for k in kept], [pelvis[k] for k in kept], [names[k] for k in kept]
    if in_ct_frame:
        femur_views = views_in_ct_frame(views, pelvis)
        world_from_pelvis = np.eye(4)
    else:
        femur_views, world_from_pelvis = list(views), pelvis[0].world_from_bone
    femur, femur_kept = _femur_stage(
        femur_views, names, volume, side, world_from_pelvis, prior_ct_from_femur, settings, seeds, record,
        left_out,
    )  # fmt: skip
    return ViewSetBones(
        tuple(pelvis[k] for k in femur_kept),
        tuple(femur_views[k].camera for k in femur_kept),
        femur,
        kept=None if not left_out else tuple(kept[k] for k in femur_kept),
        left_out=left_out,
    )


def _pelvis_stage(
    views: Sequence[BoneView],
    volume: Volume,
    side: str,
    names: list[str],
    W0: np.ndarray,
    prior_ct_from_femur: np.ndarray | None,
    settings: ViewSetSettings,
    seeds: ViewSetSeeds,
    record: StageRecorder,
) -> tuple[list[BoneRegistrationResult], list[int], dict[str, str]]:
    """Stage "pelvis": each view's pelvis (:func:`_pelvis`), checked view by view where
    ``settings.bone_checks`` says so: ``(per-view pelvis, the kept views' indices, left out: name → why)``."""
    with record("pelvis") as rec:
        rec.diagnostics["views"] = {n: {} for n in names}
        pelvis = _pelvis(
            views, volume, side, names, W0, prior_ct_from_femur, settings, seeds, rec.diagnostics
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
    return pelvis, kept, left_out


def _femur_stage(
    femur_views: Sequence[BoneView],
    names: list[str],
    volume: Volume,
    side: str,
    world_from_pelvis: np.ndarray,
    prior_ct_from_femur: np.ndarray | None,
    settings: ViewSetSettings,
    seeds: ViewSetSeeds,
    record: StageRecorder,
    left_out: dict[str, str],
) -> tuple[BoneRegistrationResult, list[int]]:
    """Stage "femur": the femur registered to the views, checked view by view where
    ``settings.bone_checks`` says so (the views it leaves out added to ``left_out``):
    ``(femur, the kept views' indices into femur_views)``."""

    def femur_of(fviews: Sequence[BoneView]) -> BoneRegistrationResult:
        config = settings.femur or femur_config(views=len(fviews))
        if settings.local and prior_ct_from_femur is not None:
            config = settings.femur_local  # from the earlier femur
        return register_femur(
            fviews,
            volume,
            side=side,
            world_from_patient=world_from_pelvis,
            config=replace(config, device=settings.device),
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
    return femur, femur_kept


def _pelvis(
    views: Sequence[BoneView],
    volume: Volume,
    side: str,
    names: Sequence[str],
    W0: np.ndarray,
    prior_ct_from_femur: np.ndarray | None,
    settings: ViewSetSettings,
    seeds: ViewSetSeeds,
    record: dict[str, Any],
) -> list[BoneRegistrationResult]:
    """Each view's pelvis: the ladder (``settings.pelvis``) from ``W0``, or with ``settings.local``
    nothing yet; then, after a move, the local levels (``pelvis_refine``, or ``pelvis_local``
    with ``settings.local``) with the earlier femur's footprint left out. ``record["views"]`` (per
    view name) gets each registration's cost, convergence and reason."""
    views_record = record["views"]
    starts = np.array(np.broadcast_to(np.asarray(W0, np.float64), (len(views), 4, 4)))
    if settings.local:  # the cameras are already close: the local levels alone, from them
        settings = replace(settings, pelvis_refine=settings.pelvis_local)
    if not (settings.local and prior_ct_from_femur is not None):
        pelvis = register_pelvis_per_view(
            views,
            volume,
            initial_world_from_patient=starts if settings.local else W0,
            config=replace(
                settings.pelvis_local if settings.local else settings.pelvis, device=settings.device
            ),
            seed=seeds.pelvis_refine if settings.local else seeds.pelvis,
        )
        for n, r in zip(names, pelvis, strict=True):
            views_record[n] = {"cost": float(r.cost), "converged": bool(r.converged), "reason": r.reason}
        if settings.local or prior_ct_from_femur is None or settings.pelvis_refine is None:
            return pelvis
        starts = np.stack([r.world_from_bone for r in pelvis])
    assert prior_ct_from_femur is not None
    pelvis = _pelvis_without_femur(
        views, volume, side, starts, prior_ct_from_femur, settings, seeds, views_record
    )
    if settings.local:
        for n, r in zip(names, pelvis, strict=True):
            views_record[n].update(cost=float(r.cost), converged=bool(r.converged), reason=r.reason)
    return pelvis


def _pelvis_without_femur(
    views: Sequence[BoneView],
    volume: Volume,
    side: str,
    starts: np.ndarray,
    ct_from_femur: np.ndarray,
    settings: ViewSetSettings,
    seeds: ViewSetSeeds,
    record: dict[str, Any],
) -> list[BoneRegistrationResult]:
    """Each view's pelvis from ``starts`` ((V, 4, 4) ``world_from_pelvis``: a first result, or the
    given camera) with the femur's footprint (the femur at ``ct_from_femur``, seen through that
    start's camera) left out of the similarity; ``record`` (per view name) gets what was left out
    and the cost without it."""
    assert settings.pelvis_refine is not None
    cams = [v.camera.camera_from_world @ W for v, W in zip(views, starts, strict=True)]
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
        initial_world_from_patient=np.array(starts),
        config=replace(settings.pelvis_refine, device=settings.device),
        seed=seeds.pelvis_refine,
    )
    for name, f, r in zip(record, femur, again, strict=True):
        record[name].update(
            femur_left_out=float(f.mean()), cost_without_femur=float(r.cost), reason_without_femur=r.reason
        )
    return again
