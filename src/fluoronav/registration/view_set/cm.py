"""The CM of a view set whose cameras are known in one frame (stage ``cm`` of
:func:`~fluoronav.registration.view_set.register_view_set`).

The CM's landmarks are triangulated over the views and its roll scanned against the centrelines
(:func:`~fluoronav.registration.centerline.centerline_initialize_multiview`); the CM is then
registered (pose and shape) from the best roll minima and checked view by view
(:mod:`fluoronav.registration.cm.checks`). After a move (:class:`ViewSetPrior`) the images' own
starts are screened together with the kinematic prediction, the plan's pose is the fallback, and
the result is compared with the prediction (reported, not judged).

Frames: the world frame of the given cameras (the CT frame, LPS, mm); the prior's poses are
relative to the femur (``femur_from_cm``), placed through the registered ``ct_from_femur``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fluoronav.errors import RegistrationRefused
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.registration.centerline import (
    MultiViewInitResult,
    centerline_initialize_multiview,
    multiview_start_poses,
)
from fluoronav.registration.cm import CMRegistrationResult, CMView
from fluoronav.registration.cm.checks import PredictedCMPose, motion_agreement, register_cm_checked
from fluoronav.registration.cm.multistart import register_cm_multistart
from fluoronav.registration.view_set.settings import ViewSetPrior, ViewSetSettings
from fluoronav.registration.view_set.views import FluoroView

__all__ = [
    "register_view_set_cm",
]


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
