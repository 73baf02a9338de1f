"""The CM of a view set whose cameras are known in one frame (stage ``cm`` of ``register_view_set``).

The CM's landmarks are triangulated over the views and its roll scanned against the centrelines
(:func:`~fluoronav.registration.centerline.centerline_initialize_multiview`); the CM is registered
from the best roll minima and checked view by view (:mod:`fluoronav.registration.cm.checks`).
After a move (:class:`ViewSetPrior`) it is first registered from the kinematic prediction with the
local levels, the views' checks judging it (one view only where its landmarks agree with the
prediction); otherwise the images' own starts are screened with the prediction, the plan's pose
the fallback. The result is compared with the prediction and, where consistent, its tip fused with the
predicted one (:func:`~fluoronav.registration.view_set.fusion.fuse_tip`). Frames: the cameras' world (CT, LPS,
mm); the prior's poses are the femur's (``femur_from_cm``), placed via the registered ``ct_from_femur``.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from fluoronav.errors import RegistrationRefused
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.registration.centerline import (
    MultiViewInitResult,
    centerline_initialize_multiview,
    multiview_start_poses,
)
from fluoronav.registration.cm import CMRegistrationResult, CMView
from fluoronav.registration.cm.checks import (
    PredictedCMPose,
    motion_agreement,
    register_cm_checked,
)
from fluoronav.registration.cm.config import CMRegistrationConfig, local_cm_levels
from fluoronav.registration.cm.multistart import register_cm_multistart
from fluoronav.registration.cm.odd_view import name_odd_view
from fluoronav.registration.cm.shared_causes import RefusedCM, name_shared_cause
from fluoronav.registration.view_set.fusion import fuse_tip
from fluoronav.registration.view_set.settings import ViewSetPrior, ViewSetSettings
from fluoronav.registration.view_set.views import FluoroView

__all__ = [
    "landmark_gap_mm",
    "register_view_set_cm",
]

log = logging.getLogger(__name__)


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
            a prediction, how far the images' own landmarks lie from it (``prediction_gap_mm``,
            :func:`landmark_gap_mm`) and the registration's agreement with it
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
    tries, predicted = _tries(views, prior, ct_from_femur, image_starts)
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
    fast = _from_prediction(
        cm_views, lm_views, init, predicted, prior, cm_settings, settings, cm_config,
        initial_control_points_deg, seed, diag,
    )  # fmt: skip
    if fast is not None:
        cm = fast
    else:
        cm = _register_checked(
            cm_views,
            lm_views,
            tries,
            predicted,
            cm_settings,
            settings,
            initial_control_points_deg,
            seed,
            diag,
            functools.partial(_starts_for_shape, views, cameras, cm_config, settings.max_cm_starts),
        )
    if predicted is not None:  # reported, not judged here: the caller knows what a disagreement means
        sigma = None if prior is None else prior.prediction_sigma_mm
        cm = _compare_and_fuse(cm, cm_views, predicted, sigma, settings, cm_config, diag)
    return cm, init


def _from_prediction(
    cm_views: Sequence[CMView],
    lm_views: Sequence[np.ndarray | None],
    init: MultiViewInitResult | None,
    predicted: PredictedCMPose | None,
    prior: ViewSetPrior | None,
    cm_settings: CMRegistrationConfig,
    settings: ViewSetSettings,
    cm_config: CMConfig,
    initial_control_points_deg: np.ndarray,
    seed: int,
    diag: dict[str, Any],
) -> CMRegistrationResult | None:
    """With a prediction, the images' own landmarks against it (``prediction_gap_mm``, before any
    registration) and, where it has a σ, the CM registered from it (:func:`_register_from_prediction`);
    None otherwise."""
    if predicted is None:
        return None
    gap = landmark_gap_mm(
        cm_views, lm_views, init, predicted.world_from_cm, cm_config, initial_control_points_deg
    )
    diag["prediction_gap_mm"] = gap
    if prior is None or prior.prediction_sigma_mm is None:
        return None
    return _register_from_prediction(
        cm_views,
        lm_views,
        init,
        gap,
        predicted,
        cm_settings,
        settings,
        initial_control_points_deg,
        seed,
        diag,
    )


def _register_checked(
    cm_views: Sequence[CMView],
    lm_views: Sequence[np.ndarray | None],
    tries: Sequence[Sequence[np.ndarray]],
    predicted: PredictedCMPose | None,
    cm_settings: CMRegistrationConfig,
    settings: ViewSetSettings,
    initial_control_points_deg: np.ndarray,
    seed: int,
    diag: dict[str, Any],
    starts_for: Callable[[np.ndarray], tuple[list[list[np.ndarray]], float]] | None = None,
) -> CMRegistrationResult:
    """The CM registered from the starts ``tries`` and checked; without a prediction a refusal that
    an input every view shares explains is raised naming it (:func:`name_shared_cause`; what was
    found in ``diag["shared_causes"]``), else one that one view explains naming that view
    (:func:`name_odd_view`, ``diag["odd_view"]``)."""
    assert settings.cm_checks is not None
    try:
        return register_cm_checked(
            cm_views,
            lm_views,
            tries,
            diag,
            initial_control_points_deg=initial_control_points_deg,
            config=cm_settings,
            checks=settings.cm_checks,
            seed=seed,
        )
    except RegistrationRefused as exc:
        if predicted is not None:
            raise
        # a view's failure may be the FBG reading's or the CT's scale's: name it where it is
        failed = RefusedCM(
            exc,
            cm_views,
            lm_views,
            tries,
            reading_deg=np.asarray(initial_control_points_deg, np.float64),
            config=cm_settings,
            checks=settings.cm_checks,
            seed=seed + 101,
            starts_for=starts_for,
        )
        named = name_shared_cause(failed, diag.setdefault("shared_causes", {}))
        if named.check == exc.check:  # no shared input explains it: does one view?
            odd = name_odd_view(failed, diag.setdefault("odd_view", {}))
            named = named if odd is exc else odd
        raise named from exc


def _starts_for_shape(
    views: Sequence[FluoroView],
    cameras: Sequence[Camera],
    cm_config: CMConfig,
    max_starts: int,
    shape_deg: np.ndarray,
) -> tuple[list[list[np.ndarray]], float]:
    """The starts of the CM at ``shape_deg`` (its multi-view initialisation's, as one try) and their
    centreline cost (px; inf without two views with a CM)."""
    init, _ = _initialize(views, cameras, cm_config, np.asarray(shape_deg, np.float64), {})
    starts = [] if init is None else multiview_start_poses(init, max_starts=max_starts)
    return ([starts] if starts else []), (math.inf if init is None else float(init.cost_px))


def _tries(
    views: Sequence[FluoroView],
    prior: ViewSetPrior | None,
    ct_from_femur: np.ndarray | None,
    image_starts: list[np.ndarray],
) -> tuple[list[list[np.ndarray]], PredictedCMPose | None]:
    """The starts of the registration, in the order they are tried, and the prediction (after a
    move); without a prior the images' own, which need two views with a CM."""
    if prior is not None:
        if ct_from_femur is None:
            raise ValueError("a prior's poses need the registered ct_from_femur")
        return _prior_tries(prior, ct_from_femur, image_starts)
    if not image_starts:
        seen = sum(v.detection is not None for v in views)
        raise RegistrationRefused(
            "cm", "views_with_cm", f"the CM was found in {seen} of {len(views)} views, 2 needed"
        )
    return [image_starts], None


def _compare_and_fuse(
    cm: CMRegistrationResult,
    cm_views: Sequence[CMView],
    predicted: PredictedCMPose,
    sigma_mm: float | None,
    settings: ViewSetSettings,
    cm_config: CMConfig,
    diag: dict[str, Any],
) -> CMRegistrationResult:
    """The registration compared with the prediction (``motion_tip_mm``, ``motion_rotation_deg``)
    and, with a σ, its tip fused with the predicted one where the two are consistent: their
    difference within ``settings.fusion_max_mahalanobis`` of their combined uncertainty
    (``fusion_mahalanobis``; a depth one view cannot see counts little). After a fusion the
    comparison is of the fused CM (the images' own in ``image_motion_tip_mm``)."""
    agreement = motion_agreement(predicted, cm, cm_config)
    diag.update(agreement)
    if sigma_mm is None:
        return cm
    fused, fusion = _fuse(cm, cm_views, predicted, sigma_mm, settings, cm_config)
    diag["fusion_mahalanobis"] = fusion["mahalanobis"]
    if not fusion["mahalanobis"] <= settings.fusion_max_mahalanobis:
        log.info("the images and the kinematics differ by %.1f σ: not fused", fusion["mahalanobis"])
        return cm
    diag.update(fusion, image_motion_tip_mm=agreement["motion_tip_mm"])
    diag.update(motion_agreement(predicted, fused, cm_config))
    return fused


def _register_from_prediction(
    cm_views: Sequence[CMView],
    lm_views: Sequence[np.ndarray | None],
    init: MultiViewInitResult | None,
    gap: float,
    predicted: PredictedCMPose,
    cm_settings: CMRegistrationConfig,
    settings: ViewSetSettings,
    initial_control_points_deg: np.ndarray,
    seed: int,
    diag: dict[str, Any],
) -> CMRegistrationResult | None:
    """The CM registered with the local levels from the kinematic prediction, where the images'
    own landmarks agree with it (``gap``: :func:`landmark_gap_mm`); None where they do not, or where
    that registration failed its checks (the caller registers from the images' own starts)."""
    assert settings.cm_checks is not None
    W = predicted.world_from_cm
    # one view's checks cannot see depth: there the prediction is used only where the landmarks
    # agree with it; with two or more the checks of each view judge the registration from it
    if init is None and not gap <= settings.fusion_max_gap_mm:
        diag["from_prediction"] = False
        log.info("the landmarks are %.1f mm from the prediction: the image's own starts", gap)
        return None
    levels = settings.fusion_cm_levels or local_cm_levels(len(cm_views))
    try:
        cm = register_cm_checked(
            cm_views,
            lm_views,
            [[W]],
            diag,
            initial_control_points_deg=initial_control_points_deg,
            config=cm_settings.with_(levels=levels),
            checks=settings.cm_checks,
            seed=seed,
        )
    except RegistrationRefused as exc:
        diag["from_prediction"] = False
        diag["from_prediction_refused"] = str(exc)
        log.info("the registration from the prediction failed its checks (%s)", exc)
        return None
    diag["from_prediction"] = True
    return cm


def _fuse(
    cm: CMRegistrationResult,
    cm_views: Sequence[CMView],
    predicted: PredictedCMPose,
    sigma_mm: float,
    settings: ViewSetSettings,
    cm_config: CMConfig,
) -> tuple[CMRegistrationResult, dict[str, Any]]:
    """The registered tip and the predicted one fused (:func:`fuse_tip`) over the views the
    registration used."""
    cameras = {v.name: v.camera for v in cm_views}
    used = [cameras[n] for n in cm.view_names]
    cp = torch.as_tensor(np.asarray(cm.control_points_deg, np.float64))
    tip_cm = CMKinematics(cm_config).tip_cm(cp).numpy()
    W = predicted.world_from_cm
    fused, diag = fuse_tip(cm, used, W[:3, :3] @ tip_cm + W[:3, 3], sigma_mm, settings.tip_fusion)
    diag["prediction_sigma_mm"] = float(sigma_mm)
    return fused, diag


def landmark_gap_mm(
    views: Sequence[CMView],
    landmarks_px: Sequence[np.ndarray | None],
    init: MultiViewInitResult | None,
    world_from_cm: np.ndarray,
    cm_config: CMConfig,
    control_points_deg: np.ndarray,
) -> float:
    """How far the images' own landmarks A, B lie from those of the pose ``world_from_cm``, mm (the
    larger of the two): triangulated where two views have a CM; with one, the reprojection
    distance in that view scaled to the CM's depth (what one view can tell); inf without any."""
    kin = CMKinematics(cm_config)
    ab_cm = kin.landmarks_cm(torch.as_tensor(np.asarray(control_points_deg, np.float64))).numpy()
    ab = ab_cm @ world_from_cm[:3, :3].T + world_from_cm[:3, 3]
    if init is not None:
        return float(np.linalg.norm(np.asarray(init.landmarks_world) - ab, axis=1).max())
    gaps = []
    for v, lm in zip(views, landmarks_px, strict=True):
        if lm is None:
            continue
        depth = v.camera.to_camera(ab)[:, 2]
        px = np.linalg.norm(v.camera.project(ab) - np.asarray(lm, np.float64), axis=1)
        gaps.append(float((px * depth / v.camera.K[0, 0]).max()))
    return max(gaps) if gaps else math.inf


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
