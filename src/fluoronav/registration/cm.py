"""CM 2D/3D registration workflows: single-view, multi-view and multiple-CM (Gao et al. 2022, II-C).

All three are one problem: K images (views), each of the CM at one of M base poses, with known
cameras in a common world frame, and 6 + 5 unknowns (a rigid perturbation of the CM base pose, or of
the multiple-CM reference frame, plus the five control points):

- single-view: K = 1, M = 1;
- multi-view: K views of one CM pose (cameras related through the pelvis registration), M = 1;
- multiple-CM: one C-arm pose, M images of the CM at M robot poses whose relative poses are known
  (robot kinematics + hand-eye, ``base_from_cm``), K = M; parameterised by
  :class:`~fluoronav.registration.parameterization.MultiCMReference` (reference frame: identity
  rotation, mean translation of the CM base origins).

Per view the image is cropped to a square of ``roi_size_full_px`` *full-detector* pixels (authors: 500)
around the midpoint of the two landmarks and binned to the level's resolution (authors: 4×). Images
that are already binned (``CMView.binning``, e.g. 2 for a 768² image of the 1536² CIOS detector) are
cropped to ``500 / binning`` pixels and binned ``4 / binning`` times, so the working ROI is the same.
All views share the working ROI size, so the whole CMA-ES population × all views is rendered in
one :class:`~fluoronav.rendering.cm.CMRenderer` call per generation.

Cost: Σ_views patch gradient NCC (authors: patch radius round(41/4) = 10 px at 4×, stride 5 for the
CM) + the landmark reprojection prior (eqs. 2/4) with σ in full-detector pixels (authors: 100). An
optional static background per view (the anatomy rendered once at the registered bone pose) is added
to the CM DRR; see :mod:`fluoronav.registration.background`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from fluoronav.detection.tube_profile import fit_tube_profile
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.rotations import angle_between_rotations_deg
from fluoronav.manipulator.config import CMConfig, with_shaft
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.registration.engine import PriorFn, Registration
from fluoronav.registration.levels import CM_SIGMA, LevelConfig
from fluoronav.registration.parameterization import CMPoseShape, MultiCMReference, reference_frame
from fluoronav.registration.priors import LandmarkPrior, control_point_prior
from fluoronav.registration.roi import CropBox, crop_and_downsample_image
from fluoronav.registration.trace import RegistrationTrace
from fluoronav.rendering.cm import CMRenderer
from fluoronav.rendering.response import veil_response

__all__ = [
    "DEFAULT_CM_MU_PER_MM",
    "CMProblem",
    "CMRegistrationConfig",
    "CMRegistrationResult",
    "CMView",
    "RollScanResult",
    "ViewROI",
    "cm_pose_errors",
    "default_cm_levels",
    "register_cm",
    "register_cm_multistart",
    "roll_scan",
    "roll_scan_initialization",
    "save_overlays",
    "view_roi",
]

logger = logging.getLogger(__name__)

Workflow = Literal["single-view", "multi-view", "multi-cm"]
BackgroundFn = Callable[[Camera], np.ndarray]

#: μ of the CM material for the analytic DRR, 1/mm: nitinol is 0.76/mm at 60 keV and 0.52/mm at
#: 70 keV (xraylib); 0.6 sits between, consistent with μ_water = 0.02/mm of ``hu_to_mu`` (≈ 60 keV).
#: It only matters relative to a background DRR (the similarity is invariant to a global scale).
DEFAULT_CM_MU_PER_MM = 0.6


def default_cm_levels(*, popsize: int = 50, refine: bool = True) -> tuple[LevelConfig, ...]:
    """CM levels: the authors' CMA-ES level at 4× (σ 2°/5 mm/1.5°, stride 5, population 50, tolx 0.01)
    with tolfun 1e-3 instead of 0.01 (the cost changes by only ~0.002 per mm of depth at 4×: 0.01
    stops before the depth is resolved), and with ``refine`` a local CMA-ES level at 2× (σ / 4,
    population 20, tolfun 1e-4), where depth is ~3× better resolved (our choice, see
    docs/registration.md)."""
    coarse = LevelConfig(sigma=CM_SIGMA, downsample=4, stride=5, popsize=popsize, tolfun=1e-3, name="cm-4x")
    if not refine:
        return (coarse,)
    fine = LevelConfig(
        sigma=tuple(s / 4.0 for s in CM_SIGMA),
        downsample=2,
        stride=5,
        popsize=20,
        tolfun=1e-4,
        name="cm-2x",
    )
    return (coarse, fine)


@dataclass(frozen=True)
class CMRegistrationConfig:
    """Settings of :func:`register_cm`.

    Attributes:
        levels: registration levels; ``downsample`` is counted in full-detector pixels (4 = the
            authors' 4× of a 1536² image), whatever the binning of the input images; a level finer
            than the coarsest image binning is skipped (e.g. the 2× level for 384² CIOS images).
        roi_size_full_px: side of the square crop around the landmarks, full-detector pixels.
        landmark_sigma_full_px: landmark prior σ in full-detector pixels (authors: 100); None
            disables the prior.
        control_point_sigma_deg, control_point_tolerance_deg: prior of the control points around
            their initial values (the FBG reading): free within ± tolerance, Gaussian walls of σ
            beyond (:func:`~fluoronav.registration.priors.gaussian_parameter_prior`); σ None disables
            it (the authors have none). Why a flat bottom: a plain Gaussian (σ 1°) held the notch
            angles at the FBG error (multi-view notch 0.37 → 0.13° and 0.40 → 0.05° without it),
            and without any prior one of eight multi-view trials traded the base rotation against
            the shape (notch error 4.4°). The tolerance is the FBG accuracy with a margin (the
            simulated reading is within ±0.5°); docs/registration.md.
        single_view_control_point_sigma_deg: one view without a measured response (a single
            level, e.g. 384² images, or ``response="linear"``): a plain Gaussian of this σ instead of
            the flat-bottomed prior; there one view does not tell depth from shape (a 384² test case:
            depth 7.1 mm off with the flat prior, < 6 mm with σ = 1°). With the measured response
            the flat prior is used in every workflow: on six 768² single-view scenes it beat σ = 1°
            (tip 0.55 → 0.29 mm mean, notch 0.31 → 0.06°; docs/registration.md).
        use_background: add the views' background DRRs (when given) to the CM DRR.
        cm_mu_per_mm: attenuation of the CM in the DRR (matters only relative to a background).
        cm_config: CM geometry.
        shaft_length_mm: length of the rigid tube the CM is mounted on, rendered as a longer base
            (:func:`~fluoronav.manipulator.config.with_shaft`): it shows in the images and pins the
            base's direction down; 0 for a bare CM. The simulator's default is the same 50 mm.
        max_rotation_deg, max_translation_mm: search box of the pose around each start (per
            parameter: rotation-vector components, translation components; None: unbounded). A
            result on the box's edge is reported as a failure (``success`` False): the optimiser
            left the region it was started in, typically pulled by a wrong landmark (a single-view
            trial with a mis-detected B otherwise ended 583 mm away, "converged").
        response: ``"measured"``: before every level after the first, each view's response to the
            CM (:mod:`~fluoronav.rendering.response`: gain and veil, from scatter, glare and beam
            hardening) is fitted on the CM's shaft at the current estimate
            (:func:`~fluoronav.detection.tube_profile.fit_tube_profile`, the shaft's scale known
            from the pose) and applied to the DRR; a view whose fit fails stays linear.
            ``"linear"``: the plain DRR throughout. Why: against physics-simulated images the linear
            DRR put single-view depth 0.5–2.7 mm nearer the source (the image's compressed profile
            matches a larger CM); with the measured response the tip error fell from 1.10 to
            0.35 mm mean on six scenes (docs/registration.md).
        chunk_size: render at most this many candidates per call (None: the whole population).
        device: torch device of rendering and similarity.
    """

    levels: tuple[LevelConfig, ...] = field(default_factory=default_cm_levels)
    roi_size_full_px: int = 500
    landmark_sigma_full_px: float | None = 100.0
    control_point_sigma_deg: float | None = 0.25
    control_point_tolerance_deg: float = 1.0
    single_view_control_point_sigma_deg: float | None = 1.0
    use_background: bool = True
    cm_mu_per_mm: float = DEFAULT_CM_MU_PER_MM
    cm_config: CMConfig = field(default_factory=CMConfig)
    shaft_length_mm: float = 50.0
    max_rotation_deg: float | None = 45.0
    max_translation_mm: float | None = 50.0
    response: Literal["linear", "measured"] = "measured"
    chunk_size: int | None = None
    device: str = "cpu"

    def with_(self, **changes: Any) -> CMRegistrationConfig:
        return replace(self, **changes)


@dataclass(frozen=True, eq=False)
class CMView:
    """One X-ray image for CM registration.

    Attributes:
        image: (H, W) −log intensity image (bone and metal bright), any resolution.
        camera: its camera (``camera_from_world`` in the workflow's world frame, K for this image).
        landmarks_px: (2, 2) detected landmarks A, B as (u, v) in this image's pixels; NaN rows are
            missing (then the ROI is centred on the initial pose's projection).
        background: optional static DRR of the anatomy: an (H, W) array aligned with ``image`` or a
            callable ``roi_camera -> (h, w)`` (rendered once per level); in the DRR's line-integral
            units (μ_water = 0.02/mm).
        binning: full-detector pixels per image pixel (2 for 768² of a 1536² detector); None infers
            it from ``camera.pixel_spacing_mm`` and ``full_pixel_spacing_mm`` (1 when unknown).
        full_pixel_spacing_mm: detector pixel pitch at full resolution (CIOS Fusion: 0.194 mm).
        name: label used in results and overlay file names.
    """

    image: np.ndarray
    camera: Camera
    landmarks_px: np.ndarray | None = None
    background: np.ndarray | BackgroundFn | None = None
    binning: int | None = None
    full_pixel_spacing_mm: float = 0.194
    name: str = ""

    @property
    def image_binning(self) -> int:
        if self.binning is not None:
            return int(self.binning)
        ps = self.camera.pixel_spacing_mm
        if ps is None:
            return 1
        return max(1, round(ps / self.full_pixel_spacing_mm))


@dataclass(frozen=True, eq=False)
class ViewROI:
    """A view's ROI at one level: crop box in image pixels, binning factor, camera and fixed image."""

    box: CropBox
    factor: int
    camera: Camera
    image: np.ndarray
    background: np.ndarray | None


def _landmark_center(view: CMView, fallback_uv: np.ndarray) -> np.ndarray:
    lm = None if view.landmarks_px is None else np.asarray(view.landmarks_px, dtype=np.float64)
    if lm is not None and lm.shape == (2, 2) and np.all(np.isfinite(lm)):
        return lm.mean(axis=0)
    return np.asarray(fallback_uv, dtype=np.float64)


def view_roi(
    view: CMView, center_uv: np.ndarray, *, downsample_full: int, roi_size_full_px: int = 500
) -> ViewROI:
    """Crop ``roi_size_full_px`` full-detector pixels around ``center_uv`` (image pixels), binned to
    ``downsample_full`` full-detector pixels per working pixel (e.g. 768² image: crop 250, bin 2).

    Raises:
        ValueError: when the image's binning does not divide ``downsample_full``.
    """
    b = view.image_binning
    if downsample_full % b:
        raise ValueError(f"image binning {b} does not divide the level's downsampling {downsample_full}")
    factor = downsample_full // b
    size = round(roi_size_full_px / b)
    size -= size % factor
    cropped, (row0, col0) = view.camera.crop_around(center_uv, size)
    box = CropBox(row0, col0, cropped.rows, cropped.cols)
    cam = cropped.downsample(factor)
    img = np.asarray(crop_and_downsample_image(np.asarray(view.image, dtype=np.float32), box, factor))
    bg: np.ndarray | None = None
    if view.background is not None:
        if callable(view.background):
            bg = np.asarray(view.background(cam), dtype=np.float32)
        else:
            bg = np.asarray(crop_and_downsample_image(np.asarray(view.background, np.float32), box, factor))
        if bg.shape != (cam.rows, cam.cols):
            raise ValueError(f"background of view {view.name!r} has shape {bg.shape}, expected ROI shape")
    return ViewROI(box=box, factor=factor, camera=cam, image=img.astype(np.float32), background=bg)


@dataclass(frozen=True, eq=False)
class CMRegistrationResult:
    """Outcome of :func:`register_cm`.

    Attributes:
        workflow: "single-view", "multi-view" or "multi-cm".
        world_from_cm: (M, 4, 4) registered CM base pose per CM pose (M = 1 except multiple-CM).
        camera_from_cm: (K, 4, 4) registered CM pose in each view's camera.
        control_points_deg: (5,); joint_angles_deg: (27,).
        tip_world: (M, 3) distal end point; landmarks_world: (M, 2, 3) A and B.
        landmarks_px: (K, 2, 2) landmark projections in each view's image pixels.
        cost, converged, success, reason: final level's outcome (see ``RegistrationResult``).
        trace: per-level and per-iteration records; seconds: wall time of the registration.
        params: (11,) optimiser vector; view_names: (K,) labels.
        roi_images, roi_drrs: (K, h, w) fixed ROI images and final CM DRRs (without background) at
            the last level, for overlays; roi_cameras: their cameras.
        world_from_ref: (4, 4) multiple-CM reference frame (None otherwise).
        responses: per view, the measured response applied at the last level (``gain``, ``veil``,
            ``blur_mm``, ``rms``, ``level``), or None where none was measured (linear DRR).
    """

    workflow: str
    world_from_cm: np.ndarray
    camera_from_cm: np.ndarray
    control_points_deg: np.ndarray
    joint_angles_deg: np.ndarray
    tip_world: np.ndarray
    landmarks_world: np.ndarray
    landmarks_px: np.ndarray
    cost: float
    converged: bool
    success: bool
    reason: str
    trace: RegistrationTrace
    seconds: float
    params: np.ndarray
    view_names: list[str]
    roi_images: np.ndarray
    roi_drrs: np.ndarray
    roi_cameras: list[Camera]
    world_from_ref: np.ndarray | None = None
    responses: list[dict[str, float] | None] | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no images, no trace)."""
        d: dict[str, Any] = {
            "workflow": self.workflow,
            "world_from_cm": self.world_from_cm.tolist(),
            "camera_from_cm": {
                n: T.tolist() for n, T in zip(self.view_names, self.camera_from_cm, strict=True)
            },
            "control_points_deg": self.control_points_deg.tolist(),
            "joint_angles_deg": self.joint_angles_deg.tolist(),
            "tip_world_mm": self.tip_world.tolist(),
            "landmarks_world_mm": self.landmarks_world.tolist(),
            "landmarks_px": {n: p.tolist() for n, p in zip(self.view_names, self.landmarks_px, strict=True)},
            "cost": self.cost if math.isfinite(self.cost) else None,
            "converged": self.converged,
            "success": self.success,
            "reason": self.reason,
            "seconds": self.seconds,
            "n_evaluations": self.trace.n_evals,
            "params": self.params.tolist(),
        }
        if self.world_from_ref is not None:
            d["world_from_ref"] = self.world_from_ref.tolist()
        if self.responses is not None:
            d["responses"] = dict(zip(self.view_names, self.responses, strict=True))
        return d


def _initial_world_from_cm(
    views: Sequence[CMView],
    initial_world_from_cm: np.ndarray | None,
    initial_camera_from_cm: np.ndarray | None,
) -> np.ndarray:
    if (initial_world_from_cm is None) == (initial_camera_from_cm is None):
        raise ValueError("give exactly one of initial_world_from_cm and initial_camera_from_cm")
    if initial_world_from_cm is not None:
        T = np.asarray(initial_world_from_cm, dtype=np.float64)
    else:
        T = views[0].camera.world_from_camera @ np.asarray(initial_camera_from_cm, dtype=np.float64)
    if T.shape != (4, 4):
        raise ValueError(f"initial pose must be (4, 4), got {T.shape}")
    return T


class CMProblem:
    """The registration problem of :func:`register_cm`, built once: parameterisation, ROIs per level,
    batched moving-image renderer, landmark prior and the :class:`Registration` engine.

    Arguments as :func:`register_cm`. Useful beyond ``run``: :meth:`params_for` maps a pose and shape
    to the optimiser vector and ``registration.objective(level)`` evaluates the cost of candidates.
    """

    def __init__(
        self,
        views: Sequence[CMView],
        *,
        initial_control_points_deg: np.ndarray | Sequence[float],
        initial_world_from_cm: np.ndarray | None = None,
        initial_camera_from_cm: np.ndarray | None = None,
        base_from_cm: np.ndarray | None = None,
        config: CMRegistrationConfig | None = None,
        seed: int = 0,
    ) -> None:
        cfg = self.config = config or CMRegistrationConfig()
        views = self.views = list(views)
        if not views:
            raise ValueError("at least one view is needed")
        self.names = [v.name or f"view{k}" for k, v in enumerate(views)]
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"view names must be unique, got {self.names}")
        device = self.device = torch.device(cfg.device)
        cp0 = np.asarray(initial_control_points_deg, dtype=np.float64).reshape(-1)
        if cp0.shape != (cfg.cm_config.n_control_points,):
            raise ValueError(f"initial_control_points_deg must have {cfg.cm_config.n_control_points} values")
        world_from_cm0 = _initial_world_from_cm(views, initial_world_from_cm, initial_camera_from_cm)
        self.kinematics = CMKinematics(cfg.cm_config)

        # workflow and parameterisation (the world frame plays the parameterisation's "camera")
        self.param: CMPoseShape | MultiCMReference
        if base_from_cm is not None:
            bfc = np.asarray(base_from_cm, dtype=np.float64)
            if bfc.ndim != 3 or bfc.shape[1:] != (4, 4) or bfc.shape[0] != len(views):
                raise ValueError(f"base_from_cm must be ({len(views)}, 4, 4) for {len(views)} views")
            self.workflow: Workflow = "multi-cm"
            world_from_base0 = world_from_cm0 @ np.linalg.inv(bfc[0])
            base_from_ref, ref_from_cm = reference_frame(bfc)
            self.param = MultiCMReference(
                world_from_base0 @ base_from_ref.numpy(), ref_from_cm, cp0, device=device
            )
            self.pose_of_view = torch.arange(len(views), device=device)
        else:
            self.workflow = "single-view" if len(views) == 1 else "multi-view"
            self.param = CMPoseShape(world_from_cm0, cp0, device=device)
            self.pose_of_view = torch.zeros(len(views), dtype=torch.long, device=device)

        # ROI centres: the landmarks' midpoint, else the initial pose's projection
        W0 = (
            self.world_from_cm(torch.as_tensor(self.param.initial()[None], device=device))[0][0].cpu().numpy()
        )
        ab0 = self.kinematics.landmarks_cm(torch.as_tensor(cp0)).numpy()  # (2, 3)
        self.centers = []
        for k, v in enumerate(views):
            T = W0[int(self.pose_of_view[k])]
            proj = v.camera.project(ab0 @ T[:3, :3].T + T[:3, 3])
            self.centers.append(_landmark_center(v, proj.mean(axis=0)))

        self.renderer = CMRenderer(
            with_shaft(cfg.cm_config, cfg.shaft_length_mm), mu_per_mm=cfg.cm_mu_per_mm, device=device
        )
        # per-view response of the image to the DRR (linear until measured)
        self.gain = torch.ones(len(views), dtype=torch.float32, device=device)
        self.veil = torch.zeros(len(views), dtype=torch.float32, device=device)
        self.responses: list[dict[str, float] | None] = [None] * len(views)
        self._rois: dict[int, list[ViewROI]] = {}
        self._tensors: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]] = {}
        f64 = torch.float64
        self.K_full = torch.as_tensor(np.stack([v.camera.K for v in views]), dtype=f64, device=device)
        self.T_full = torch.as_tensor(
            np.stack([v.camera.camera_from_world for v in views]), dtype=f64, device=device
        )

        # landmark prior in full-detector pixels (the same at every level)
        priors: list[PriorFn] = []
        if cfg.landmark_sigma_full_px is not None:
            detected = np.full((len(views), 2, 2), np.nan)
            for k, v in enumerate(views):
                if v.landmarks_px is not None:
                    detected[k] = np.asarray(v.landmarks_px, dtype=np.float64) * v.image_binning
            if np.isfinite(detected).any():
                bins = torch.as_tensor([float(v.image_binning) for v in views], dtype=f64, device=device)

                def project(params: torch.Tensor) -> torch.Tensor:
                    return self.landmarks_px(params) * bins[None, :, None, None]

                priors.append(LandmarkPrior(project, detected, cfg.landmark_sigma_full_px))

        # a level finer than an image's binning cannot be formed from it: drop it
        coarsest = max(v.image_binning for v in views)
        self.levels = [lv for lv in cfg.levels if lv.downsample % coarsest == 0]
        if not self.levels:
            raise ValueError(f"no level is compatible with images binned {coarsest}x")
        if len(self.levels) < len(cfg.levels):
            logger.info(
                "dropped %d level(s) finer than the images' binning", len(cfg.levels) - len(self.levels)
            )
        self.pose_box = _pose_box(
            self.param.initial(),
            cfg.cm_config.n_control_points,
            max_rotation_deg=cfg.max_rotation_deg,
            max_translation_mm=cfg.max_translation_mm,
        )
        if self.pose_box is not None:
            box = (tuple(self.pose_box[0].tolist()), tuple(self.pose_box[1].tolist()))
            self.levels = [lv if lv.bounds is not None else lv.with_(bounds=box) for lv in self.levels]

        sigma, tolerance = cfg.control_point_sigma_deg, cfg.control_point_tolerance_deg
        measured = cfg.response == "measured" and cfg.shaft_length_mm > 0 and len(self.levels) > 1
        if len(views) == 1 and cfg.single_view_control_point_sigma_deg is not None and not measured:
            sigma, tolerance = cfg.single_view_control_point_sigma_deg, 0.0
        if sigma is not None:
            priors.append(control_point_prior(cp0, n_leading=6, sigma_deg=sigma, tolerance_deg=tolerance))

        self.registration = Registration(
            self.moving,
            self.fixed,
            self.levels,
            priors=priors,
            parameter_names=self.param.names,
            seed=seed,
            chunk_size=cfg.chunk_size,
            device=device,
            before_level=self._before_level,
        )

    # ----- pieces -----------------------------------------------------------------------------
    def world_from_cm(self, params: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """params (P, 11) → (world_from_cm (P, M, 4, 4), control points (P, 5))."""
        st = self.param(params)
        W = st.camera_from_cm
        return (W if W.dim() == 4 else W[:, None]), st.control_points_deg

    def landmarks_px(self, params: torch.Tensor) -> torch.Tensor:
        """(P, K, 2, 2) landmark projections in each view's image pixels."""
        W, cp = self.world_from_cm(params)
        return self.renderer.landmarks_px(self.T_full[None] @ W[:, self.pose_of_view], cp, self.K_full)

    def params_for(self, world_from_cm: np.ndarray, control_points_deg: np.ndarray) -> np.ndarray:
        """Optimiser vector (11,) of a pose (of the CM in ``views[0]``) and shape."""
        from fluoronav.geometry.transforms import params_from_transform

        W = np.asarray(world_from_cm, np.float64).reshape(-1, 4, 4)[0]
        if isinstance(self.param, MultiCMReference):
            target = W @ np.linalg.inv(self.param.ref_from_cm[0].cpu().numpy())
            ref0 = self.param.camera_from_ref0.cpu().numpy()
        else:
            target, ref0 = W, self.param.camera_from_cm0.cpu().numpy()
        d = params_from_transform(torch.as_tensor(np.linalg.inv(ref0) @ target)).numpy()
        d[:3] = np.degrees(d[:3])
        return np.concatenate([d, np.asarray(control_points_deg, np.float64)])

    def rois(self, level: LevelConfig) -> list[ViewROI]:
        """The views' ROIs at a level (computed once)."""
        if level.downsample not in self._rois:
            rs = [
                view_roi(
                    v, c, downsample_full=level.downsample, roi_size_full_px=self.config.roi_size_full_px
                )
                for v, c in zip(self.views, self.centers, strict=True)
            ]
            if len({(r.camera.rows, r.camera.cols) for r in rs}) != 1:
                raise ValueError("views give ROIs of different sizes; use images of compatible binning")
            self._rois[level.downsample] = rs
        return self._rois[level.downsample]

    def _level_tensors(self, level: LevelConfig) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        if level.downsample not in self._tensors:
            rs = self.rois(level)
            f64, dev = torch.float64, self.device
            K = torch.as_tensor(np.stack([r.camera.K for r in rs]), dtype=f64, device=dev)
            T = torch.as_tensor(np.stack([r.camera.camera_from_world for r in rs]), dtype=f64, device=dev)
            bg = None
            if self.config.use_background and any(r.background is not None for r in rs):
                stack = [r.background if r.background is not None else np.zeros_like(r.image) for r in rs]
                bg = torch.as_tensor(np.stack(stack), dtype=torch.float32, device=dev)
            self._tensors[level.downsample] = (K, T, bg)
        return self._tensors[level.downsample]

    def moving(
        self, params: torch.Tensor, level: LevelConfig, *, with_background: bool = True
    ) -> torch.Tensor:
        """Moving images (P, K, h, w): all candidates × views in one CM renderer call, through each
        view's response, (+ background)."""
        K, cam_from_world, bg = self._level_tensors(level)
        W, cp = self.world_from_cm(params)
        T = cam_from_world[None] @ W[:, self.pose_of_view]  # (P, K, 4, 4)
        roi = self.rois(level)[0].camera
        drr = self.renderer.render(T, cp, K, roi.rows, roi.cols)
        if any(r is not None for r in self.responses):
            drr = veil_response(drr, self.gain, self.veil)
        return drr if bg is None or not with_background else drr + bg[None]

    def measure_response(self, params: np.ndarray, *, level_index: int = -1) -> None:
        """Fit each view's response (gain, veil) on the CM's shaft projected at ``params`` (11,) and use
        it from now on; views whose fit fails keep their previous response."""
        cfg = self.config
        shaft = cfg.shaft_length_mm
        if shaft <= 0:
            return
        with torch.no_grad():
            p = torch.as_tensor(np.asarray(params)[None], dtype=torch.float64, device=self.device)
            W = self.world_from_cm(p)[0][0].cpu().numpy()  # (M, 4, 4)
        t = np.linspace(0.1 * shaft, 0.9 * shaft, 40)
        pts_cm = np.stack([np.zeros_like(t), np.zeros_like(t), -t], axis=1)
        for k, v in enumerate(self.views):
            Wk = W[int(self.pose_of_view[k])]
            pts_world = pts_cm @ Wk[:3, :3].T + Wk[:3, 3]
            pc = v.camera.to_camera(pts_world)
            if np.any(pc[:, 2] <= 0):
                continue
            fit = fit_tube_profile(
                v.image,
                v.camera.project(pts_world),
                outer_radius_mm=cfg.cm_config.outer_radius_mm,
                inner_radius_mm=cfg.cm_config.inner_radius_mm,
                px_per_mm=float(v.camera.K[0, 0] / pc[:, 2].mean()),
            )
            if fit is None:
                logger.info("%s: no response fit on the shaft; the DRR stays as it was", self.names[k])
                continue
            self.gain[k] = fit.mu_per_mm / cfg.cm_mu_per_mm
            self.veil[k] = fit.veil
            self.responses[k] = {
                "gain": float(self.gain[k]),
                "veil": fit.veil,
                "blur_mm": fit.blur_mm,
                "rms": fit.rms_residual,
                "level": level_index,
            }
            logger.debug("%s: response gain %.3f veil %.3f", self.names[k], float(self.gain[k]), fit.veil)

    def _before_level(self, index: int, level: LevelConfig, x: np.ndarray) -> None:
        if self.config.response == "measured" and index >= 1:
            self.measure_response(x, level_index=index)

    def fixed(self, level: LevelConfig) -> torch.Tensor:
        """Fixed ROI images (K, h, w) at a level."""
        return torch.as_tensor(np.stack([r.image for r in self.rois(level)]), device=self.device)

    # ----- run --------------------------------------------------------------------------------
    def run(self, x0: np.ndarray | None = None) -> CMRegistrationResult:
        """Run the levels from ``x0`` (default: the initial pose and shape)."""
        res = self.registration.run(self.param.initial() if x0 is None else x0)
        return self.result(res.params, res)

    def result(self, params: np.ndarray, res: Any) -> CMRegistrationResult:
        dev, kin = self.device, self.kinematics
        edge = _on_box_edge(
            np.asarray(params), self.pose_box, self.param.names, self.config.cm_config.n_control_points
        )
        if edge and res.success:
            res = replace(res, success=False, reason=f"{res.reason}; left the search box ({edge})")
        with torch.no_grad():
            p = torch.as_tensor(np.asarray(params)[None], dtype=torch.float64, device=dev)
            W, cp = self.world_from_cm(p)
            last = self.levels[-1]
            drr = self.moving(p, last, with_background=False)[0].cpu().numpy()
            cam_from_cm = (self.T_full[None] @ W[:, self.pose_of_view])[0]
            lm_px = self.landmarks_px(p)[0].cpu().numpy()
            Wn = W[0].cpu().numpy()
            cpn = cp[0].cpu()
            ab = kin.landmarks_cm(cpn).numpy()
            tip = kin.tip_cm(cpn).numpy()
        world_from_ref = None
        if isinstance(self.param, MultiCMReference):
            world_from_ref = (
                (self.param.camera_from_ref0 @ _delta(np.asarray(params)[:6], dev))[0].cpu().numpy()
            )
        rs = self.rois(last)
        return CMRegistrationResult(
            workflow=self.workflow,
            world_from_cm=Wn,
            camera_from_cm=cam_from_cm.cpu().numpy(),
            control_points_deg=cpn.numpy(),
            joint_angles_deg=kin.joint_angles_deg(cpn).numpy(),
            tip_world=np.einsum("mij,j->mi", Wn[:, :3, :3], tip) + Wn[:, :3, 3],
            landmarks_world=np.einsum("mij,lj->mli", Wn[:, :3, :3], ab) + Wn[:, None, :3, 3],
            landmarks_px=lm_px,
            cost=res.cost,
            converged=res.converged,
            success=res.success,
            reason=res.reason,
            trace=res.trace,
            seconds=res.seconds,
            params=np.asarray(res.params),
            view_names=self.names,
            roi_images=np.stack([r.image for r in rs]),
            roi_drrs=drr,
            roi_cameras=[r.camera for r in rs],
            world_from_ref=world_from_ref,
            responses=list(self.responses),
        )


def register_cm(
    views: Sequence[CMView],
    *,
    initial_control_points_deg: np.ndarray | Sequence[float],
    initial_world_from_cm: np.ndarray | None = None,
    initial_camera_from_cm: np.ndarray | None = None,
    base_from_cm: np.ndarray | None = None,
    config: CMRegistrationConfig | None = None,
    seed: int = 0,
) -> CMRegistrationResult:
    """Register the CM (pose + shape) to one or more X-ray images.

    Args:
        views: K views; single-view K = 1, multi-view K > 1 of one CM pose, multiple-CM one view per
            CM pose (same camera) in the order of ``base_from_cm``.
        initial_control_points_deg: (5,) initial shape (FBG reading).
        initial_world_from_cm: (4, 4) initial CM base pose in the world frame (for multiple-CM: the
            pose of the CM in ``views[0]``).
        initial_camera_from_cm: alternatively, the initial pose in ``views[0]``'s camera frame.
        base_from_cm: (M, 4, 4) multiple-CM only: the CM poses in the robot base frame (forward
            kinematics × hand-eye); their relative poses are held fixed.
        config: settings (default :class:`CMRegistrationConfig`).
        seed: CMA-ES seed.

    Returns:
        :class:`CMRegistrationResult`.
    """
    return CMProblem(
        views,
        initial_control_points_deg=initial_control_points_deg,
        initial_world_from_cm=initial_world_from_cm,
        initial_camera_from_cm=initial_camera_from_cm,
        base_from_cm=base_from_cm,
        config=config,
        seed=seed,
    ).run()


def register_cm_multistart(
    views: Sequence[CMView],
    starts_world_from_cm: Sequence[np.ndarray],
    *,
    initial_control_points_deg: np.ndarray | Sequence[float],
    base_from_cm: np.ndarray | None = None,
    config: CMRegistrationConfig | None = None,
    seed: int = 0,
    screen_iterations: int | None = 40,
) -> CMRegistrationResult:
    """Register from several start poses: screen every start on the first level, finish the best.

    Use it with the centreline initialisation's alternatives and their mirrors
    (:func:`~fluoronav.registration.centerline_init.mirror_about_chord`): a single view hardly tells
    the roll about the A→B chord apart, and a wrong basin cannot be left by a local optimiser.

    Screening runs the first (coarsest, cheapest) level from every start for at most
    ``screen_iterations`` CMA-ES generations (None: to convergence); the start with the lowest cost
    (NaN/inf count as worst) then runs all levels from where its screening ended. 15 generations
    proved too short to rank a start 70° off in roll below the right one (measured on a demo scene:
    costs 2.364 vs 2.372 after 15, 2.143 vs 1.767 at convergence).

    Args:
        views, initial_control_points_deg, base_from_cm, config, seed: as :func:`register_cm`.
        starts_world_from_cm: S ≥ 1 start poses (4, 4) in the world frame.
        screen_iterations: generation budget of the screening; with a single start there is none.

    Returns:
        the :class:`CMRegistrationResult` of the finished start; ``seconds`` includes the screening,
        ``reason`` notes which start won.
    """
    if len(starts_world_from_cm) == 0:
        raise ValueError("need at least one start pose")
    cfg = config or CMRegistrationConfig()
    cp0 = np.asarray(initial_control_points_deg, dtype=np.float64)
    if len(starts_world_from_cm) == 1:
        return register_cm(
            views,
            initial_control_points_deg=cp0,
            initial_world_from_cm=starts_world_from_cm[0],
            base_from_cm=base_from_cm,
            config=cfg,
            seed=seed,
        )
    screen = cfg.with_(levels=(cfg.levels[0].with_(max_iters=screen_iterations, restarts=0),))
    screened = [
        register_cm(
            views,
            initial_control_points_deg=cp0,
            initial_world_from_cm=W,
            base_from_cm=base_from_cm,
            config=screen,
            seed=seed,
        )
        for W in starts_world_from_cm
    ]
    costs = [r.cost if math.isfinite(r.cost) else math.inf for r in screened]
    k = int(np.argmin(costs))
    best = screened[k]
    logger.info("multi-start: screening costs %s, finishing start %d", np.round(costs, 4).tolist(), k)
    spent = sum(r.seconds for r in screened)
    res = register_cm(
        views,
        initial_control_points_deg=best.control_points_deg,
        initial_world_from_cm=best.world_from_cm[0],
        base_from_cm=base_from_cm,
        config=cfg,
        seed=seed + 1,
    )
    return replace(res, seconds=res.seconds + spent, reason=f"{res.reason}; start {k} of {len(screened)}")


@dataclass(frozen=True)
class RollScanResult:
    """Result of :func:`roll_scan`.

    Attributes:
        world_from_cm: (4, 4) the best-scoring pose.
        angle_deg: its turn about the A→B chord from the given pose.
        angles_deg, costs: (n,) the scanned turns and the winning start's image costs (lower is
            better; inf where the centreline gate excluded a turn).
        start_index: which start won (0: the given pose, k: ``alternatives[k - 1]``).
    """

    world_from_cm: np.ndarray
    angle_deg: float
    angles_deg: np.ndarray
    costs: np.ndarray
    start_index: int = 0


def roll_scan(
    view: CMView,
    world_from_cm: np.ndarray,
    control_points_deg: np.ndarray,
    *,
    n_angles: int = 36,
    alternatives: Sequence[np.ndarray] = (),
    centerline_px: np.ndarray | None = None,
    centerline_margin_px: float = 1.0,
    config: CMRegistrationConfig | None = None,
) -> RollScanResult:
    """Score the CM turned about its A→B chord through ``n_angles`` angles against one image.

    One view's centreline leaves the roll about the chord open (the paper's θ: 31° mean error); the
    image shows it through the bend's foreshortening, the notches and the shaft. Every turned pose
    keeps A and B where they were (on the landmarks' rays); all are rendered in one batch and scored
    with the first level's similarity (patch gradient NCC, no priors, linear DRR).

    Args:
        view: the image.
        world_from_cm: (4, 4) the pose to turn (e.g. a centreline initialisation).
        control_points_deg: (5,) shape.
        n_angles: turns evenly spaced over 360°.
        alternatives: further (4, 4) poses to turn the same way (e.g. the initialisation's other
            local minima), scored in the same batch; the best of all wins.
        centerline_px: (Q, 2) the extracted centreline in ``view``'s pixels: when given, only turns
            whose centreline cost is within ``centerline_margin_px`` of the best turn's compete
            (a turn that moves the projected bend off the centreline is not a candidate, however
            well its DRR scores).
        centerline_margin_px: see ``centerline_px``.
        config: registration settings (first level, ROI, shaft, μ).

    Returns:
        :class:`RollScanResult`; ``angle_deg`` is the turn of the winning pose, which is
        ``world_from_cm`` or one of the ``alternatives`` (``start_index``: 0 = ``world_from_cm``).
    """
    from fluoronav.registration.centerline_init import turn_about_chord

    cfg = (config or CMRegistrationConfig()).with_(
        landmark_sigma_full_px=None,
        control_point_sigma_deg=None,
        single_view_control_point_sigma_deg=None,
        max_rotation_deg=None,
        max_translation_mm=None,
        response="linear",
    )
    prob = CMProblem(
        [view], initial_control_points_deg=control_points_deg, initial_world_from_cm=world_from_cm, config=cfg
    )
    angles = np.arange(n_angles) * (360.0 / n_angles)
    starts = [np.asarray(world_from_cm, np.float64), *(np.asarray(W, np.float64) for W in alternatives)]
    poses = [turn_about_chord(W, control_points_deg, a, cfg.cm_config) for W in starts for a in angles]
    X = np.stack([prob.params_for(W, control_points_deg) for W in poses])
    costs = prob.registration.objective(prob.levels[0])(X).reshape(len(starts), n_angles)
    if centerline_px is not None:
        from fluoronav.detection.centerline import resample_polyline
        from fluoronav.registration.centerline_init import centerline_cost

        f64 = torch.float64
        cl_cm = prob.kinematics.centerline_cm(torch.as_tensor(control_points_deg, dtype=f64), n_points=48)
        cam_from_cm = np.stack([view.camera.camera_from_world @ W for W in poses])
        cl_cost = centerline_cost(
            torch.as_tensor(view.camera.K, dtype=f64),
            torch.as_tensor(cam_from_cm, dtype=f64),
            cl_cm,
            torch.as_tensor(resample_polyline(np.asarray(centerline_px, np.float64), 64), dtype=f64),
        ).numpy()
        gated = cl_cost.reshape(costs.shape) > float(np.min(cl_cost)) + centerline_margin_px
        costs = np.where(gated, np.inf, costs)
    i, k = np.unravel_index(int(np.argmin(costs)), costs.shape)
    return RollScanResult(
        world_from_cm=poses[i * n_angles + k],
        angle_deg=float(angles[k]),
        angles_deg=angles,
        costs=costs[i],
        start_index=int(i),
    )


def roll_scan_initialization(
    view: CMView,
    init: Any,
    centerline_px: np.ndarray,
    control_points_deg: np.ndarray,
    *,
    config: CMRegistrationConfig | None = None,
) -> RollScanResult:
    """:func:`roll_scan` of a centreline initialisation in ``view`` (its pose in ``view.camera``'s frame
    and its other refined minima as alternatives, its control points, else ``control_points_deg``),
    gated by the centreline it was fitted to."""
    to_world = view.camera.world_from_camera
    alts = [] if init.alternatives is None else [to_world @ T for T in init.alternatives[1:]]
    cp = init.control_points_deg if init.control_points_deg is not None else control_points_deg
    return roll_scan(
        view,
        to_world @ init.camera_from_cm,
        cp,
        alternatives=alts,
        centerline_px=centerline_px,
        config=config,
    )


def _pose_box(
    x0: np.ndarray,
    n_control_points: int,
    *,
    max_rotation_deg: float | None,
    max_translation_mm: float | None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """(lower, upper) of the pose parameters (every block of 3 rotations + 3 translations) around
    ``x0``; the last ``n_control_points`` stay effectively free (±90°, the prior holds them)."""
    if max_rotation_deg is None and max_translation_mm is None:
        return None
    unbounded = 1e6  # pycma wants finite bounds on every coordinate
    rot = unbounded if max_rotation_deg is None else max_rotation_deg
    trans = unbounded if max_translation_mm is None else max_translation_mm
    half = np.full(x0.size, 90.0)
    for k in range(0, x0.size - n_control_points, 6):
        half[k : k + 3], half[k + 3 : k + 6] = rot, trans
    return x0 - half, x0 + half


def _on_box_edge(
    params: np.ndarray,
    box: tuple[np.ndarray, np.ndarray] | None,
    names: Sequence[str] | None,
    n_control_points: int,
) -> str:
    """Names of the pose parameters within 2 % of the box's half-width of its edge ('' if none)."""
    if box is None:
        return ""
    lo, hi = box
    margin = 0.02 * (hi - lo) / 2.0
    hit = (params <= lo + margin) | (params >= hi - margin)
    hit[params.size - n_control_points :] = False  # control points are not boxed
    idx = np.flatnonzero(hit)
    labels = list(names) if names is not None else [f"p{i}" for i in range(params.size)]
    return ", ".join(labels[i] for i in idx)


def _delta(params6: np.ndarray, device: torch.device) -> torch.Tensor:
    from fluoronav.registration.parameterization import delta_transform

    return delta_transform(torch.as_tensor(np.asarray(params6)[None], dtype=torch.float64, device=device))


# ----- errors -------------------------------------------------------------------------------------
def cm_pose_errors(
    world_from_cm: np.ndarray,
    control_points_deg: np.ndarray,
    world_from_cm_true: np.ndarray,
    control_points_true_deg: np.ndarray,
    *,
    cm_config: CMConfig | None = None,
) -> dict[str, float]:
    """Errors of a registered CM against the truth (one pose).

    Returns:
        ``tip_error_mm`` (distance of the distal end points), ``base_translation_error_mm`` and
        ``base_rotation_error_deg`` of ``δ = T_gt⁻¹ · T_reg`` (expressed in the true CM base frame),
        ``notch_rotation_error_deg`` (mean |Δ joint angle| over the notches) and
        ``control_point_error_deg`` (mean |Δ control point|).
    """
    kin = CMKinematics(cm_config or CMConfig())
    T, Tg = np.asarray(world_from_cm, np.float64), np.asarray(world_from_cm_true, np.float64)
    cp, cpg = (
        torch.as_tensor(np.asarray(c, np.float64)) for c in (control_points_deg, control_points_true_deg)
    )
    tip = T[:3, :3] @ kin.tip_cm(cp).numpy() + T[:3, 3]
    tip_g = Tg[:3, :3] @ kin.tip_cm(cpg).numpy() + Tg[:3, 3]
    delta = np.linalg.inv(Tg) @ T
    return {
        "tip_error_mm": float(np.linalg.norm(tip - tip_g)),
        "base_translation_error_mm": float(np.linalg.norm(delta[:3, 3])),
        "base_rotation_error_deg": float(
            angle_between_rotations_deg(torch.as_tensor(T[:3, :3]), torch.as_tensor(Tg[:3, :3]))
        ),
        "notch_rotation_error_deg": float(
            (kin.joint_angles_deg(cp) - kin.joint_angles_deg(cpg)).abs().mean().item()
        ),
        "control_point_error_deg": float((cp - cpg).abs().mean().item()),
    }


# ----- overlays -----------------------------------------------------------------------------------
def _edges(img: np.ndarray) -> np.ndarray:
    """Edge mask of a DRR: Sobel magnitude above 20 % of its maximum."""
    from scipy import ndimage

    g = np.hypot(ndimage.sobel(img, axis=0), ndimage.sobel(img, axis=1))
    top = float(g.max())
    return g > 0.2 * top if top > 0 else np.zeros(img.shape, bool)


def _to_uint8(img: np.ndarray) -> np.ndarray:
    lo, hi = np.percentile(img, [1, 99])
    return (np.clip((img - lo) / max(hi - lo, 1e-12), 0, 1) * 255).astype(np.uint8)


def save_overlays(result: CMRegistrationResult, out_dir: str | Path, *, scale: int = 4) -> list[Path]:
    """Write ``overlay_<view>.png`` per view: edges of the final CM DRR (green) on the ROI image
    (as the paper's Fig. 12), upscaled ``scale``× (nearest). Returns the written paths."""
    import cv2

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, img, drr in zip(result.view_names, result.roi_images, result.roi_drrs, strict=True):
        gray = _to_uint8(img)
        rgb = np.repeat(gray[..., None], 3, axis=-1)
        edge = _edges(drr)
        rgb[edge] = (0, 255, 0)
        rgb = np.kron(rgb, np.ones((scale, scale, 1), np.uint8))
        p = out / f"overlay_{name}.png"
        cv2.imwrite(str(p), rgb[..., ::-1])
        paths.append(p)
    return paths
