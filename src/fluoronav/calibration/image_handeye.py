"""Image-based hand-eye calibration inside the multiple-CM registration (Gao et al. 2022, §II-D, eqs. 5–6).

Data: M X-ray images of the CM from one static C-arm (the world frame), each at a robot pose
``rbase_from_ee_m``. Unknowns: ``world_from_rbase``, ``ee_from_cm``, one shape:

    world_from_cm_m = world_from_rbase · rbase_from_ee_m · ee_from_cm

parameterised by :class:`~fluoronav.registration.parameterization.HandEye` (17 parameters). The cost
is the CM registration's (:mod:`fluoronav.registration.cm`) plus the landmark prior of eq. 6 and a
flat-bottomed prior of the shape around the FBG reading. ``world_from_rbase`` starts from a PnP of
the detected landmarks; the stages and why: docs/robot-and-calibration.md.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
import torch

from fluoronav.calibration.handeye import check_motion
from fluoronav.calibration.results import HandEyeFailure
from fluoronav.geometry import se3
from fluoronav.manipulator.config import CMConfig, with_shaft
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.registration.cm import DEFAULT_CM_MU_PER_MM, CMView, ViewROI, view_roi
from fluoronav.registration.engine import PriorFn, Registration
from fluoronav.registration.levels import LevelConfig
from fluoronav.registration.parameterization import HandEye
from fluoronav.registration.priors import LandmarkPrior, control_point_prior
from fluoronav.registration.trace import RegistrationTrace
from fluoronav.rendering.cm import CMRenderer

__all__ = [
    "ImageHandEyeConfig",
    "ImageHandEyeProblem",
    "ImageHandEyeResult",
    "calibrate_hand_eye_from_images",
    "default_handeye_levels",
    "initial_world_from_rbase_pnp",
]

logger = logging.getLogger(__name__)

_REF_SIGMA = (2.0, 2.0, 2.0, 5.0, 5.0, 5.0)
_HE_SIGMA = (3.0, 3.0, 3.0, 5.0, 5.0, 5.0)
_CP_SIGMA = (1.5,) * 5
#: σ of parameters held fixed in a stage (CMA-ES needs positive σ; this moves them by ~1e-5)
_HELD = 1e-6


def default_handeye_levels(
    *,
    popsize: int = 50,
    two_stage: bool = True,
    refine: bool = True,
    max_iters: tuple[int, int, int] = (60, 300, 200),
) -> tuple[LevelConfig, ...]:
    """Levels of the image-based hand-eye (17 parameters, ``downsample`` in full-detector pixels).

    ``two_stage``: a first 4× level with the hand-eye held (multiple-CM registration with the initial
    hand-eye, §II-C), then the full 17-parameter 4× level (CMA-ES as the authors' CM level, tolfun
    1e-3 as :func:`~fluoronav.registration.cm.default_cm_levels`); ``refine``: a local 2× level (σ/4).
    ``max_iters``: generation caps of the three levels (the cost of a generation grows with M); the
    caps 150 / 60 of the first version stopped the 4× and 2× levels before convergence at M = 8–30.
    """
    levels = []
    if two_stage:
        levels.append(
            LevelConfig(
                sigma=_REF_SIGMA + (_HELD,) * 6 + _CP_SIGMA,
                downsample=4,
                stride=5,
                popsize=popsize,
                tolfun=1e-3,
                max_iters=max_iters[0],
                name="multi-cm-4x",
            )
        )
    full = _REF_SIGMA + _HE_SIGMA + _CP_SIGMA
    levels.append(
        LevelConfig(
            sigma=full,
            downsample=4,
            stride=5,
            popsize=popsize,
            tolfun=1e-3,
            max_iters=max_iters[1],
            name="handeye-4x",
        )
    )
    if refine:
        levels.append(
            LevelConfig(
                sigma=tuple(s / 4.0 for s in full),
                downsample=2,
                stride=5,
                popsize=24,
                tolfun=1e-4,
                max_iters=max_iters[2],
                name="handeye-2x",
            )
        )
    return tuple(levels)


@dataclass(frozen=True)
class ImageHandEyeConfig:
    """Settings of :func:`calibrate_hand_eye_from_images`.

    Attributes:
        levels: registration levels (17 σ values each); ``downsample`` in full-detector pixels.
        roi_size_full_px: square ROI side around the landmarks, full-detector pixels (authors: 500).
        landmark_sigma_full_px: eq. 6 σ in full-detector pixels (authors: 100); None disables it.
        control_point_sigma_deg, control_point_tolerance_deg: prior of the control points around
            the initial values (the FBG reading): free within ± tolerance, Gaussian walls of σ
            beyond (as :class:`~fluoronav.registration.cm.CMRegistrationConfig`); None: no prior.
        min_axis_spread_deg: degeneracy threshold of :func:`~fluoronav.calibration.handeye.check_motion`.
        cm_mu_per_mm, cm_config: CM DRR attenuation and geometry.
        shaft_length_mm: length of the rigid tube the CM is mounted on, rendered as a longer base
            (:func:`~fluoronav.manipulator.config.with_shaft`): it shows in the images and pins the
            base's direction down; 0 for a bare CM. The simulator's default is the same 50 mm.
        chunk_size: render at most this many candidates per call (None: whole population).
        device: torch device.
    """

    levels: tuple[LevelConfig, ...] = field(default_factory=default_handeye_levels)
    roi_size_full_px: int = 500
    landmark_sigma_full_px: float | None = 100.0
    control_point_sigma_deg: float | None = 0.25
    control_point_tolerance_deg: float = 1.0
    min_axis_spread_deg: float = 5.0
    cm_mu_per_mm: float = DEFAULT_CM_MU_PER_MM
    cm_config: CMConfig = field(default_factory=CMConfig)
    shaft_length_mm: float = 50.0
    chunk_size: int | None = None
    device: str = "cpu"

    def with_(self, **changes: Any) -> ImageHandEyeConfig:
        return replace(self, **changes)


@dataclass(frozen=True, eq=False)
class ImageHandEyeResult:
    """Outcome of :func:`calibrate_hand_eye_from_images`.

    Attributes:
        ee_from_cm: (4, 4) hand-eye matrix T_CM^ee.
        world_from_rbase: (4, 4) robot base in the views' world frame.
        carm_from_rbase: (4, 4) robot base in the C-arm (first view's camera) frame.
        control_points_deg: (5,) registered shape.
        world_from_cm: (M, 4, 4) registered CM base pose per image.
        landmarks_px: (M, 2, 2) model landmark projections (image pixels).
        residuals_px: (M,) per pose, mean distance of the projected model landmarks A, B from the
            given landmarks (image pixels; NaN where none were given).
        cost, converged, reason: last level's outcome; trace: per-level records; seconds: wall time.
        params: (17,) final optimiser vector; view_names: (M,) labels.
        roi_images, roi_drrs, roi_cameras: last-level ROIs and CM DRRs (overlays).
    """

    ee_from_cm: np.ndarray
    world_from_rbase: np.ndarray
    carm_from_rbase: np.ndarray
    control_points_deg: np.ndarray
    world_from_cm: np.ndarray
    landmarks_px: np.ndarray
    residuals_px: np.ndarray
    cost: float
    converged: bool
    reason: str
    trace: RegistrationTrace
    seconds: float
    params: np.ndarray
    view_names: list[str]
    roi_images: np.ndarray
    roi_drrs: np.ndarray
    roi_cameras: list[Any]

    @property
    def ok(self) -> bool:
        return True

    @property
    def n_poses(self) -> int:
        return int(self.world_from_cm.shape[0])

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no images, no trace)."""
        res = self.residuals_px
        return {
            "ee_from_cm": self.ee_from_cm.tolist(),
            "world_from_rbase": self.world_from_rbase.tolist(),
            "carm_from_rbase": self.carm_from_rbase.tolist(),
            "control_points_deg": self.control_points_deg.tolist(),
            "world_from_cm": {
                n: T.tolist() for n, T in zip(self.view_names, self.world_from_cm, strict=True)
            },
            "landmark_residuals_px": {
                n: (None if not np.isfinite(r) else float(r))
                for n, r in zip(self.view_names, res, strict=True)
            },
            "mean_landmark_residual_px": float(np.nanmean(res)) if np.isfinite(res).any() else None,
            "cost": self.cost if np.isfinite(self.cost) else None,
            "converged": self.converged,
            "reason": self.reason,
            "seconds": self.seconds,
            "n_poses": self.n_poses,
            "n_evaluations": self.trace.n_evals,
        }


def initial_world_from_rbase_pnp(
    views: Sequence[CMView],
    rbase_from_ee: np.ndarray,
    ee_from_cm: np.ndarray,
    control_points_deg: np.ndarray,
    *,
    cm_config: CMConfig | None = None,
) -> np.ndarray | None:
    """Closed-form ``world_from_rbase`` from the landmarks: SQPnP on the 2M points A, B (robot base
    frame through ``ee_from_cm``) and their 2D landmarks in the one camera (``views[0].camera``).

    Returns:
        (4, 4) or None when fewer than 4 landmarks are available or PnP fails.
    """
    kin = CMKinematics(cm_config or CMConfig())
    ab = kin.landmarks_cm(torch.as_tensor(np.asarray(control_points_deg, np.float64))).numpy()
    obj, img = [], []
    for v, T in zip(views, np.asarray(rbase_from_ee, np.float64), strict=True):
        if v.landmarks_px is None:
            continue
        lm = np.asarray(v.landmarks_px, np.float64)
        P = T @ ee_from_cm
        for k in range(2):
            if np.all(np.isfinite(lm[k])):
                obj.append(P[:3, :3] @ ab[k] + P[:3, 3])
                img.append(lm[k])
    if len(obj) < 4:
        return None
    cam = views[0].camera
    ok, rvec, tvec = cv2.solvePnP(np.asarray(obj), np.asarray(img), cam.K, None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        return None
    camera_from_rbase = se3.make(cv2.Rodrigues(rvec)[0], np.asarray(tvec).reshape(3))
    return cam.world_from_camera @ camera_from_rbase


class ImageHandEyeProblem:
    """The 17-parameter problem (built once): parameterisation, ROIs, renderer, priors, engine.

    Arguments as :func:`calibrate_hand_eye_from_images` (``initial_world_from_rbase`` required).
    """

    def __init__(
        self,
        views: Sequence[CMView],
        rbase_from_ee: np.ndarray,
        *,
        initial_ee_from_cm: np.ndarray,
        initial_control_points_deg: np.ndarray | Sequence[float],
        initial_world_from_rbase: np.ndarray,
        config: ImageHandEyeConfig | None = None,
        seed: int = 0,
    ) -> None:
        cfg = self.config = config or ImageHandEyeConfig()
        self.views = list(views)
        self.names = [v.name or f"pose{m}" for m, v in enumerate(self.views)]
        dev = self.device = torch.device(cfg.device)
        cp0 = np.asarray(initial_control_points_deg, np.float64).reshape(-1)
        self.param = HandEye(initial_world_from_rbase, rbase_from_ee, initial_ee_from_cm, cp0, device=dev)
        self.kinematics = CMKinematics(cfg.cm_config)
        self.renderer = CMRenderer(
            with_shaft(cfg.cm_config, cfg.shaft_length_mm), mu_per_mm=cfg.cm_mu_per_mm, device=dev
        )
        f64 = torch.float64
        self.K_full = torch.as_tensor(np.stack([v.camera.K for v in self.views]), dtype=f64, device=dev)
        self.T_full = torch.as_tensor(
            np.stack([v.camera.camera_from_world for v in self.views]), dtype=f64, device=dev
        )
        self.bins = torch.as_tensor([float(v.image_binning) for v in self.views], dtype=f64, device=dev)
        # ROI centres: the given landmarks' midpoint, else the initial pose's projection
        p0 = torch.as_tensor(self.param.initial()[None], device=dev)
        lm0 = self.landmarks_px(p0)[0].cpu().numpy()
        self.centers = []
        for v, l0 in zip(self.views, lm0, strict=True):
            lm = None if v.landmarks_px is None else np.asarray(v.landmarks_px, np.float64)
            ok = lm is not None and lm.shape == (2, 2) and np.all(np.isfinite(lm))
            self.centers.append(lm.mean(axis=0) if ok and lm is not None else l0.mean(axis=0))
        priors: list[PriorFn] = []
        self.detected = np.full((len(self.views), 2, 2), np.nan)
        for m, v in enumerate(self.views):
            if v.landmarks_px is not None:
                self.detected[m] = np.asarray(v.landmarks_px, np.float64)
        if cfg.landmark_sigma_full_px is not None and np.isfinite(self.detected).any():
            full = self.detected * self.bins.cpu().numpy()[:, None, None]

            def project(params: torch.Tensor) -> torch.Tensor:
                return self.landmarks_px(params) * self.bins[None, :, None, None]

            priors.append(LandmarkPrior(project, full, cfg.landmark_sigma_full_px))
        if cfg.control_point_sigma_deg is not None:
            priors.append(
                control_point_prior(
                    cp0,
                    n_leading=12,
                    sigma_deg=cfg.control_point_sigma_deg,
                    tolerance_deg=cfg.control_point_tolerance_deg,
                )
            )
        coarsest = max(v.image_binning for v in self.views)
        self.levels = [lv for lv in cfg.levels if lv.downsample % coarsest == 0]
        if not self.levels:
            raise ValueError(f"no level is compatible with images binned {coarsest}x")
        self._rois: dict[int, list[ViewROI]] = {}
        self.registration = Registration(
            self.moving,
            self.fixed,
            self.levels,
            priors=priors,
            parameter_names=self.param.names,
            seed=seed,
            chunk_size=cfg.chunk_size,
            device=dev,
        )

    def world_from_cm(self, params: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """params (P, 17) → (world_from_cm (P, M, 4, 4), control points (P, 5))."""
        st = self.param(params)
        return st.camera_from_cm, st.control_points_deg

    def landmarks_px(self, params: torch.Tensor) -> torch.Tensor:
        """(P, M, 2, 2) model landmark projections in each view's image pixels."""
        W, cp = self.world_from_cm(params)
        return self.renderer.landmarks_px(self.T_full[None] @ W, cp, self.K_full)

    def rois(self, level: LevelConfig) -> list[ViewROI]:
        if level.downsample not in self._rois:
            self._rois[level.downsample] = [
                view_roi(
                    v, c, downsample_full=level.downsample, roi_size_full_px=self.config.roi_size_full_px
                )
                for v, c in zip(self.views, self.centers, strict=True)
            ]
        return self._rois[level.downsample]

    def fixed(self, level: LevelConfig) -> torch.Tensor:
        return torch.as_tensor(np.stack([r.image for r in self.rois(level)]), device=self.device)

    def moving(self, params: torch.Tensor, level: LevelConfig) -> torch.Tensor:
        """(P, M, h, w): all candidates × all poses in one renderer call."""
        rs = self.rois(level)
        f64 = torch.float64
        K = torch.as_tensor(np.stack([r.camera.K for r in rs]), dtype=f64, device=self.device)
        T = torch.as_tensor(np.stack([r.camera.camera_from_world for r in rs]), dtype=f64, device=self.device)
        W, cp = self.world_from_cm(params)
        return self.renderer.render(T[None] @ W, cp, K, rs[0].camera.rows, rs[0].camera.cols)

    def run(self) -> ImageHandEyeResult:
        res = self.registration.run(self.param.initial())
        with torch.no_grad():
            p = torch.as_tensor(res.params[None], dtype=torch.float64, device=self.device)
            st = self.param(p)
            W = st.camera_from_cm[0].cpu().numpy()
            ee_from_cm = st.ee_from_cm[0].cpu().numpy()
            world_from_ref = st.camera_from_ref[0].cpu().numpy()
            lm = self.landmarks_px(p)[0].cpu().numpy()
            drr = self.moving(p, self.levels[-1])[0].cpu().numpy()
        world_from_rbase = world_from_ref @ np.linalg.inv(self.param.base_from_ref.cpu().numpy())
        resid = np.linalg.norm(lm - self.detected, axis=-1)  # (M, 2), NaN where missing
        with np.errstate(invalid="ignore"):
            per_pose = np.where(
                np.isfinite(resid).any(axis=1),
                np.nanmean(np.where(np.isfinite(resid), resid, np.nan), axis=1),
                np.nan,
            )
        rs = self.rois(self.levels[-1])
        return ImageHandEyeResult(
            ee_from_cm=ee_from_cm,
            world_from_rbase=world_from_rbase,
            carm_from_rbase=self.views[0].camera.camera_from_world @ world_from_rbase,
            control_points_deg=res.params[12:17].copy(),
            world_from_cm=W,
            landmarks_px=lm,
            residuals_px=per_pose,
            cost=res.cost,
            converged=res.converged,
            reason=res.reason,
            trace=res.trace,
            seconds=res.seconds,
            params=np.asarray(res.params),
            view_names=self.names,
            roi_images=np.stack([r.image for r in rs]),
            roi_drrs=drr,
            roi_cameras=[r.camera for r in rs],
        )


def calibrate_hand_eye_from_images(
    views: Sequence[CMView],
    rbase_from_ee: np.ndarray,
    *,
    initial_ee_from_cm: np.ndarray,
    initial_control_points_deg: np.ndarray | Sequence[float],
    initial_world_from_rbase: np.ndarray | None = None,
    config: ImageHandEyeConfig | None = None,
    seed: int = 0,
) -> ImageHandEyeResult | HandEyeFailure:
    """Image-based hand-eye calibration (eqs. 5, 6): register the M images jointly for
    ``world_from_rbase``, ``ee_from_cm`` and the shape.

    Args:
        views: M :class:`~fluoronav.registration.cm.CMView` of one static C-arm (same camera pose; the
            cameras' world frame is the frame ``world_from_rbase`` is returned in), with landmarks.
        rbase_from_ee: (M, 4, 4) robot forward kinematics per image (mm).
        initial_ee_from_cm: (4, 4) initial hand-eye guess (e.g. the mount's design).
        initial_control_points_deg: (5,) FBG reading.
        initial_world_from_rbase: (4, 4) initial robot base pose; None: PnP of the landmarks
            (:func:`initial_world_from_rbase_pnp`).
        config: settings; seed: CMA-ES seed.

    Returns:
        :class:`ImageHandEyeResult`, or :class:`HandEyeFailure` for M < 3, degenerate motion
        (rotations about one axis), or no initial robot base pose.
    """
    t0 = time.perf_counter()
    cfg = config or ImageHandEyeConfig()
    A = np.asarray(rbase_from_ee, np.float64)
    views = list(views)
    if A.ndim != 3 or A.shape[1:] != (4, 4) or A.shape[0] != len(views):
        raise ValueError(f"rbase_from_ee must be ({len(views)}, 4, 4) for {len(views)} views, got {A.shape}")
    bad = check_motion(A, min_axis_spread_deg=cfg.min_axis_spread_deg)
    if bad is not None:
        return HandEyeFailure(bad.reason, method="IMAGE", n_poses=bad.n_poses)
    X0 = np.asarray(initial_ee_from_cm, np.float64)
    cp0 = np.asarray(initial_control_points_deg, np.float64)
    W0 = initial_world_from_rbase
    if W0 is None:
        W0 = initial_world_from_rbase_pnp(views, A, X0, cp0, cm_config=cfg.cm_config)
        if W0 is None:
            return HandEyeFailure(
                "no initial robot base pose: fewer than 4 landmarks or PnP failed",
                method="IMAGE",
                n_poses=len(views),
            )
    problem = ImageHandEyeProblem(
        views,
        A,
        initial_ee_from_cm=X0,
        initial_control_points_deg=cp0,
        initial_world_from_rbase=W0,
        config=cfg,
        seed=seed,
    )
    out = problem.run()
    logger.info(
        "image hand-eye (M = %d): cost %.4g, %s, %.1f s",
        len(views),
        out.cost,
        out.reason,
        time.perf_counter() - t0,
    )
    return replace(out, seconds=time.perf_counter() - t0)
