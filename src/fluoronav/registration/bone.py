"""Intensity-based 2D/3D registration of the pelvis and the femur (single and multi-view).

Pelvis (the fiducial relating the C-arm views, FACTS.md): 6 DoF (:class:`RigidAboutPoint`, rotation
about the pelvis centre, axes of the first view's camera) of the label-masked pelvis DRR against the
whole image with patch gradient NCC, as xReg does. Femur: 3 DoF rotation about the femoral head
(:class:`RotationAboutPoint`) after the pelvis; the moving image is the static pelvis DRR at the
registered pose (rendered once per level) plus the femur DRR.

The DRR volume of a bone is its *attenuation in excess of soft tissue*,
``max(0, μ(HU) − μ(FILLER_HU))`` on the bone's label (dilated by one voxel for its partial-volume
rim), cropped to the label's bounding box: bone against the tissue around it is what the X-ray
shows, and the excess goes smoothly to 0 at the bone surface, so the label mask itself adds no
artificial edge.

Speed: every level renders the whole CMA-ES population and all views in one call (P·V cameras) of
a box-downsampled copy of the cropped volume (``voxel_mm``) at a binned working image of about
``image_px`` pixels (the ROI is the whole image, binned). Defaults (:func:`pelvis_config`,
:func:`femur_config`): from ~96 px with 2 mm voxels to ~256 px with 1 mm voxels, populations of
12–16 and capped generations; a femur in one view from a grid of tilted starts. ``authors=True``
gives the authors' σ and population 50.
Patch radius: xReg's rule (41 px at the 0.194 mm detector pixel, scaled; 3 px at ~96 px of a
1536² detector); with much larger patches the femur's out-of-plane rotations were unobservable
(measured: a 10° rotation about the camera x axis changed the cost by < 2 %).

Instruments: a view's ``mask`` leaves the CM and its shaft out of the similarity (their metal edges
pulled the bones, e.g. a femur 10 mm off in depth); the masked pixels are filled from their
surroundings first. Several images of one static view (the multiple-CM workflow) become one
:func:`static_view_composite`: each image's instrument filled from the others.

Multi-view: ``register_pelvis`` with several views optimises one ``world_from_patient`` against all
of them (joint); :func:`register_pelvis_per_view` registers each view alone and returns each view's
``camera_from_patient``, from which ``relative_view_poses`` gives ``camera_k_from_camera_0``.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage
from torch.nn import functional as tnf

from fluoronav.anatomy.volume import MU_WATER_PER_MM, Volume, hu_to_mu
from fluoronav.device import resolve_device
from fluoronav.geometry.camera import CIOS_FUSION, Camera
from fluoronav.registration.engine import Registration, SimilarityFactory, default_similarity
from fluoronav.registration.fill import harmonic_fill
from fluoronav.registration.levels import FEMUR_SIGMA, PELVIS_SIGMA, LevelConfig, patch_radius_for
from fluoronav.registration.parameterization import RigidAboutPoint, RotationAboutPoint
from fluoronav.registration.roi import area_downsample
from fluoronav.registration.trace import RegistrationTrace

__all__ = [
    "BoneLevel",
    "BoneRegistrationConfig",
    "BoneRegistrationResult",
    "BoneView",
    "bone_excess_mu",
    "femur_config",
    "pelvis_config",
    "register_femur",
    "register_pelvis",
    "register_pelvis_per_view",
    "relative_view_poses",
    "static_view_composite",
    "views_from_images",
    "views_in_ct_frame",
]

log = logging.getLogger(__name__)

#: soft tissue HU subtracted from the bone attenuation (see the module docstring)
TISSUE_HU = 40.0
#: tilt of the femur's one-view start grid (:func:`femur_config`), degrees
FEMUR_TILT_START_DEG = 8.0


# ----- inputs and settings ------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class BoneView:
    """One X-ray: image (H, W) float (−ln(I/I0) or any monotone intensity) and its camera.

    ``mask``: optional (H, W) bool, True on the pixels the similarity may use (e.g. False on a
    metal instrument the bone DRR does not contain). The masked pixels are filled from the others
    (:func:`~fluoronav.registration.fill.harmonic_fill`) before binning, so the instrument's edge
    does not reach the used pixels through the filters; a working pixel is used when at least half
    of it is.
    """

    image: np.ndarray
    camera: Camera
    mask: np.ndarray | None = None

    def __post_init__(self) -> None:
        img = np.asarray(self.image)
        if img.shape != (self.camera.rows, self.camera.cols):
            raise ValueError(
                f"image shape {img.shape} does not match camera {self.camera.rows}x{self.camera.cols}"
            )
        if self.mask is not None and np.shape(self.mask) != img.shape:
            raise ValueError(f"mask shape {np.shape(self.mask)} does not match image {img.shape}")

    @functools.cached_property
    def filled_image(self) -> np.ndarray:
        """The image with its masked pixels filled (:func:`harmonic_fill`); computed once per view,
        shared by the pelvis and femur registrations of the view."""
        if self.mask is None:
            return np.asarray(self.image)
        return harmonic_fill(self.image, ~np.asarray(self.mask, dtype=bool))


def views_from_images(
    images: Sequence[object], instruments: Sequence[np.ndarray | None] | None = None
) -> list[BoneView]:
    """BoneViews from objects with ``image`` and ``camera`` (e.g. ``SimulatedImage``).

    ``instruments``: per image, (H, W) bool True on instrument pixels (the CM and its shaft,
    :func:`fluoronav.detection.instrument.instrument_mask`) or None; those pixels are left out of
    the bone similarity.
    """
    masks = list(instruments) if instruments is not None else [None] * len(images)
    if len(masks) != len(images):
        raise ValueError(f"{len(masks)} instrument masks for {len(images)} images")
    return [
        BoneView(
            np.asarray(im.image, dtype=np.float32),  # type: ignore[attr-defined]
            im.camera,  # type: ignore[attr-defined]
            None if m is None else ~np.asarray(m, dtype=bool),
        )
        for im, m in zip(images, masks, strict=True)
    ]


def static_view_composite(views: Sequence[BoneView]) -> BoneView:
    """One view from several images of one static C-arm view (the multiple-CM workflow: the
    anatomy is still, the instrument moves): per pixel the mean of the images whose mask uses it, so
    the instrument of one image is filled from the others and the noise averages down; the mask
    keeps the pixels no image could fill. Views without a mask are left out (their instrument was
    not found), unless no view has one (then the first view).

    Raises:
        ValueError: no views, or the views' cameras differ.
    """
    if not views:
        raise ValueError("no views given")
    cam = views[0].camera
    for v in views[1:]:
        if not (
            np.allclose(v.camera.K, cam.K) and np.allclose(v.camera.camera_from_world, cam.camera_from_world)
        ):
            raise ValueError("a static-view composite needs one camera for all images")
    masked = [v for v in views if v.mask is not None]
    if not masked:
        return views[0]
    w = np.stack([np.asarray(v.mask, dtype=np.float64) for v in masked])
    img = np.stack([np.asarray(v.image, dtype=np.float64) for v in masked])
    n = w.sum(axis=0)
    mean = (w * img).sum(axis=0) / np.maximum(n, 1.0)
    return BoneView(np.where(n > 0, mean, img.mean(axis=0)).astype(np.float32), cam, n > 0)


@dataclass(frozen=True)
class BoneLevel:
    """One registration level.

    Attributes:
        optimizer: CMA-ES settings (σ, population, tolerances, generation cap, patch stride and
            smoothing; its ``downsample`` and ``patch_radius`` are not used).
        image_px: target working image side; the image is binned by ``round(cols / image_px)``.
        voxel_mm: voxel size of the rendered volume (box-downsampled by an integer factor ≥ 1).
        patch_radius_px: patch-NCC radius in working pixels; None → xReg's rule, round(41 / s) with
            s the working pixel size over the 0.194 mm CIOS Fusion pixel.
    """

    optimizer: LevelConfig
    image_px: int = 96
    voxel_mm: float = 2.0
    patch_radius_px: int | None = None


@dataclass(frozen=True)
class BoneRegistrationConfig:
    """Levels run in order, each warm-started from the previous.

    ``starts``: more first-level starts in the parameters' units (deg, mm) relative to the initial
    pose (multi-start: the first level runs from the initial pose and from each, the ``keep``
    lowest go on through all levels and the lowest final cost wins; see :meth:`Registration.run`).
    """

    levels: tuple[BoneLevel, ...]
    device: str = "cpu"
    starts: tuple[tuple[float, ...], ...] = ()
    keep: int = 1


def pelvis_config(*, authors: bool = False, device: str = "cpu") -> BoneRegistrationConfig:
    """Pelvis levels: ~96 px, then ~128 px, both with 2 mm voxels (or the CT's own grid if coarser),
    then ~256 px with 1 mm voxels.

    ``authors=True``: the authors' coarse σ (30° ×3, 50/50/100 mm) and population 50, then σ/10.
    Default (ours, for an initial error of a few degrees / ~10 mm as in the authors' protocol):
    σ 5° / 10, 10, 20 mm, population 16, ≤ 40 generations, then σ 1° / 2, 2, 4 mm, population 12,
    ≤ 30 generations, then σ 0.5° / 1, 1, 2 mm, population 12, ≤ 30 generations at ~256 px. The
    third level: the pelvis centre (mostly depth) on 9 multiple-CM trials (768² images, instrument
    masked) 0.08–0.89 mm → 0.06–0.56 mm; ~10 s more per view on this CPU. Translations and
    rotations are in the first view's camera axes (z = depth).
    """
    if authors:
        coarse = LevelConfig(sigma=PELVIS_SIGMA, popsize=50, stride=1, name="pelvis-coarse")
        fine = LevelConfig(
            sigma=tuple(s / 10 for s in PELVIS_SIGMA), popsize=50, stride=1, name="pelvis-fine"
        )
    else:
        coarse = LevelConfig(
            sigma=(5.0, 5.0, 5.0, 10.0, 10.0, 20.0),
            popsize=16,
            max_iters=40,
            smooth_sigma_px=2.0,
            name="pelvis-coarse",
        )
        fine = LevelConfig(sigma=(1.0, 1.0, 1.0, 2.0, 2.0, 4.0), popsize=12, max_iters=30, name="pelvis-fine")
    levels: tuple[BoneLevel, ...] = (
        BoneLevel(coarse, image_px=96, voxel_mm=2.0, patch_radius_px=None if authors else 10),
        BoneLevel(fine, image_px=128, voxel_mm=2.0),
    )
    if not authors:
        finest = LevelConfig(
            sigma=(0.5, 0.5, 0.5, 1.0, 1.0, 2.0), popsize=12, max_iters=30, name="pelvis-finest"
        )
        levels += (BoneLevel(finest, image_px=256, voxel_mm=1.0),)
    return BoneRegistrationConfig(levels=levels, device=device)


def femur_config(*, authors: bool = False, device: str = "cpu", views: int = 1) -> BoneRegistrationConfig:
    """Femur: rotation about the head (3 DoF, camera axes, degrees).

    ``authors=True``: σ = 10° and population 50 at ~96 px / 2 mm voxels, then σ = 2° at ~128 px /
    1 mm, no generation cap.

    Default, several views (``views`` > 1): σ = 10°, 2°, 1° at ~96 px / 2 mm, ~128 px / 1 mm,
    ~256 px / 1 mm, population 16, ≤ 50 / 30 / 50 generations.

    Default, one view: one view hardly tells a femur tilted towards the source from one tilted away,
    and the out-of-plane rotation (the entry point's depth) shows at ~256 px, hardly at 128 or 96:

    - on three multiple-CM trials the cost at 128 px was lower at the (1.2–2.5 mm off) estimate
      than at the truth in two, at 256 px higher in all three;
    - on one, the σ = 10° level ran from every start (also tilted ones) into a minimum 16° off
      (entry 7 mm), whose cost at 256 px was above the truth's.

    So the first level (~128 px / 1 mm, σ = 3°, population 12, ≤ 30 generations) is local and runs
    from 9 starts, a grid of ±``FEMUR_TILT_START_DEG`` about the camera's x and y axes; the best 3
    are finished at ~256 px / 1 mm (σ = 1.5°, population 16, ≤ 40 generations) and the lowest final
    cost wins. Entry error on 9 multiple-CM trials of seed 9205 (instrument masked, the
    pelvis's third level) 0.79 mm mean with the σ = 10° levels and 5 tilted starts, 0.73 mm with
    this; ~15–20 s per registration on one core of this CPU.
    """
    if authors:
        coarse = LevelConfig(sigma=FEMUR_SIGMA, popsize=50, name="femur-coarse")
        fine = LevelConfig(sigma=tuple(s / 5 for s in FEMUR_SIGMA), popsize=50, name="femur-fine")
        return BoneRegistrationConfig(
            levels=(
                BoneLevel(coarse, image_px=96, voxel_mm=2.0),
                BoneLevel(fine, image_px=128, voxel_mm=1.0),
            ),
            device=device,
        )
    if views > 1:
        coarse = LevelConfig(sigma=FEMUR_SIGMA, popsize=16, max_iters=50, name="femur-coarse")
        fine = LevelConfig(
            sigma=tuple(s / 5 for s in FEMUR_SIGMA), popsize=16, max_iters=30, name="femur-fine"
        )
        finest = LevelConfig(sigma=(1.0, 1.0, 1.0), popsize=16, max_iters=50, name="femur-finest")
        return BoneRegistrationConfig(
            levels=(
                BoneLevel(coarse, image_px=96, voxel_mm=2.0),
                BoneLevel(fine, image_px=128, voxel_mm=1.0),
                BoneLevel(finest, image_px=256, voxel_mm=1.0),
            ),
            device=device,
        )
    t = FEMUR_TILT_START_DEG
    grid = tuple((a, b, 0.0) for a in (-t, 0.0, t) for b in (-t, 0.0, t) if (a, b) != (0.0, 0.0))
    local = LevelConfig(sigma=(3.0, 3.0, 3.0), popsize=12, max_iters=30, name="femur-tilt-grid")
    fine = LevelConfig(sigma=(1.5, 1.5, 1.5), popsize=16, max_iters=40, name="femur-fine")
    return BoneRegistrationConfig(
        levels=(BoneLevel(local, image_px=128, voxel_mm=1.0), BoneLevel(fine, image_px=256, voxel_mm=1.0)),
        device=device,
        starts=grid,
        keep=3,
    )


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


# ----- volumes ------------------------------------------------------------------------------------
def bone_excess_mu(volume: Volume, label_names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Bone attenuation in excess of soft tissue on the labels, cropped: (μ (nz, ny, nx) float32 1/mm,
    world_from_index (4, 4) of the crop).

    Raises:
        ValueError: no labels or a missing / empty label.
    """
    if volume.labels is None:
        raise ValueError("bone registration needs a labelled CT")
    values = []
    for name in label_names:
        v = volume.label_value(name)
        if v is None:
            raise ValueError(f"the CT has no label {name!r} (labels: {volume.label_names})")
        values.append(v)
    bone = np.isin(volume.labels, values)
    if not bone.any():
        raise ValueError(f"labels {list(label_names)} are empty")
    other = (volume.labels > 0) & ~bone
    mask = ndimage.binary_dilation(bone, iterations=1) & ~other
    idx = np.argwhere(mask)
    lo, hi = idx.min(0), idx.max(0) + 1
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    tissue = float(hu_to_mu(np.array([TISSUE_HU]), MU_WATER_PER_MM)[0])
    mu = np.where(mask[box], np.maximum(hu_to_mu(volume.data[box], MU_WATER_PER_MM) - tissue, 0.0), 0.0)
    offset = np.eye(4)
    offset[:3, 3] = [lo[2], lo[1], lo[0]]
    return np.ascontiguousarray(mu, dtype=np.float32), np.asarray(
        volume.world_from_index, np.float64
    ) @ offset


def _box_downsample(
    mu: torch.Tensor, world_from_index: np.ndarray, f: int
) -> tuple[torch.Tensor, np.ndarray]:
    """Box-average by ``f`` along every axis (zero padding: the zero outside the grid)."""
    if f == 1:
        return mu, world_from_index
    nz, ny, nx = mu.shape
    x = tnf.pad(mu[None, None], (0, (-nx) % f, 0, (-ny) % f, 0, (-nz) % f))
    small = tnf.avg_pool3d(x, kernel_size=f, stride=f)[0, 0].contiguous()
    S = np.diag([float(f), float(f), float(f), 1.0])
    S[:3, 3] = (f - 1) / 2.0
    return small, world_from_index @ S


class _LevelData:
    """Per level: working cameras, fixed images and the volume pyramid level."""

    def __init__(
        self,
        views: Sequence[BoneView],
        mu: torch.Tensor,
        world_from_index: np.ndarray,
        levels: Sequence[BoneLevel],
        prefix: str,
        device: torch.device,
    ) -> None:
        sizes = {(v.camera.rows, v.camera.cols) for v in views}
        if len(sizes) != 1:
            raise ValueError(f"all views must have the same image size, got {sorted(sizes)}")
        spacing = float(np.linalg.norm(world_from_index[:3, :3], axis=0).min())
        self.levels: list[LevelConfig] = []
        self.cams: dict[str, list[Camera]] = {}
        self.fixed: dict[str, torch.Tensor] = {}
        self.volume: dict[str, tuple[torch.Tensor, np.ndarray]] = {}
        self.masks: dict[str, torch.Tensor | None] = {}
        masks = (
            None
            if all(v.mask is None for v in views)
            else torch.stack(
                [
                    torch.as_tensor(
                        np.ones(np.shape(v.image)) if v.mask is None else np.asarray(v.mask, dtype=np.float64)
                    )
                    for v in views
                ]
            ).to(device)
        )
        # masked pixels are filled from their surroundings first: the instrument's edge would
        # otherwise reach the used pixels next to it through binning, smoothing and Sobel
        images = torch.stack([torch.as_tensor(np.asarray(v.filled_image, np.float32)) for v in views]).to(
            device
        )
        for i, lv in enumerate(levels):
            cols = views[0].camera.cols
            f = max(1, round(cols / lv.image_px))
            cams = [v.camera.downsample(f) for v in views]
            name = f"{prefix}-{i}"
            ps = cams[0].pixel_spacing_mm
            scale = (ps / CIOS_FUSION.pixel_spacing_mm) if ps else CIOS_FUSION.cols / cams[0].cols
            radius = (
                lv.patch_radius_px
                if lv.patch_radius_px is not None
                else patch_radius_for(max(1, round(scale)))
            )
            opt = lv.optimizer.with_(patch_radius=radius, name=name)
            self.levels.append(opt)
            self.cams[name] = cams
            self.fixed[name] = area_downsample(images, f)
            self.masks[name] = None if masks is None else area_downsample(masks, f) >= 0.5
            vf = max(1, math.floor(lv.voxel_mm / spacing + 1e-6))
            self.volume[name] = _box_downsample(mu, world_from_index, vf)


def _render(
    level_data: _LevelData, camera_from_view0: np.ndarray, object_poses: torch.Tensor, level: LevelConfig
) -> torch.Tensor:
    """DRRs (P, V, h, w) of the level volume for object poses ``view0_from_object`` (P, 4, 4)."""
    from fluoronav.rendering.ct import render_line_integrals

    cams = level_data.cams[level.name]
    mu, w = level_data.volume[level.name]
    P, V = object_poses.shape[0], len(cams)
    T = (
        torch.as_tensor(camera_from_view0, dtype=torch.float64)[None] @ object_poses.cpu()[:, None]
    )  # (P, V, 4, 4)
    K = np.broadcast_to(np.stack([c.K for c in cams])[None], (P, V, 3, 3)).reshape(P * V, 3, 3)
    out = render_line_integrals(
        mu, w, K, T.reshape(P * V, 4, 4).numpy(), cams[0].rows, cams[0].cols, mipmap=False
    )
    return out.reshape(P, V, cams[0].rows, cams[0].cols)


def _similarity(level_data: _LevelData) -> SimilarityFactory:
    """The engine's default similarity with the level's binned view masks."""

    def make(
        fixed: torch.Tensor, level: LevelConfig, mask: torch.Tensor | None
    ) -> Callable[..., torch.Tensor]:
        return default_similarity(fixed, level, level_data.masks[level.name])

    return make


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
    device = resolve_device(config.device)
    mu_np, w_index = bone_excess_mu(volume, ["pelvis"])
    mu = torch.from_numpy(mu_np).to(device)
    center = np.asarray(volume.landmarks_world.get(center_landmark, volume.center_world), np.float64)
    k_from_0, world_from_0 = _view_transforms(views)
    W0 = np.asarray(initial_world_from_patient, np.float64)
    param = RigidAboutPoint(views[0].camera.camera_from_world @ W0, center, axes="camera", device=device)
    data = _LevelData(views, mu, w_index, config.levels, "pelvis", device)

    def render(params: torch.Tensor, level: LevelConfig) -> torch.Tensor:
        return _render(data, k_from_0, param(params).camera_from_object, level)

    reg = Registration(
        render,
        lambda lv: data.fixed[lv.name],
        data.levels,
        similarity=_similarity(data),
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
    ``camera_from_patient`` estimate (use :func:`relative_view_poses` for the view geometry)."""
    return [
        register_pelvis(
            [v],
            volume,
            initial_world_from_patient=initial_world_from_patient,
            config=config,
            seed=seed + 101 * k,
        )
        for k, v in enumerate(views)
    ]


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
        BoneView(v.image, v.camera.with_pose(r.camera_from_bone[0]), v.mask)
        for v, r in zip(views, per_view, strict=True)
    ]


# ----- femur --------------------------------------------------------------------------------------
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
    femur = _LevelData(views, torch.from_numpy(mu_f).to(device), w_f, config.levels, "femur", device)
    pelvis = _LevelData(views, torch.from_numpy(mu_p).to(device), w_p, config.levels, "femur", device)
    view0_from_patient = torch.as_tensor(views[0].camera.camera_from_world @ np.asarray(world_from_patient))[
        None
    ]
    static = {lv.name: _render(pelvis, k_from_0, view0_from_patient, lv) for lv in femur.levels}

    def render(params: torch.Tensor, level: LevelConfig) -> torch.Tensor:
        return static[level.name] + _render(femur, k_from_0, param(params).camera_from_object, level)

    reg = Registration(
        render,
        lambda lv: femur.fixed[lv.name],
        femur.levels,
        similarity=_similarity(femur),
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
