"""The CM registration problem (Gao et al., IEEE TBME 69(1), 2022, sec. II-C): :class:`CMProblem`
and :func:`register_cm`.

K images (views), each of the CM at one of M base poses, with known cameras in a common world frame,
and 6 + 5 unknowns (a rigid perturbation of the CM base pose, or of the multiple-CM reference frame,
plus the five control points). All views share the working ROI size, so the whole CMA-ES population
× all views is rendered in one :class:`~fluoronav.rendering.cm.CMRenderer` call per generation.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import replace
from typing import Any, Literal

import numpy as np
import torch

from fluoronav.detection.tube_profile import fit_tube_profile
from fluoronav.geometry.transforms import params_from_transform
from fluoronav.manipulator.config import with_shaft
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.registration.cm.config import CMRegistrationConfig
from fluoronav.registration.cm.result import CMRegistrationResult
from fluoronav.registration.cm.views import CMView, ViewROI, landmark_center, view_roi
from fluoronav.registration.engine import PriorFn, Registration
from fluoronav.registration.levels import LevelConfig
from fluoronav.registration.parameterization import (
    CMPoseShape,
    MultiCMReference,
    delta_transform,
    reference_frame,
)
from fluoronav.registration.priors import LandmarkPrior, control_point_prior
from fluoronav.rendering.cm import CMRenderer
from fluoronav.rendering.response import veil_response

__all__ = [
    "BOX_EDGE_FRACTION",
    "CONTROL_POINT_BOX_DEG",
    "CMProblem",
    "Workflow",
    "cm_workflow",
    "on_box_edge",
    "pose_box",
    "register_cm",
]

logger = logging.getLogger(__name__)

Workflow = Literal["single-view", "multi-view", "multi-cm"]

#: half-width of the control points' search box, degrees: effectively free (their prior holds them)
CONTROL_POINT_BOX_DEG = 90.0
#: a pose parameter within this fraction of the box's half-width of its edge is "on the edge"
BOX_EDGE_FRACTION = 0.02
#: stands for "no bound" (pycma wants finite bounds on every coordinate)
_UNBOUNDED = 1e6


def cm_workflow(n_views: int, *, multiple_cm: bool) -> Workflow:
    """The workflow of ``n_views`` views: "multi-cm" with one CM pose per view (``base_from_cm``),
    else "single-view" or "multi-view"."""
    if multiple_cm:
        return "multi-cm"
    return "single-view" if n_views == 1 else "multi-view"


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
        prior_control_points_deg: np.ndarray | Sequence[float] | None = None,
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
        self.workflow = cm_workflow(len(views), multiple_cm=base_from_cm is not None)
        self.param: CMPoseShape | MultiCMReference
        self.param, self.pose_of_view = self._parameterisation(world_from_cm0, cp0, base_from_cm)
        self.centers = self._roi_centers(cp0)
        self.renderer = CMRenderer(
            with_shaft(cfg.cm_config, cfg.shaft_length_mm),
            mu_per_mm=cfg.cm_mu_per_mm,
            device=device,
            row_spans=cfg.row_spans,
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
        priors = self._landmark_priors()
        self.levels, self.pose_box = self._levels_and_box()
        reading = cp0 if prior_control_points_deg is None else np.asarray(prior_control_points_deg, float)
        priors += self._control_point_priors(reading.reshape(-1))
        self.levels = self._shape_steps_capped(self.levels)
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

    # ----- set-up -----------------------------------------------------------------------------
    def _parameterisation(
        self, world_from_cm0: np.ndarray, cp0: np.ndarray, base_from_cm: np.ndarray | None
    ) -> tuple[CMPoseShape | MultiCMReference, torch.Tensor]:
        """The parameterisation (the world frame plays its "camera") and each view's CM pose index:
        one pose, or with ``base_from_cm`` one per view about the multiple-CM reference frame."""
        views, device = self.views, self.device
        if base_from_cm is None:
            pose_of_view = torch.zeros(len(views), dtype=torch.long, device=device)
            return CMPoseShape(world_from_cm0, cp0, device=device), pose_of_view
        bfc = np.asarray(base_from_cm, dtype=np.float64)
        if bfc.ndim != 3 or bfc.shape[1:] != (4, 4) or bfc.shape[0] != len(views):
            raise ValueError(f"base_from_cm must be ({len(views)}, 4, 4) for {len(views)} views")
        world_from_base0 = world_from_cm0 @ np.linalg.inv(bfc[0])
        base_from_ref, ref_from_cm = reference_frame(bfc)
        param = MultiCMReference(world_from_base0 @ base_from_ref.numpy(), ref_from_cm, cp0, device=device)
        return param, torch.arange(len(views), device=device)

    def _roi_centers(self, cp0: np.ndarray) -> list[np.ndarray]:
        """Each view's ROI centre: its landmarks' midpoint, else the initial pose's projection."""
        W0 = (
            self.world_from_cm(torch.as_tensor(self.param.initial()[None], device=self.device))[0][0]
            .cpu()
            .numpy()
        )
        ab0 = self.kinematics.landmarks_cm(torch.as_tensor(cp0)).numpy()  # (2, 3)
        centers = []
        for k, v in enumerate(self.views):
            T = W0[int(self.pose_of_view[k])]
            proj = v.camera.project(ab0 @ T[:3, :3].T + T[:3, 3])
            centers.append(landmark_center(v, proj.mean(axis=0)))
        return centers

    def _landmark_priors(self) -> list[PriorFn]:
        """The prior on the detected landmarks, in full-detector pixels (the same at every level);
        none without a σ or detections."""
        views, sigma = self.views, self.config.landmark_sigma_full_px
        if sigma is None:
            return []
        detected = np.full((len(views), 2, 2), np.nan)
        for k, v in enumerate(views):
            if v.landmarks_px is not None:
                detected[k] = np.asarray(v.landmarks_px, dtype=np.float64) * v.image_binning
        if not np.isfinite(detected).any():
            return []
        bins = torch.as_tensor(
            [float(v.image_binning) for v in views], dtype=torch.float64, device=self.device
        )

        def project(params: torch.Tensor) -> torch.Tensor:
            return self.landmarks_px(params) * bins[None, :, None, None]

        return [LandmarkPrior(project, detected, sigma)]

    def _levels_and_box(self) -> tuple[list[LevelConfig], tuple[np.ndarray, np.ndarray] | None]:
        """The workflow's levels that the images' binning allows (a level finer than an image's
        binning cannot be formed from it), bounded by the pose box where there is one."""
        cfg = self.config
        coarsest = max(v.image_binning for v in self.views)
        levels = cfg.levels_for(self.workflow)
        kept = [lv for lv in levels if lv.downsample % coarsest == 0]
        if not kept:
            raise ValueError(f"no level is compatible with images binned {coarsest}x")
        if len(kept) < len(levels):
            logger.info("dropped %d level(s) finer than the images' binning", len(levels) - len(kept))
        box = pose_box(
            self.param.initial(),
            cfg.cm_config.n_control_points,
            max_rotation_deg=cfg.max_rotation_deg,
            max_translation_mm=cfg.max_translation_mm,
        )
        if box is not None:
            bounds = (tuple(box[0].tolist()), tuple(box[1].tolist()))
            kept = [lv if lv.bounds is not None else lv.with_(bounds=bounds) for lv in kept]
        return kept, box

    def _shape_prior(self) -> tuple[float, float] | None:
        """(σ, tolerance) of the control points' prior in degrees: one view whose response is not
        measured on several levels gets the single-view σ; None: no prior."""
        cfg = self.config
        sigma, tolerance = cfg.control_point_sigma_deg, cfg.control_point_tolerance_deg
        measured = cfg.response == "measured" and cfg.shaft_length_mm > 0 and len(self.levels) > 1
        if len(self.views) == 1 and cfg.single_view_control_point_sigma_deg is not None and not measured:
            sigma, tolerance = cfg.single_view_control_point_sigma_deg, 0.0
        return None if sigma is None else (float(sigma), float(tolerance))

    def _control_point_priors(self, cp0: np.ndarray) -> list[PriorFn]:
        """The prior on the control points about the FBG reading ``cp0`` (:meth:`_shape_prior`)."""
        prior = self._shape_prior()
        if prior is None:
            return []
        return [control_point_prior(cp0, n_leading=6, sigma_deg=prior[0], tolerance_deg=prior[1])]

    def _shape_steps_capped(self, levels: list[LevelConfig]) -> list[LevelConfig]:
        """The levels with the control points' steps at most the prior's tolerance plus
        ``control_point_step_sigmas`` of its σ (:class:`CMRegistrationConfig`)."""
        prior = self._shape_prior()
        n_cp = self.config.cm_config.n_control_points
        if prior is None:
            return levels
        cap = prior[1] + self.config.control_point_step_sigmas * prior[0]
        out = []
        for lv in levels:
            if np.size(lv.sigma) not in (1, 6 + n_cp):  # another parameterisation's steps
                out.append(lv)
                continue
            sigma = tuple(float(v) for v in np.broadcast_to(np.asarray(lv.sigma, float), (6 + n_cp,)))
            capped = sigma[:6] + tuple(min(v, cap) for v in sigma[6:])
            out.append(lv if capped == sigma else lv.with_(sigma=capped))
        return out

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
        span_lo, span_hi = cfg.response_shaft_span
        t = np.linspace(span_lo * shaft, span_hi * shaft, cfg.response_profiles)
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
        """The :class:`CMRegistrationResult` of optimiser vector ``params`` (11,) and the engine's
        result ``res`` (its cost, convergence, trace and time)."""
        dev, kin = self.device, self.kinematics
        edge = on_box_edge(
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
    prior_control_points_deg: np.ndarray | Sequence[float] | None = None,
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
        prior_control_points_deg: (5,) the centre of the shape's prior (the FBG reading) where the
            start is another shape (a registration continued); None: ``initial_control_points_deg``.

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
        prior_control_points_deg=prior_control_points_deg,
    ).run()


def pose_box(
    x0: np.ndarray,
    n_control_points: int,
    *,
    max_rotation_deg: float | None,
    max_translation_mm: float | None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """(lower, upper) of the pose parameters (every block of 3 rotations + 3 translations) around
    ``x0``; the last ``n_control_points`` stay effectively free (± :data:`CONTROL_POINT_BOX_DEG`, the
    prior holds them)."""
    if max_rotation_deg is None and max_translation_mm is None:
        return None
    rot = _UNBOUNDED if max_rotation_deg is None else max_rotation_deg
    trans = _UNBOUNDED if max_translation_mm is None else max_translation_mm
    half = np.full(x0.size, CONTROL_POINT_BOX_DEG)
    for k in range(0, x0.size - n_control_points, 6):
        half[k : k + 3], half[k + 3 : k + 6] = rot, trans
    return x0 - half, x0 + half


def on_box_edge(
    params: np.ndarray,
    box: tuple[np.ndarray, np.ndarray] | None,
    names: Sequence[str] | None,
    n_control_points: int,
) -> str:
    """Names of the pose parameters within :data:`BOX_EDGE_FRACTION` of the box's half-width of its
    edge ('' if none)."""
    if box is None:
        return ""
    lo, hi = box
    margin = BOX_EDGE_FRACTION * (hi - lo) / 2.0
    hit = (params <= lo + margin) | (params >= hi - margin)
    hit[params.size - n_control_points :] = False  # control points are not boxed
    idx = np.flatnonzero(hit)
    labels = list(names) if names is not None else [f"p{i}" for i in range(params.size)]
    return ", ".join(labels[i] for i in idx)


def _delta(params6: np.ndarray, device: torch.device) -> torch.Tensor:
    """(1, 4, 4) rigid transform of 6 pose parameters (degrees, mm)."""
    return delta_transform(torch.as_tensor(np.asarray(params6)[None], dtype=torch.float64, device=device))
