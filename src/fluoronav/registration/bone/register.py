"""The pelvis and femur registrations (the method: :mod:`fluoronav.registration.bone`)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage as ndi

from fluoronav.anatomy.volume import Volume
from fluoronav.device import resolve_device
from fluoronav.geometry.camera import Camera
from fluoronav.registration.bone.levels import (
    BoneLevelData,
    bone_excess_mu,
    level_similarity,
    render_level,
    shared_level_renderers,
)
from fluoronav.registration.bone.presets import (
    BoneRegistrationConfig,
    femur_config,
    pelvis_config,
)
from fluoronav.registration.bone.views import BoneView
from fluoronav.registration.engine import Registration
from fluoronav.registration.levels import LevelConfig
from fluoronav.registration.parameterization import RigidAboutPoint, RotationAboutPoint
from fluoronav.registration.trace import RegistrationTrace
from fluoronav.rendering.ct import CTRenderer

__all__ = [
    "BoneRegistrationResult",
    "bone_footprints",
    "register_femur",
    "register_pelvis",
    "register_pelvis_per_view",
    "relative_view_poses",
    "views_in_ct_frame",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class BoneRegistrationResult:
    """Outcome of a bone registration.

    Attributes:
        world_from_bone: (4, 4) estimated bone motion (``world_from_patient`` for the pelvis,
            ``world_from_femur`` for the femur), assuming the given cameras.
        camera_from_bone: (V, 4, 4) the estimate seen from each view (``camera_k_from_world @
            world_from_bone``); for per-view registration each view's own estimate.
        params: (D,) the optimiser's parameters (deg, mm) w.r.t. the initial pose.
        cost, converged, reason, trace, seconds: from the engine.
    """

    world_from_bone: np.ndarray
    camera_from_bone: np.ndarray
    params: np.ndarray
    cost: float
    converged: bool
    reason: str
    trace: RegistrationTrace
    seconds: float


def _view_transforms(views: Sequence[BoneView]) -> tuple[np.ndarray, np.ndarray]:
    """(camera_k_from_camera_0 (V, 4, 4), world_from_camera_0 (4, 4))."""
    w0 = views[0].camera.world_from_camera
    return np.stack([v.camera.camera_from_world @ w0 for v in views]), w0


def _result(
    views: Sequence[BoneView], world_from_view0: np.ndarray, view0_from_bone: np.ndarray, res: object
) -> BoneRegistrationResult:
    world_from_bone = world_from_view0 @ view0_from_bone
    return BoneRegistrationResult(
        world_from_bone=world_from_bone,
        camera_from_bone=np.stack([v.camera.camera_from_world @ world_from_bone for v in views]),
        params=np.asarray(res.params),  # type: ignore[attr-defined]
        cost=float(res.cost),  # type: ignore[attr-defined]
        converged=bool(res.converged),  # type: ignore[attr-defined]
        reason=str(res.reason),  # type: ignore[attr-defined]
        trace=res.trace,  # type: ignore[attr-defined]
        seconds=float(res.seconds),  # type: ignore[attr-defined]
    )


# ----- pelvis -------------------------------------------------------------------------------------
def register_pelvis(
    views: Sequence[BoneView],
    volume: Volume,
    *,
    initial_world_from_patient: np.ndarray,
    config: BoneRegistrationConfig | None = None,
    seed: int = 1,
    center_landmark: str = "pelvis_center",
) -> BoneRegistrationResult:
    """Register the pelvis to one view or jointly to several (one ``world_from_patient``).

    Args:
        views: images with their (known) cameras; all the same size.
        volume: labelled CT (label ``pelvis``) in HU.
        initial_world_from_patient: (4, 4) start pose.
        config: levels (default :func:`pelvis_config`).
        seed: CMA-ES seed.
        center_landmark: rotation centre (CT frame); the CT centre when the landmark is missing.

    Returns:
        :class:`BoneRegistrationResult` with ``world_from_bone`` = estimated ``world_from_patient``.
    """
    if not views:
        raise ValueError("no views given")
    config = config or pelvis_config()
    return _register_pelvis(
        views, _PelvisVolume(volume, config, center_landmark), initial_world_from_patient, seed
    )


class _PelvisVolume:
    """The pelvis's excess-μ volume, its rotation centre and its level renderers, built once for the
    registrations of several views."""

    def __init__(self, volume: Volume, config: BoneRegistrationConfig, center_landmark: str) -> None:
        self.config = config
        self.device = resolve_device(config.device)
        mu_np, self.w_index = bone_excess_mu(volume, ["pelvis"])
        self.mu = torch.from_numpy(mu_np).to(self.device)
        self.center = np.asarray(volume.landmarks_world.get(center_landmark, volume.center_world), np.float64)
        self.renderers = shared_level_renderers(volume, ["pelvis"], self.device)


def _register_pelvis(
    views: Sequence[BoneView], pv: _PelvisVolume, initial_world_from_patient: np.ndarray, seed: int
) -> BoneRegistrationResult:
    config, device = pv.config, pv.device
    k_from_0, world_from_0 = _view_transforms(views)
    W0 = np.asarray(initial_world_from_patient, np.float64)
    param = RigidAboutPoint(views[0].camera.camera_from_world @ W0, pv.center, axes="camera", device=device)
    data = BoneLevelData(
        views,
        pv.mu,
        pv.w_index,
        config.levels,
        "pelvis",
        device,
        skip_empty=config.skip_empty,
        renderers=pv.renderers,
    )

    def render(params: torch.Tensor, level: LevelConfig) -> torch.Tensor:
        return render_level(data, k_from_0, param(params).camera_from_object, level)

    reg = Registration(
        render,
        lambda lv: data.fixed[lv.name],
        data.levels,
        similarity=level_similarity(data),
        parameter_names=param.names,
        seed=seed,
        device=device,
    )
    res = reg.run(
        param.initial(), starts=[np.asarray(x, np.float64) for x in config.starts], keep=config.keep
    )
    view0_from_patient = param(res.params[None]).camera_from_object[0].cpu().numpy()
    log.info("pelvis (%d views): cost %.4f, %s, %.1f s", len(views), res.cost, res.reason, res.seconds)
    return _result(views, world_from_0, view0_from_patient, res)


def register_pelvis_per_view(
    views: Sequence[BoneView],
    volume: Volume,
    *,
    initial_world_from_patient: np.ndarray,
    config: BoneRegistrationConfig | None = None,
    seed: int = 1,
) -> list[BoneRegistrationResult]:
    """Register the pelvis to each view alone; ``result[k].camera_from_bone[0]`` is view k's
    ``camera_from_patient`` estimate (use :func:`relative_view_poses` for the view geometry). The
    bone volume and its level renderers are built once for all views.

    ``initial_world_from_patient``: (4, 4) the start of every view, or (V, 4, 4) one per view.
    """
    if not views:
        raise ValueError("no views given")
    W0 = np.asarray(initial_world_from_patient, np.float64)
    starts = np.broadcast_to(W0, (len(views), 4, 4)) if W0.ndim == 2 else W0
    if starts.shape != (len(views), 4, 4):
        raise ValueError(f"initial_world_from_patient must be (4, 4) or ({len(views)}, 4, 4), got {W0.shape}")
    pv = _PelvisVolume(volume, config or pelvis_config(), "pelvis_center")
    return [_register_pelvis([v], pv, starts[k], seed + 101 * k) for k, v in enumerate(views)]


def bone_footprints(
    cameras: Sequence[Camera],
    volume: Volume,
    label: str,
    camera_from_bone: np.ndarray,
    *,
    margin_mm: float,
    center_bone_mm: np.ndarray,
    min_fraction: float = 0.02,
) -> np.ndarray:
    """Where a bone lies in each view, widened by a margin: (V, rows, cols) bool.

    The label's excess-μ DRR at ``camera_from_bone`` (V, 4, 4) (the CT's copy of the bone placed by
    that pose), thresholded at ``min_fraction`` of its maximum and dilated by ``margin_mm`` at the
    depth of ``center_bone_mm`` (a point of the bone, in the CT's coordinates): the pixels another bone's
    registration leaves out where this one overlaps it (a femoral head over the acetabulum pulled
    the pelvis ~1.5 mm along the beam in views centred on the hip).
    """
    mu, world_from_index = bone_excess_mu(volume, [label])
    renderer = CTRenderer.from_tensor(torch.from_numpy(mu), world_from_index)
    T = np.asarray(camera_from_bone, np.float64).reshape(-1, 4, 4)
    out = []
    for cam, pose in zip(cameras, T, strict=True):
        drr = renderer.render_poses(cam.K, pose, cam.rows, cam.cols)[0].numpy()
        inside = drr > min_fraction * max(float(drr.max()), 1e-12)
        depth = float((pose @ np.r_[center_bone_mm, 1.0])[2])
        margin_px = margin_mm * float(cam.K[0, 0]) / max(depth, 1e-6)
        out.append(ndi.distance_transform_edt(~inside) <= margin_px)
    return np.stack(out) if out else np.zeros((0, 0, 0), bool)


def relative_view_poses(per_view: Sequence[BoneRegistrationResult]) -> np.ndarray:
    """(V, 4, 4) ``camera_k_from_camera_0 = camera_k_from_patient · inv(camera_0_from_patient)``."""
    c0 = per_view[0].camera_from_bone[0]
    return np.stack([r.camera_from_bone[0] @ np.linalg.inv(c0) for r in per_view])


def views_in_ct_frame(
    views: Sequence[BoneView], per_view: Sequence[BoneRegistrationResult]
) -> list[BoneView]:
    """The views with each camera placed by its own pelvis registration (``camera_from_patient``):
    the CT frame becomes the world frame of all views (``world_from_patient`` = identity), the view
    geometry of the multi-view workflows (§II-C)."""
    return [
        v.with_camera(v.camera.with_pose(r.camera_from_bone[0])) for v, r in zip(views, per_view, strict=True)
    ]


# ----- femur --------------------------------------------------------------------------------------
def _femur_level_data(
    views: Sequence[BoneView],
    volume: Volume,
    mu: np.ndarray,
    world_from_index: np.ndarray,
    label: str,
    config: BoneRegistrationConfig,
    device: torch.device,
) -> BoneLevelData:
    """One bone's level data on the femur's levels (the moving femur, or the static pelvis)."""
    return BoneLevelData(
        views,
        torch.from_numpy(mu).to(device),
        world_from_index,
        config.levels,
        "femur",
        device,
        skip_empty=config.skip_empty,
        renderers=shared_level_renderers(volume, [label], device),
    )


def register_femur(
    views: Sequence[BoneView],
    volume: Volume,
    *,
    side: str,
    world_from_patient: np.ndarray,
    config: BoneRegistrationConfig | None = None,
    seed: int = 1,
    initial_world_from_femur: np.ndarray | None = None,
) -> BoneRegistrationResult:
    """Register the femur (rotation about its head) after the pelvis, to one or several views.

    Args:
        views: images and cameras (as for :func:`register_pelvis`).
        volume: labelled CT (labels ``pelvis``, ``femur_<side>``; landmark ``femoral_head_<side>``).
        side: "left" or "right".
        world_from_patient: (4, 4) registered pelvis pose; the static pelvis DRR is rendered there.
        config: levels (default :func:`femur_config` for the number of views).
        seed: CMA-ES seed.
        initial_world_from_femur: (4, 4) start (default ``world_from_patient``: the CT's femur pose).

    Returns:
        :class:`BoneRegistrationResult` with ``world_from_bone`` = estimated ``world_from_femur``;
        the entry point estimate is ``world_from_bone @ entry_ct``.
    """
    if not views:
        raise ValueError("no views given")
    config = config or femur_config(views=len(views))
    device = resolve_device(config.device)
    head_name = f"femoral_head_{side}"
    if head_name not in volume.landmarks_world:
        raise ValueError(f"the CT has no landmark {head_name!r}")
    head = np.asarray(volume.landmarks_world[head_name], np.float64)
    mu_f, w_f = bone_excess_mu(volume, [f"femur_{side}"])
    mu_p, w_p = bone_excess_mu(volume, ["pelvis"])
    k_from_0, world_from_0 = _view_transforms(views)
    W0 = np.asarray(
        initial_world_from_femur if initial_world_from_femur is not None else world_from_patient, np.float64
    )
    param = RotationAboutPoint(views[0].camera.camera_from_world @ W0, head, axes="camera", device=device)
    femur = _femur_level_data(views, volume, mu_f, w_f, f"femur_{side}", config, device)
    pelvis = _femur_level_data(views, volume, mu_p, w_p, "pelvis", config, device)
    view0_from_patient = torch.as_tensor(views[0].camera.camera_from_world @ np.asarray(world_from_patient))[
        None
    ]
    static = {lv.name: render_level(pelvis, k_from_0, view0_from_patient, lv) for lv in femur.levels}

    def render(params: torch.Tensor, level: LevelConfig) -> torch.Tensor:
        return static[level.name] + render_level(femur, k_from_0, param(params).camera_from_object, level)

    reg = Registration(
        render,
        lambda lv: femur.fixed[lv.name],
        femur.levels,
        similarity=level_similarity(femur),
        parameter_names=param.names,
        seed=seed,
        device=device,
    )
    res = reg.run(
        param.initial(), starts=[np.asarray(x, np.float64) for x in config.starts], keep=config.keep
    )
    view0_from_femur = param(res.params[None]).camera_from_object[0].cpu().numpy()
    log.info("femur (%d views): cost %.4f, %s, %.1f s", len(views), res.cost, res.reason, res.seconds)
    return _result(views, world_from_0, view0_from_femur, res)
