"""Single-view centreline initialisation of the CM pose (Gao et al., IEEE TBME 69(1), 2022, sec. II-B).

See :mod:`fluoronav.registration.centerline` for the method; this module holds its settings
(:class:`CenterlineInitConfig`), the search (:func:`centerline_initialize`) and the depth range about
an anatomical anchor (:func:`depth_range_about`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
from torch.nn import functional as nnf

from fluoronav.detection.centerline import resample_polyline
from fluoronav.errors import InputError, RegistrationFailure
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator import CMConfig, CMKinematics
from fluoronav.registration.centerline.cost import centerline_cost, checked_array
from fluoronav.registration.centerline.geometry import normalize, poses_from_depth_theta, roll_of_pose
from fluoronav.registration.centerline.joint_fit import JointFitConfig, joint_fit
from fluoronav.registration.centerline.shaft_depth import (
    SHAFT_DEPTH_SIGMA_FRACTION,
    ShaftDepthCue,
    measure_shaft_depth,
    shaft_depth_residual,
)

__all__ = [
    "ANATOMY_DEPTH_WINDOW_MM",
    "BRANCHES",
    "CenterlineInitConfig",
    "CenterlineInitResult",
    "centerline_initialize",
    "depth_range_about",
    "grid_local_minima",
    "grid_shape",
]

logger = logging.getLogger(__name__)

#: names of the two roots of B on its ray, by branch index
BRANCHES = ("near", "far")

#: half-width of the depth search around an anatomical anchor (the femoral head): the CM works at
#: the hip, and one view's centreline cannot tell depth from tilt (equal-cost minima 175 mm apart)
ANATOMY_DEPTH_WINDOW_MM = 100.0


@dataclass(frozen=True)
class CenterlineInitConfig:
    """Settings of :func:`centerline_initialize`.

    Attributes:
        n_samples: number of (d_A, θ) samples (stratified uniform); each is tried on both branches;
            at least 8.
        theta_cells_per_depth_cell: shape of the stratified grid, θ cells per depth cell (1.6: 25 × 40
            for 1,000 samples; θ is the better determined of the two).
        refine: refine the best grid local minima by a batched compass search.
        n_starts: number of grid local minima refined.
        refine_iterations: compass-search iterations (3 × 3 stencil, step halved on failure).
        joint_refine: polish the refined minima by the 11-DoF least-squares fit
            (:mod:`~fluoronav.registration.centerline.joint_fit`); needs ``refine``.
        joint_fit: priors and solver settings of that fit.
        n_model_points: points on the model centreline A → B.
        n_extracted_points: the extracted centreline is resampled to this many points by arc length.
        trim_fraction: robust cost, fraction of the largest distances dropped (each direction).
        default_depth_range_sdd: the depth range searched when none is given, as fractions of the
            source-to-detector distance.
        shaft_length_mm: length of the rigid shaft behind A (the simulator's and registration's 50);
            with an image and a shaft its width gives a depth cue (0: none).
        depth_cue_sigma_fraction: σ of the shaft depth as a fraction of it.
        return_candidates: keep the grid samples and costs in the result.
    """

    n_samples: int = 1000
    theta_cells_per_depth_cell: float = 1.6
    refine: bool = True
    n_starts: int = 4
    refine_iterations: int = 30
    joint_refine: bool = True
    joint_fit: JointFitConfig = field(default_factory=JointFitConfig)
    n_model_points: int = 48
    n_extracted_points: int = 64
    trim_fraction: float = 0.1
    default_depth_range_sdd: tuple[float, float] = (0.3, 0.7)
    shaft_length_mm: float = 50.0
    depth_cue_sigma_fraction: float = SHAFT_DEPTH_SIGMA_FRACTION
    return_candidates: bool = False

    def with_(self, **changes: Any) -> CenterlineInitConfig:
        """Copy with changes."""
        return replace(self, **changes)


@dataclass(frozen=True)
class CenterlineInitResult:
    """Result of :func:`centerline_initialize`.

    Attributes:
        camera_from_cm: (4, 4) float64 pose of the CM base frame in the camera (source) frame, mm.
        depth_mm: d_A, camera-frame z of landmark A.
        theta_deg: roll θ about the chord A→B in [0, 360) (see
            :mod:`~fluoronav.registration.centerline` for θ = 0).
        branch: ``"near"`` or ``"far"`` root for B on its ray.
        cost_px: centreline cost of the returned pose (pixels).
        grid_cost_px: best cost of the sampled grid, before refinement (pixels).
        n_evaluated: number of feasible candidates whose cost was evaluated (grid + refinement).
        depth_range_mm: the searched depth interval (the requested range clipped to feasibility).
        candidate_costs: (n_depth, n_theta, 2) grid costs (inf = infeasible), if requested.
        candidate_depth_mm, candidate_theta_deg: (n_depth, n_theta) grid samples, if requested.
        alternatives: (S, 4, 4) ``camera_from_cm`` of the refined local minima (up to ``n_starts``),
            lowest cost first (the first is the returned pose when refinement improved on the grid);
            starts for a multi-start registration.
        alternative_costs_px: (S,) their centreline costs.
        control_points_deg: (5,) the control points of the returned pose (the FBG reading unless the
            joint refinement moved them).
        shaft_depth_mm: the shaft depth measured from its width and used as a cue (None: none).
    """

    camera_from_cm: np.ndarray
    depth_mm: float
    theta_deg: float
    branch: str
    cost_px: float
    grid_cost_px: float
    n_evaluated: int
    depth_range_mm: tuple[float, float]
    candidate_costs: np.ndarray | None = None
    candidate_depth_mm: np.ndarray | None = None
    candidate_theta_deg: np.ndarray | None = None
    alternatives: np.ndarray | None = None
    alternative_costs_px: np.ndarray | None = None
    control_points_deg: np.ndarray | None = None
    shaft_depth_mm: float | None = None

    def world_from_cm(self, camera: Camera) -> np.ndarray:
        """(4, 4) pose in the camera's world frame."""
        return camera.world_from_camera @ self.camera_from_cm


def grid_shape(n_samples: int, theta_cells_per_depth_cell: float) -> tuple[int, int]:
    """(n_depth, n_theta) cells of the stratified grid of about ``n_samples`` cells."""
    n_theta = max(4, round(math.sqrt(theta_cells_per_depth_cell * n_samples)))
    n_depth = max(2, round(n_samples / n_theta))
    return n_depth, n_theta


def grid_local_minima(cost: torch.Tensor) -> torch.Tensor:
    """(B, D, T) grid costs, θ cyclic → bool mask of finite 8-neighbourhood minima (ties kept)."""
    c = torch.where(torch.isfinite(cost), cost, torch.full_like(cost, 1e300))
    padded = torch.cat([c[..., -1:], c, c[..., :1]], dim=-1)  # wrap θ
    padded = nnf.pad(padded.unsqueeze(1), (0, 0, 1, 1), value=1e300)  # depth edges
    neigh_min = -nnf.max_pool2d(-padded, kernel_size=3, stride=1).squeeze(1)
    return (c <= neigh_min) & torch.isfinite(cost)


@dataclass(frozen=True)
class _Search:
    """One view's search space and cost: the rays of A and B (z = 1), the model's landmarks and
    centreline (CM frame, mm), the extracted centreline (pixels) and the depth interval of A (mm)."""

    K: torch.Tensor
    ray_a: torch.Tensor
    ray_b: torch.Tensor
    landmarks_cm: torch.Tensor
    centerline_cm: torch.Tensor
    extracted: torch.Tensor
    trim_fraction: float
    cue: ShaftDepthCue | None
    lo: float
    hi: float

    def poses(
        self, depth: torch.Tensor, theta: torch.Tensor, branch: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(N,) candidates → ``camera_from_cm`` (N, 4, 4) and feasibility (N,)."""
        return poses_from_depth_theta(self.ray_a, self.ray_b, self.landmarks_cm, depth, theta, branch)

    def evaluate(self, depth: torch.Tensor, theta: torch.Tensor, branch: torch.Tensor) -> torch.Tensor:
        """(N,) candidates → cost (N,) pixels (inf: infeasible), with the depth cue's term."""
        T, ok = self.poses(depth, theta, branch)
        cost = torch.full_like(depth, math.inf)
        if bool(ok.any()):
            cost[ok] = centerline_cost(
                self.K, T[ok], self.centerline_cm, self.extracted, trim_fraction=self.trim_fraction
            )
            if self.cue is not None:
                cost[ok] = cost[ok] + 0.5 * shaft_depth_residual(self.cue, self.K, T[ok]) ** 2
        return cost


@dataclass(frozen=True)
class _Grid:
    """The stratified grid: samples (D, T) of depth (mm) and θ (degrees), on both branches
    (2, D, T), their costs (2, D, T) and the cells' sides."""

    depth: torch.Tensor
    theta: torch.Tensor
    depth_b: torch.Tensor
    theta_b: torch.Tensor
    branch_b: torch.Tensor
    cost: torch.Tensor
    step_d: float
    step_t: float

    def best(self) -> tuple[tuple[float, float, int], float]:
        """The lowest-cost sample's (depth, θ, branch) and its cost."""
        flat = int(torch.argmin(self.cost))
        n_cells = self.depth.numel()
        best = (float(self.depth_b.reshape(-1)[flat]), float(self.theta_b.reshape(-1)[flat]), flat // n_cells)
        return best, float(self.cost.reshape(-1)[flat])


def _checked_inputs(
    camera: Camera,
    landmarks_px: np.ndarray | torch.Tensor,
    centerline_px: np.ndarray | torch.Tensor,
    control_points_deg: np.ndarray | torch.Tensor,
    opt: CenterlineInitConfig,
    cfg: CMConfig,
    depth_range_mm: tuple[float, float] | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """The inputs of :func:`centerline_initialize` checked: ``(landmarks, centreline, control
    points, depth min, depth max)``; InputError where malformed."""
    lm = checked_array(landmarks_px, (2, 2), "landmarks_px")
    cl = checked_array(centerline_px, None, "centerline_px")
    if cl.ndim != 2 or cl.shape[1] != 2 or cl.shape[0] < 2:
        raise InputError("centerline_px", f"must have shape (P >= 2, 2), got {cl.shape}")
    cp = checked_array(control_points_deg, (cfg.n_control_points,), "control_points_deg")
    if opt.n_samples < 8:
        raise InputError("n_samples", f"must be at least 8, got {opt.n_samples}")
    if depth_range_mm is None:
        if camera.sdd_mm is None:
            raise InputError("camera", "pixel_spacing_mm is unknown; pass depth_range_mm")
        f_lo, f_hi = opt.default_depth_range_sdd
        depth_range_mm = (f_lo * camera.sdd_mm, f_hi * camera.sdd_mm)
    lo, hi = (float(v) for v in depth_range_mm)
    if not (0.0 < lo < hi):
        raise InputError("depth_range_mm", f"needs 0 < min < max, got {depth_range_mm}")
    return lm, cl, cp, lo, hi


def _search(
    camera: Camera,
    lm: np.ndarray,
    cl: np.ndarray,
    cp_t: torch.Tensor,
    kin: CMKinematics,
    opt: CenterlineInitConfig,
    depth_range_mm: tuple[float, float],
    image: np.ndarray | None,
    device: torch.device | str | None,
) -> _Search:
    """The view's search: the depth range clipped to where the model chord spans the landmarks, and
    the shaft's depth cue where ``image`` gives one; RegistrationFailure where no depth can."""
    dt = torch.float64
    lo, hi = depth_range_mm
    landmarks_cm = kin.landmarks_cm(cp_t)  # (2, 3)
    centerline_cm = kin.centerline_cm(cp_t, n_points=opt.n_model_points)  # (M, 3)
    length = float((landmarks_cm[1] - landmarks_cm[0]).norm())
    K = torch.as_tensor(camera.K, dtype=dt, device=device)
    rays = (
        torch.cat([torch.as_tensor(lm, dtype=dt, device=device), K.new_ones(2, 1)], 1) @ torch.linalg.inv(K).T
    )  # (2, 3), z = 1
    ray_a, ray_b = rays[0], rays[1]
    sin_ab = float(torch.linalg.cross(ray_a, normalize(ray_b)).norm())
    if sin_ab < 1e-12:
        raise RegistrationFailure("landmarks A and B coincide: the CM chord is along the viewing ray")
    d_max = length / sin_ab
    if d_max < lo:
        raise RegistrationFailure(
            f"landmarks are too far apart for the CM: a {length:.1f} mm chord spans them only at depths "
            f"up to {d_max:.0f} mm, below the search range {lo:.0f}-{hi:.0f} mm"
        )
    hi = min(hi, d_max * (1.0 - 1e-9))
    extracted = torch.as_tensor(resample_polyline(cl, opt.n_extracted_points), dtype=dt, device=device)
    cue = None
    if image is not None and opt.shaft_length_mm > 0:
        cue = measure_shaft_depth(
            camera, image, cl, config=kin.config, shaft_length_mm=opt.shaft_length_mm,
            depth_range_mm=(lo, hi),
            sigma_fraction=opt.depth_cue_sigma_fraction,
        )  # fmt: skip
        if cue is None:
            logger.info("centreline init: the shaft's width could not be measured; no depth cue")
    return _Search(K, ray_a, ray_b, landmarks_cm, centerline_cm, extracted, opt.trim_fraction, cue, lo, hi)


def _grid_search(
    search: _Search, opt: CenterlineInitConfig, seed: int, device: torch.device | str | None
) -> _Grid:
    """Stratified uniform samples, one per cell and both branches, and their costs."""
    dt = torch.float64
    n_d, n_t = grid_shape(opt.n_samples, opt.theta_cells_per_depth_cell)
    rng = np.random.default_rng(seed)
    jitter = torch.as_tensor(rng.random((2, n_d, n_t)), dtype=dt, device=device)
    step_d, step_t = (search.hi - search.lo) / n_d, 360.0 / n_t
    idx_d = torch.arange(n_d, dtype=dt, device=device)[:, None]
    idx_t = torch.arange(n_t, dtype=dt, device=device)[None, :]
    depth = search.lo + (idx_d + jitter[0]) * step_d  # (D, T)
    theta = (idx_t + jitter[1]) * step_t
    depth_b, theta_b = depth.expand(2, n_d, n_t), theta.expand(2, n_d, n_t)
    branch_b = torch.arange(2, device=device)[:, None, None].expand(2, n_d, n_t)
    cost = search.evaluate(depth_b.reshape(-1), theta_b.reshape(-1), branch_b.reshape(-1)).reshape(
        2, n_d, n_t
    )
    return _Grid(depth, theta, depth_b, theta_b, branch_b, cost, step_d, step_t)


def _compass_search(
    search: _Search, grid: _Grid, opt: CenterlineInitConfig, device: torch.device | str | None
) -> tuple[np.ndarray, np.ndarray, tuple[float, float, int], float, int]:
    """The best ``n_starts`` grid local minima refined by a batched compass search on the 3 × 3
    stencil (move to the best neighbour, halve the step on failure): ``(camera_from_cm (S, 4, 4)
    lowest cost first, their costs (S,), the best's (depth, θ, branch), its cost, feasible
    evaluations)``."""
    minima = grid_local_minima(grid.cost)
    cand = torch.nonzero(minima.reshape(-1)).squeeze(-1)
    order = torch.argsort(grid.cost.reshape(-1)[cand])[: opt.n_starts]
    starts = cand[order]
    d_cur = grid.depth_b.reshape(-1)[starts].clone()
    t_cur = grid.theta_b.reshape(-1)[starts].clone()
    b_cur = grid.branch_b.reshape(-1)[starts]
    c_cur = grid.cost.reshape(-1)[starts].clone()
    offs = torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64, device=device)
    od, ot = (g.reshape(-1) for g in torch.meshgrid(offs, offs, indexing="ij"))
    sd = torch.full_like(d_cur, grid.step_d)
    st = torch.full_like(t_cur, grid.step_t)
    rows = torch.arange(d_cur.shape[0], device=device)
    n_evaluated = 0
    for _ in range(opt.refine_iterations):
        dd = (d_cur[:, None] + sd[:, None] * od).clamp(search.lo, search.hi)  # (S, 9)
        tt = torch.remainder(t_cur[:, None] + st[:, None] * ot, 360.0)
        c = search.evaluate(dd.reshape(-1), tt.reshape(-1), b_cur[:, None].expand_as(dd).reshape(-1))
        c = c.reshape(dd.shape)
        n_evaluated += int(torch.isfinite(c).sum())
        j = torch.argmin(c, dim=1)
        better = c[rows, j] < c_cur
        d_cur = torch.where(better, dd[rows, j], d_cur)
        t_cur = torch.where(better, tt[rows, j], t_cur)
        c_cur = torch.where(better, c[rows, j], c_cur)
        sd = torch.where(better, sd, 0.5 * sd)
        st = torch.where(better, st, 0.5 * st)
    order_c = torch.argsort(c_cur)
    poses = search.poses(d_cur[order_c], t_cur[order_c], b_cur[order_c])[0].cpu().numpy()
    k = int(torch.argmin(c_cur))
    best = (float(d_cur[k]), float(t_cur[k]), int(b_cur[k]))
    return poses, c_cur[order_c].cpu().numpy(), best, float(c_cur[k]), n_evaluated


def _joint_polish(
    search: _Search,
    starts: np.ndarray,
    camera: Camera,
    lm: np.ndarray,
    cp_t: torch.Tensor,
    kin: CMKinematics,
    opt: CenterlineInitConfig,
    device: torch.device | str | None,
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """The refined minima ``starts`` (S, 4, 4) polished by the 11-DoF fit, lowest cost first:
    ``(camera_from_cm (S, 4, 4), centreline costs (S,), (best pose, its control points (5,)))``."""
    dt = torch.float64
    K, extracted = search.K, search.extracted
    fits = [
        joint_fit(
            K, T0, cp_t, torch.as_tensor(lm, dtype=dt, device=device), extracted, kin,
            depth_range_mm=(search.lo, search.hi),
            landmark_sigma_px=opt.joint_fit.landmark_sigma_for(camera.pixel_spacing_mm),
            n_model_points=opt.n_model_points, config=opt.joint_fit, depth_cue=search.cue,
        )
        for T0 in torch.as_tensor(starts, dtype=dt, device=device)
    ]  # fmt: skip
    order_f = np.argsort([f[2] for f in fits], kind="stable")
    T_fit = torch.as_tensor(np.stack([fits[i][0] for i in order_f]), dtype=dt, device=device)
    cp_fit = [fits[i][1] for i in order_f]
    alternatives = T_fit.cpu().numpy()
    cl_fit = kin.centerline_cm(
        torch.as_tensor(np.stack(cp_fit), dtype=dt, device=device), n_points=opt.n_model_points
    )  # (S, M, 3)
    costs = np.array(
        [
            float(
                centerline_cost(K, T_fit[j : j + 1], cl_fit[j], extracted, trim_fraction=search.trim_fraction)
            )
            for j in range(len(cp_fit))
        ]
    )
    return alternatives, costs, (alternatives[0], np.asarray(cp_fit[0], dtype=np.float64))


@dataclass(frozen=True)
class _Optimum:
    """The search's outcome: the grid and its best cost, the best (depth, θ, branch) and its cost, the
    refined minima (S, 4, 4) and their costs (None without refinement), the joint fit's (pose,
    control points) (None without it) and the feasible evaluations."""

    grid: _Grid
    grid_cost: float
    best: tuple[float, float, int]
    best_cost: float
    alternatives: np.ndarray | None
    alternative_costs: np.ndarray | None
    joint: tuple[np.ndarray, np.ndarray] | None
    n_evaluated: int


def _optimise(
    search: _Search,
    camera: Camera,
    lm: np.ndarray,
    cp_t: torch.Tensor,
    kin: CMKinematics,
    opt: CenterlineInitConfig,
    seed: int,
    device: torch.device | str | None,
) -> _Optimum:
    """The grid search, then (as configured) the compass search and the joint fit of its minima;
    RegistrationFailure where no grid candidate is feasible."""
    grid = _grid_search(search, opt, seed, device)
    n_evaluated = int(torch.isfinite(grid.cost).sum())
    if n_evaluated == 0:
        raise RegistrationFailure("no feasible (depth, theta) candidate in the search range")
    best, grid_best = grid.best()
    best_cost = grid_best
    alternatives: np.ndarray | None = None
    alternative_costs: np.ndarray | None = None
    joint: tuple[np.ndarray, np.ndarray] | None = None  # (camera_from_cm, control points) of the fit
    if opt.refine:
        alternatives, alternative_costs, refined, refined_cost, n_refine = _compass_search(
            search, grid, opt, device
        )
        n_evaluated += n_refine
        if refined_cost < best_cost:
            best, best_cost = refined, refined_cost
        if opt.joint_refine:
            alternatives, alternative_costs, joint = _joint_polish(
                search, alternatives, camera, lm, cp_t, kin, opt, device
            )
            best_cost = float(alternative_costs[0])
    return _Optimum(grid, grid_best, best, best_cost, alternatives, alternative_costs, joint, n_evaluated)


def _returned_pose(
    search: _Search,
    best: tuple[float, float, int],
    joint: tuple[np.ndarray, np.ndarray] | None,
    cp: np.ndarray,
    device: torch.device | str | None,
) -> tuple[np.ndarray, np.ndarray, tuple[float, float, int]]:
    """The pose returned, its control points and its (depth, θ, branch): the joint fit's best where
    there is one, else the best (depth, θ, branch) with the given control points."""
    if joint is None:
        one = torch.ones(1, dtype=torch.float64, device=device)
        branch = torch.tensor([best[2]], device=device)
        return search.poses(one * best[0], one * best[1], branch)[0][0].cpu().numpy(), cp.copy(), best
    T_best, cp_best = joint
    return (
        T_best,
        cp_best,
        (float(T_best[2, 3]), roll_of_pose(T_best, search.ray_a, search.landmarks_cm), best[2]),
    )


def centerline_initialize(
    camera: Camera,
    landmarks_px: np.ndarray | torch.Tensor,
    centerline_px: np.ndarray | torch.Tensor,
    control_points_deg: np.ndarray | torch.Tensor,
    *,
    config: CenterlineInitConfig | None = None,
    cm_config: CMConfig | None = None,
    depth_range_mm: tuple[float, float] | None = None,
    seed: int = 0,
    image: np.ndarray | None = None,
    device: torch.device | str | None = None,
) -> CenterlineInitResult:
    """Initial ``camera_from_cm`` from two landmarks, a 2D centreline and the FBG control points.

    Args:
        camera: the view (only ``K`` is used; the pose is returned in the camera frame).
        landmarks_px: (2, 2) detected A and B, (u, v) pixels.
        centerline_px: (P, 2) extracted centreline, ordered A → B, pixels (P ≥ 2).
        control_points_deg: (5,) FBG control points, degrees.
        config: search settings (default :class:`CenterlineInitConfig`).
        cm_config: CM geometry (paper defaults).
        depth_range_mm: (min, max) camera-frame z of A to search; default
            ``config.default_depth_range_sdd`` × the source-to-detector distance (needs
            ``camera.pixel_spacing_mm``).
        seed: seed of the sample jitter inside the grid cells.
        image: the X-ray (−log, this camera's pixels). With it and a shaft (``shaft_length_mm`` > 0)
            the shaft's apparent width gives its depth (:func:`measure_shaft_depth`), a term
            ``½((z_pred − z_meas)/σ)²`` of every candidate's cost and a residual of the joint fit:
            one view's centreline alone does not tell depth from tilt.
        device: torch device of the evaluation (float64 throughout).

    Returns:
        :class:`CenterlineInitResult`.

    Raises:
        InputError: malformed inputs.
        RegistrationFailure: no depth in range lets the model chord span the two landmarks, the
            landmarks coincide, or no candidate is feasible.
    """
    t0 = time.perf_counter()
    opt = config or CenterlineInitConfig()
    cfg = cm_config or CMConfig()
    lm, cl, cp, lo, hi = _checked_inputs(
        camera, landmarks_px, centerline_px, control_points_deg, opt, cfg, depth_range_mm
    )
    dt = torch.float64
    kin = CMKinematics(cfg)
    cp_t = torch.as_tensor(cp, dtype=dt, device=device)
    search = _search(camera, lm, cl, cp_t, kin, opt, (lo, hi), image, device)
    out = _optimise(search, camera, lm, cp_t, kin, opt, seed, device)
    grid, grid_best, best_cost, n_evaluated = out.grid, out.grid_cost, out.best_cost, out.n_evaluated
    T_best, cp_best, best = _returned_pose(search, out.best, out.joint, cp, device)
    logger.debug(
        "centreline init: d_A %.1f mm, theta %.1f deg, %s, cost %.3f px (grid %.3f), %d evaluations, %.2f s",
        best[0], best[1], BRANCHES[best[2]], best_cost, grid_best, n_evaluated, time.perf_counter() - t0,
    )  # fmt: skip
    keep = opt.return_candidates
    return CenterlineInitResult(
        camera_from_cm=T_best,
        depth_mm=best[0],
        theta_deg=best[1] % 360.0,
        branch=BRANCHES[best[2]],
        cost_px=best_cost,
        grid_cost_px=grid_best,
        n_evaluated=n_evaluated,
        depth_range_mm=(search.lo, search.hi),
        candidate_costs=grid.cost.permute(1, 2, 0).cpu().numpy() if keep else None,
        candidate_depth_mm=grid.depth.cpu().numpy() if keep else None,
        candidate_theta_deg=grid.theta.cpu().numpy() if keep else None,
        alternatives=out.alternatives,
        alternative_costs_px=out.alternative_costs,
        control_points_deg=cp_best,
        shaft_depth_mm=None if search.cue is None else search.cue.depth_mm,
    )


def depth_range_about(
    camera: Camera, point_world: np.ndarray, *, window_mm: float = ANATOMY_DEPTH_WINDOW_MM
) -> tuple[float, float]:
    """``depth_range_mm`` for :func:`centerline_initialize`: the camera-frame depth of an anatomical
    anchor (e.g. the registered femoral head) ± ``window_mm`` (clipped to start 1 mm past the source).
    """
    z = float(camera.to_camera(np.asarray(point_world, dtype=np.float64).reshape(1, 3))[0, 2])
    if z + window_mm <= 1.0:
        raise InputError("point_world", f"the anchor lies behind the source (depth {z:.0f} mm)")
    return max(z - window_mm, 1.0), z + window_mm
