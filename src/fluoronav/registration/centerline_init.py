"""Centreline-based initialisation of the CM pose (Gao et al. 2022, sec. II-B; FACTS.md).

Two detected 2D landmarks (A = CM base origin, B = centre of the distal plane of the last notch) fix 4
of the 6 DoF of ``camera_from_cm``. The other two are searched:

- ``depth_mm`` (d_A): the camera-frame z of A (the "depth" of :meth:`Camera.backproject`), so
  ``A3D = d_A · K⁻¹ [u_A, v_A, 1]ᵀ``.
- ``theta_deg`` (θ): the roll of the CM about the chord A→B.

For a (d_A, θ), B3D is the point of B's ray at the model chord length ``L = |AB|`` (from the CM
kinematics with the FBG control points) from A3D. ``|t·r_B − A3D| = L`` is a quadratic in ``t`` with
up to two roots, the ``near`` and ``far`` branches; both are searched (a discrete third variable).
The rotation maps the chord direction of the model onto ``(B3D − A3D)/L`` and θ turns the CM's x axis
(the normal of its bending plane) about the chord, starting from ``θ = 0`` where that axis is the
unit vector along ``r_A × (B3D − A3D)`` (perpendicular to A's ray and to the chord).

A real root exists iff the distance of A3D from B's ray is at most L; that distance is linear in d_A,
so the feasible depths are ``(0, d_max]`` with ``d_max = L / |K⁻¹[u_A, v_A, 1] × r_B|`` in closed
form. The search range (``depth_range_mm``, by default 0.3–0.7 × the source-to-detector distance) is
clipped to the feasible interval before sampling; an empty intersection raises
:class:`~fluoronav.errors.RegistrationFailure`. Candidates that are still infeasible (the near
root behind the source, the model behind the source) get cost ``inf``.

Search: ``n_samples`` (d_A, θ) samples, one uniform random sample (seeded) in each cell of a
stratified ``n_depth × n_theta`` grid (≈ 25 × 40 for 1,000), each evaluated on both branches, all
candidates in one batched evaluation. Optional refinement: the best grid local minima (up to
``n_starts``) are refined together (batched) by a compass search in (d_A, θ) on their branch: the
3 × 3 stencil of ± one step around each start, moving to its best point or halving the step.

Joint refinement (``joint_refine``, default on): the grid pins A and B exactly on the detected
landmarks' rays and the chord at the FBG shape's length, so 3 px of landmark noise or 0.5° of FBG
error moves the best (d_A, θ) far along the depth valley. Each refined minimum is therefore polished
by a robust least-squares fit of all 11 DoF (pose and control points) to the centreline (point-to-
polyline distances both ways, σ ``centerline_sigma_px``) with the landmarks and control points as
Gaussian priors (σ ``landmark_sigma_px``, ``control_point_sigma_deg``), A's depth kept inside the
search range. Synthetic AP scenes (``evaluate_centerline_init(n=20, seed=7)``, landmark noise
U(±3) px, FBG U(±0.5)°): depth error 42.5 → 24.4 mm mean, and 36.9 → 21.5 mm with the depth searched
within ±100 mm of the isocentre (``depth_window_mm=100``).

Cost (pixels): the model centreline (``CMKinematics.centerline_cm``) is projected with each candidate
pose; the cost is the mean of two directed terms, model points → extracted polyline and extracted
points (resampled by arc length) → projected model polyline, each the *trimmed* mean (the largest
``trim_fraction`` of the point-to-segment distances dropped) so spurs and gaps of a centreline
extracted from a segmentation do not dominate. Both endpoints coincide with the landmarks by
construction, so the symmetric term penalises a projected model that is too short or too long.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch.nn import functional as nnf

from fluoronav.detection.centerline import resample_polyline
from fluoronav.errors import InputError, RegistrationFailure
from fluoronav.geometry.camera import Camera, project_points
from fluoronav.geometry.rotations import matrix_to_quat
from fluoronav.geometry.transforms import make_transform
from fluoronav.manipulator import CMConfig, CMKinematics

__all__ = [
    "CenterlineInitResult",
    "CenterlineScene",
    "ShaftDepthCue",
    "centerline_cost",
    "centerline_initialize",
    "depth_range_about",
    "evaluate_centerline_init",
    "measure_shaft_depth",
    "multiview_start_poses",
    "polyline_distance_cost",
    "poses_from_depth_theta",
    "roll_about_axis_deg",
    "synthetic_centerline_scene",
    "turn_about_chord",
]

logger = logging.getLogger(__name__)

_BRANCHES = ("near", "far")


@dataclass(frozen=True)
class CenterlineInitResult:
    """Result of :func:`centerline_initialize`.

    Attributes:
        camera_from_cm: (4, 4) float64 pose of the CM base frame in the camera (source) frame, mm.
        depth_mm: d_A, camera-frame z of landmark A.
        theta_deg: roll θ about the chord A→B in [0, 360) (see the module docstring for θ = 0).
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


# ----- geometry ---------------------------------------------------------------------------------
def _normalize(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-300)


def _cm_basis(chord_cm: torch.Tensor) -> torch.Tensor:
    """(3,) chord A→B in the CM frame → (3, 3) orthonormal columns [chord, x', chord × x']."""
    u = _normalize(chord_cm)
    x = torch.tensor([1.0, 0.0, 0.0], dtype=u.dtype, device=u.device)
    if float(torch.linalg.cross(u, x).norm()) < 1e-6:  # a chord along x cannot happen for a planar CM
        x = torch.tensor([0.0, 1.0, 0.0], dtype=u.dtype, device=u.device)
    n = _normalize(x - (x @ u) * u)
    return torch.stack([u, n, torch.linalg.cross(u, n)], dim=-1)


def poses_from_depth_theta(
    ray_a: torch.Tensor,
    ray_b: torch.Tensor,
    landmarks_cm: torch.Tensor,
    depth_mm: torch.Tensor,
    theta_deg: torch.Tensor,
    branch: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Candidate poses from (d_A, θ, branch), batched.

    Args:
        ray_a: (3,) ``K⁻¹ [u_A, v_A, 1]`` (camera frame, z = 1).
        ray_b: (3,) ``K⁻¹ [u_B, v_B, 1]`` (any positive scale).
        landmarks_cm: (2, 3) model landmarks A, B in the CM frame, mm.
        depth_mm: (N,) camera-frame z of A.
        theta_deg: (N,) roll about the chord.
        branch: (N,) 0 = near root, 1 = far root for B on its ray.

    Returns:
        ``camera_from_cm`` (N, 4, 4) and ``feasible`` (N,) bool (real root in front of the source).
        Infeasible rows hold a valid rigid transform built from the clamped root; ignore them.
    """
    a_cm, b_cm = landmarks_cm[0], landmarks_cm[1]
    length = (b_cm - a_cm).norm()
    rb = _normalize(ray_b)
    A = depth_mm.unsqueeze(-1) * ray_a  # (N, 3)
    proj = A @ rb  # (N,)
    disc = length**2 - ((A * A).sum(-1) - proj**2)
    sign = torch.where(branch > 0, 1.0, -1.0).to(A.dtype)
    t = proj + sign * disc.clamp_min(0.0).sqrt()
    feasible = (disc >= 0.0) & (t > 0.0)
    B = t.unsqueeze(-1) * rb
    u = _normalize(B - A)
    ref = torch.linalg.cross(ray_a.expand_as(u), u)
    ref = _normalize(ref)
    th = torch.deg2rad(theta_deg).unsqueeze(-1)
    e2 = torch.cos(th) * ref + torch.sin(th) * torch.linalg.cross(u, ref)
    cam_basis = torch.stack([u, e2, torch.linalg.cross(u, e2)], dim=-1)  # (N, 3, 3)
    R = cam_basis @ _cm_basis(b_cm - a_cm).T
    trans = A - (R @ a_cm.unsqueeze(-1)).squeeze(-1)
    return make_transform(R, trans), feasible


# ----- cost -------------------------------------------------------------------------------------
def _trimmed_mean(d: torch.Tensor, trim_fraction: float) -> torch.Tensor:
    """Mean over the last dim after dropping the largest ``trim_fraction`` of the values."""
    n = d.shape[-1]
    keep = max(1, n - math.floor(trim_fraction * n))
    if keep == n:
        return d.mean(-1)
    return torch.topk(d, keep, dim=-1, largest=False).values.mean(-1)


def _point_to_fixed_polyline(q: torch.Tensor, poly: torch.Tensor) -> torch.Tensor:
    """Distance of points q (N, M, 2) to one polyline (S+1, 2) → (N, M)."""
    p0, dvec = poly[:-1], poly[1:] - poly[:-1]
    dd = (dvec * dvec).sum(-1).clamp_min(1e-12)  # (S,)
    qd = q @ dvec.T  # (N, M, S)
    w = qd - (p0 * dvec).sum(-1)
    qq = (q * q).sum(-1, keepdim=True)
    d2 = qq - 2.0 * (q @ p0.T) + (p0 * p0).sum(-1)
    t = (w / dd).clamp(0.0, 1.0)
    return (d2 - 2.0 * t * w + t * t * dd).clamp_min(0.0).min(-1).values.sqrt()


def _fixed_points_to_polylines(q: torch.Tensor, poly: torch.Tensor) -> torch.Tensor:
    """Distance of fixed points q (Q, 2) to each polyline (N, S+1, 2) → (N, Q)."""
    p0, dvec = poly[:, :-1], poly[:, 1:] - poly[:, :-1]  # (N, S, 2)
    dd = (dvec * dvec).sum(-1).clamp_min(1e-12)  # (N, S)
    w = torch.einsum("qc,nsc->nqs", q, dvec) - (p0 * dvec).sum(-1).unsqueeze(1)
    d2 = (q * q).sum(-1)[None, :, None] - 2.0 * torch.einsum("qc,nsc->nqs", q, p0)
    d2 = d2 + (p0 * p0).sum(-1).unsqueeze(1)
    t = (w / dd.unsqueeze(1)).clamp(0.0, 1.0)
    return (d2 - 2.0 * t * w + t * t * dd.unsqueeze(1)).clamp_min(0.0).min(-1).values.sqrt()


def polyline_distance_cost(
    projected_px: torch.Tensor, extracted_px: torch.Tensor, *, trim_fraction: float = 0.1
) -> torch.Tensor:
    """Symmetric trimmed mean point-to-polyline distance between 2D curves, batched.

    Args:
        projected_px: (N, M, 2) projected model centrelines (ordered polylines), pixels.
        extracted_px: (Q, 2) the extracted centreline (ordered polyline), pixels.
        trim_fraction: fraction of the largest distances dropped in each direction.

    Returns:
        (N,) cost in pixels: ½ (model → extracted + extracted → model).
    """
    # squared distances are expanded into matrix products (no (N, M, S, 2) temporaries); centring the
    # coordinates keeps their cancellation error near 1e-6 px instead of 1e-5 px at image scale
    centre = extracted_px.mean(0)
    projected_px, extracted_px = projected_px - centre, extracted_px - centre
    d_model = _point_to_fixed_polyline(projected_px, extracted_px)
    d_ext = _fixed_points_to_polylines(extracted_px, projected_px)
    return 0.5 * (_trimmed_mean(d_model, trim_fraction) + _trimmed_mean(d_ext, trim_fraction))


def centerline_cost(
    K: torch.Tensor,
    camera_from_cm: torch.Tensor,
    centerline_cm: torch.Tensor,
    extracted_px: torch.Tensor,
    *,
    trim_fraction: float = 0.1,
    chunk_size: int = 512,
) -> torch.Tensor:
    """Centreline cost of candidate poses (pixels).

    Args:
        K: (3, 3) intrinsics.
        camera_from_cm: (N, 4, 4) candidate poses.
        centerline_cm: (M, 3) model centreline in the CM frame, mm.
        extracted_px: (Q, 2) extracted centreline, pixels.
        trim_fraction: see :func:`polyline_distance_cost`.
        chunk_size: candidates per vectorised block (bounds memory at N·M·Q doubles per block).

    Returns:
        (N,) costs; ``inf`` where a model point is not in front of the source.
    """
    out = []
    for start in range(0, camera_from_cm.shape[0], chunk_size):
        T = camera_from_cm[start : start + chunk_size]
        z = centerline_cm @ T[:, 2, :3].T + T[:, None, 2, 3].T  # (M, n) camera-frame depth
        uv = project_points(K, T, centerline_cm)  # (n, M, 2)
        cost = polyline_distance_cost(uv, extracted_px, trim_fraction=trim_fraction)
        out.append(torch.where((z > 1.0).all(0), cost, torch.full_like(cost, math.inf)))
    return torch.cat(out) if out else K.new_zeros(0)


# ----- search -----------------------------------------------------------------------------------
def _grid_shape(n_samples: int) -> tuple[int, int]:
    # 1.6 θ cells per depth cell: 25 × 40 for 1,000 (θ is the better determined of the two)
    n_theta = max(4, round(math.sqrt(1.6 * n_samples)))
    n_depth = max(2, round(n_samples / n_theta))
    return n_depth, n_theta


def _local_minima(cost: torch.Tensor) -> torch.Tensor:
    """(B, D, T) grid costs, θ cyclic → bool mask of finite 8-neighbourhood minima (ties kept)."""
    c = torch.where(torch.isfinite(cost), cost, torch.full_like(cost, 1e300))
    padded = torch.cat([c[..., -1:], c, c[..., :1]], dim=-1)  # wrap θ
    padded = nnf.pad(padded.unsqueeze(1), (0, 0, 1, 1), value=1e300)  # depth edges
    neigh_min = -nnf.max_pool2d(-padded, kernel_size=3, stride=1).squeeze(1)
    return (c <= neigh_min) & torch.isfinite(cost)


def _as_input(x: object, shape: tuple[int, ...] | None, name: str) -> np.ndarray:
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(name, "is not numeric") from None
    if shape is not None and arr.shape != shape:
        raise InputError(name, f"must have shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(name, "has non-finite values")
    return arr


def centerline_initialize(
    camera: Camera,
    landmarks_px: np.ndarray | torch.Tensor,
    centerline_px: np.ndarray | torch.Tensor,
    control_points_deg: np.ndarray | torch.Tensor,
    *,
    config: CMConfig | None = None,
    depth_range_mm: tuple[float, float] | None = None,
    n_samples: int = 1000,
    refine: bool = True,
    seed: int = 0,
    n_model_points: int = 48,
    n_extracted_points: int = 64,
    trim_fraction: float = 0.1,
    n_starts: int = 4,
    refine_iterations: int = 30,
    joint_refine: bool = True,
    landmark_sigma_px: float | None = None,
    control_point_sigma_deg: float = 0.3,
    centerline_sigma_px: float = 1.0,
    return_candidates: bool = False,
    image: np.ndarray | None = None,
    shaft_length_mm: float = 50.0,
    depth_cue_sigma_fraction: float = 0.02,
    device: torch.device | str | None = None,
) -> CenterlineInitResult:
    """Initial ``camera_from_cm`` from two landmarks, a 2D centreline and the FBG control points.

    Args:
        camera: the view (only ``K`` is used; the pose is returned in the camera frame).
        landmarks_px: (2, 2) detected A and B, (u, v) pixels.
        centerline_px: (P, 2) extracted centreline, ordered A → B, pixels (P ≥ 2).
        control_points_deg: (5,) FBG control points, degrees.
        config: CM geometry (paper defaults).
        depth_range_mm: (min, max) camera-frame z of A to search; default 0.3–0.7 × the
            source-to-detector distance (needs ``camera.pixel_spacing_mm``).
        n_samples: number of (d_A, θ) samples (stratified uniform); each is tried on both branches.
        refine: refine the best grid local minima by a batched compass search.
        seed: seed of the sample jitter inside the grid cells.
        n_model_points: points on the model centreline A → B.
        n_extracted_points: the extracted centreline is resampled to this many points by arc length.
        trim_fraction: robust cost, fraction of the largest distances dropped (each direction).
        n_starts: number of grid local minima refined.
        refine_iterations: compass-search iterations (3 × 3 stencil, step halved on failure).
        joint_refine: polish the refined minima by the 11-DoF least-squares fit (module docstring);
            needs ``refine``.
        landmark_sigma_px: landmark prior σ of the joint fit, pixels of this image; default 1 mm
            at the detector (the shipped detector's median error) or 3 px without a pixel spacing.
        control_point_sigma_deg: control-point prior σ of the joint fit (FBG U(±0.5°): σ 0.29°).
        centerline_sigma_px: σ of a centreline point's distance in the joint fit, pixels.
        return_candidates: keep the grid samples and costs in the result.
        image: the X-ray (−log, this camera's pixels). With it and a shaft (``shaft_length_mm`` > 0)
            the shaft's apparent width gives its depth (:func:`measure_shaft_depth`), a term
            ``½((z_pred − z_meas)/σ)²`` of every candidate's cost and a residual of the joint fit:
            one view's centreline alone does not tell depth from tilt (module docstring).
        shaft_length_mm: length of the rigid shaft behind A (the simulator's and registration's 50).
        depth_cue_sigma_fraction: σ of the shaft depth as a fraction of it.
        device: torch device of the evaluation (float64 throughout).

    Returns:
        :class:`CenterlineInitResult`.

    Raises:
        InputError: malformed inputs.
        RegistrationFailure: no depth in range lets the model chord span the two landmarks, the
            landmarks coincide, or no candidate is feasible.
    """
    t0 = time.perf_counter()
    lm = _as_input(landmarks_px, (2, 2), "landmarks_px")
    cl = _as_input(centerline_px, None, "centerline_px")
    if cl.ndim != 2 or cl.shape[1] != 2 or cl.shape[0] < 2:
        raise InputError("centerline_px", f"must have shape (P >= 2, 2), got {cl.shape}")
    cfg = config or CMConfig()
    cp = _as_input(control_points_deg, (cfg.n_control_points,), "control_points_deg")
    if n_samples < 8:
        raise InputError("n_samples", f"must be at least 8, got {n_samples}")
    if depth_range_mm is None:
        if camera.sdd_mm is None:
            raise InputError("camera", "pixel_spacing_mm is unknown; pass depth_range_mm")
        depth_range_mm = (0.3 * camera.sdd_mm, 0.7 * camera.sdd_mm)
    lo, hi = (float(v) for v in depth_range_mm)
    if not (0.0 < lo < hi):
        raise InputError("depth_range_mm", f"needs 0 < min < max, got {depth_range_mm}")

    dt = torch.float64
    kin = CMKinematics(cfg)
    cp_t = torch.as_tensor(cp, dtype=dt, device=device)
    landmarks_cm = kin.landmarks_cm(cp_t)  # (2, 3)
    centerline_cm = kin.centerline_cm(cp_t, n_points=n_model_points)  # (M, 3)
    length = float((landmarks_cm[1] - landmarks_cm[0]).norm())
    K = torch.as_tensor(camera.K, dtype=dt, device=device)
    rays = (
        torch.cat([torch.as_tensor(lm, dtype=dt, device=device), K.new_ones(2, 1)], 1) @ torch.linalg.inv(K).T
    )  # (2, 3), z = 1
    ray_a, ray_b = rays[0], rays[1]
    sin_ab = float(torch.linalg.cross(ray_a, _normalize(ray_b)).norm())
    if sin_ab < 1e-12:
        raise RegistrationFailure("landmarks A and B coincide: the CM chord is along the viewing ray")
    d_max = length / sin_ab
    if d_max < lo:
        raise RegistrationFailure(
            f"landmarks are too far apart for the CM: a {length:.1f} mm chord spans them only at depths "
            f"up to {d_max:.0f} mm, below the search range {lo:.0f}-{hi:.0f} mm"
        )
    hi = min(hi, d_max * (1.0 - 1e-9))
    extracted = torch.as_tensor(resample_polyline(cl, n_extracted_points), dtype=dt, device=device)
    cue = None
    if image is not None and shaft_length_mm > 0:
        cue = measure_shaft_depth(
            camera, image, cl, config=cfg, shaft_length_mm=shaft_length_mm, depth_range_mm=(lo, hi),
            sigma_fraction=depth_cue_sigma_fraction,
        )  # fmt: skip
        if cue is None:
            logger.info("centreline init: the shaft's width could not be measured; no depth cue")

    def evaluate(depth: torch.Tensor, theta: torch.Tensor, branch: torch.Tensor) -> torch.Tensor:
        T, ok = poses_from_depth_theta(ray_a, ray_b, landmarks_cm, depth, theta, branch)
        cost = torch.full_like(depth, math.inf)
        if bool(ok.any()):
            cost[ok] = centerline_cost(K, T[ok], centerline_cm, extracted, trim_fraction=trim_fraction)
            if cue is not None:
                cost[ok] = cost[ok] + 0.5 * _shaft_depth_residual(cue, K, T[ok]) ** 2
        return cost

    # stratified uniform samples: one per cell, both branches
    n_d, n_t = _grid_shape(n_samples)
    rng = np.random.default_rng(seed)
    jitter = torch.as_tensor(rng.random((2, n_d, n_t)), dtype=dt, device=device)
    step_d, step_t = (hi - lo) / n_d, 360.0 / n_t
    idx_d = torch.arange(n_d, dtype=dt, device=device)[:, None]
    idx_t = torch.arange(n_t, dtype=dt, device=device)[None, :]
    depth = lo + (idx_d + jitter[0]) * step_d  # (D, T)
    theta = (idx_t + jitter[1]) * step_t
    depth_b, theta_b = depth.expand(2, n_d, n_t), theta.expand(2, n_d, n_t)
    branch_b = torch.arange(2, device=device)[:, None, None].expand(2, n_d, n_t)
    grid_cost = evaluate(depth_b.reshape(-1), theta_b.reshape(-1), branch_b.reshape(-1)).reshape(2, n_d, n_t)
    n_evaluated = int(torch.isfinite(grid_cost).sum())
    if n_evaluated == 0:
        raise RegistrationFailure("no feasible (depth, theta) candidate in the search range")
    flat = int(torch.argmin(grid_cost))
    best = (float(depth_b.reshape(-1)[flat]), float(theta_b.reshape(-1)[flat]), flat // (n_d * n_t))
    grid_best = float(grid_cost.reshape(-1)[flat])
    best_cost = grid_best
    alternatives: np.ndarray | None = None
    alternative_costs: np.ndarray | None = None
    joint: tuple[np.ndarray, np.ndarray] | None = None  # (camera_from_cm, control points) of the fit

    if refine:
        minima = _local_minima(grid_cost)
        cand = torch.nonzero(minima.reshape(-1)).squeeze(-1)
        order = torch.argsort(grid_cost.reshape(-1)[cand])[:n_starts]
        starts = cand[order]
        d_cur = depth_b.reshape(-1)[starts].clone()
        t_cur = theta_b.reshape(-1)[starts].clone()
        b_cur = branch_b.reshape(-1)[starts]
        c_cur = grid_cost.reshape(-1)[starts].clone()
        # compass search on the 3 × 3 stencil: move to the best neighbour, halve the step on failure
        offs = torch.tensor([-1.0, 0.0, 1.0], dtype=dt, device=device)
        od, ot = (g.reshape(-1) for g in torch.meshgrid(offs, offs, indexing="ij"))
        sd = torch.full_like(d_cur, step_d)
        st = torch.full_like(t_cur, step_t)
        rows = torch.arange(d_cur.shape[0], device=device)
        for _ in range(refine_iterations):
            dd = (d_cur[:, None] + sd[:, None] * od).clamp(lo, hi)  # (S, 9)
            tt = torch.remainder(t_cur[:, None] + st[:, None] * ot, 360.0)
            c = evaluate(dd.reshape(-1), tt.reshape(-1), b_cur[:, None].expand_as(dd).reshape(-1))
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
        T_alt, _ = poses_from_depth_theta(
            ray_a, ray_b, landmarks_cm, d_cur[order_c], t_cur[order_c], b_cur[order_c]
        )
        alternatives = T_alt.cpu().numpy()
        alternative_costs = c_cur[order_c].cpu().numpy()
        k = int(torch.argmin(c_cur))
        if float(c_cur[k]) < best_cost:
            best = (float(d_cur[k]), float(t_cur[k]), int(b_cur[k]))
            best_cost = float(c_cur[k])
        if joint_refine:
            if landmark_sigma_px is None:
                spacing = camera.pixel_spacing_mm
                landmark_sigma_px = 1.0 / spacing if spacing else 3.0
            fits = [
                _joint_fit(
                    K, T0, cp_t, torch.as_tensor(lm, dtype=dt, device=device), extracted, kin,
                    depth_range_mm=(lo, hi), landmark_sigma_px=landmark_sigma_px,
                    control_point_sigma_deg=control_point_sigma_deg, centerline_sigma_px=centerline_sigma_px,
                    n_model_points=n_model_points, depth_cue=cue,
                )
                for T0 in torch.as_tensor(alternatives, dtype=dt, device=device)
            ]  # fmt: skip
            order_f = np.argsort([f[2] for f in fits], kind="stable")
            T_fit = torch.as_tensor(np.stack([fits[i][0] for i in order_f]), dtype=dt, device=device)
            cp_fit = [fits[i][1] for i in order_f]
            alternatives = T_fit.cpu().numpy()
            cl_fit = kin.centerline_cm(
                torch.as_tensor(np.stack(cp_fit), dtype=dt, device=device), n_points=n_model_points
            )  # (S, M, 3)
            trim = trim_fraction
            alternative_costs = np.array(
                [
                    float(centerline_cost(K, T_fit[j : j + 1], cl_fit[j], extracted, trim_fraction=trim))
                    for j in range(len(cp_fit))
                ]
            )
            joint = alternatives[0], np.asarray(cp_fit[0], dtype=np.float64)
            best_cost = float(alternative_costs[0])

    if joint is None:
        one = torch.ones(1, dtype=dt, device=device)
        T_best = (
            poses_from_depth_theta(
                ray_a,
                ray_b,
                landmarks_cm,
                one * best[0],
                one * best[1],
                torch.tensor([best[2]], device=device),
            )[0][0]
            .cpu()
            .numpy()
        )
        cp_best = cp.copy()
    else:
        T_best, cp_best = joint
        best = (float(T_best[2, 3]), _roll_of_pose(T_best, ray_a, landmarks_cm), best[2])
    logger.debug(
        "centreline init: d_A %.1f mm, theta %.1f deg, %s, cost %.3f px (grid %.3f), %d evaluations, %.2f s",
        best[0], best[1], _BRANCHES[best[2]], best_cost, grid_best, n_evaluated, time.perf_counter() - t0,
    )  # fmt: skip
    return CenterlineInitResult(
        camera_from_cm=T_best,
        depth_mm=best[0],
        theta_deg=best[1] % 360.0,
        branch=_BRANCHES[best[2]],
        cost_px=best_cost,
        grid_cost_px=grid_best,
        n_evaluated=n_evaluated,
        depth_range_mm=(lo, hi),
        candidate_costs=grid_cost.permute(1, 2, 0).cpu().numpy() if return_candidates else None,
        candidate_depth_mm=depth.cpu().numpy() if return_candidates else None,
        candidate_theta_deg=theta.cpu().numpy() if return_candidates else None,
        alternatives=alternatives,
        alternative_costs_px=alternative_costs,
        control_points_deg=cp_best,
        shaft_depth_mm=None if cue is None else cue.depth_mm,
    )


#: half-width of the depth search around an anatomical anchor (the femoral head): the CM works at
#: the hip, and one view's centreline cannot tell depth from tilt (equal-cost minima 175 mm apart)
ANATOMY_DEPTH_WINDOW_MM = 100.0


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


def _roll_of_pose(camera_from_cm: np.ndarray, ray_a: torch.Tensor, landmarks_cm: torch.Tensor) -> float:
    """θ (degrees, [0, 360)) of a pose in the convention of :func:`poses_from_depth_theta`."""
    R = torch.as_tensor(camera_from_cm[:3, :3], dtype=ray_a.dtype, device=ray_a.device)
    basis = R @ _cm_basis(landmarks_cm[1] - landmarks_cm[0])  # [u, e2, u × e2] in the camera
    u, e2 = basis[:, 0], basis[:, 1]
    ref = _normalize(torch.linalg.cross(ray_a, u))
    return math.degrees(math.atan2(float(e2 @ torch.linalg.cross(u, ref)), float(e2 @ ref))) % 360.0


@dataclass(frozen=True)
class ShaftDepthCue:
    """The CM shaft's distance from the source, measured from its apparent width
    (:func:`~fluoronav.detection.tube_profile.fit_tube_profile` along the centreline's continuation
    behind A, :func:`~fluoronav.detection.tube_profile.shaft_axis_px`).

    Attributes:
        depth_mm: measured camera-frame z of the sampled stretch of shaft (``focal / px_per_mm``).
        sigma_mm: its assumed error σ.
        distances_px: (Q,) image distances behind A of the profiles that were fitted.
        shaft_length_mm: length of the shaft behind A.
    """

    depth_mm: float
    sigma_mm: float
    distances_px: np.ndarray
    shaft_length_mm: float


def measure_shaft_depth(
    camera: Camera,
    image: np.ndarray,
    centerline_px: np.ndarray,
    *,
    config: CMConfig,
    shaft_length_mm: float,
    depth_range_mm: tuple[float, float],
    sigma_fraction: float = 0.02,
) -> ShaftDepthCue | None:
    """Measure :class:`ShaftDepthCue` in ``image`` (None when the shaft's profile does not fit).

    The shaft's scale is searched for depths 50 mm either side of ``depth_range_mm`` (the shaft
    reaches behind A). ``sigma_fraction``: σ as a fraction of the depth; on physics-simulated 768²
    phantom images the measured depth was −9 to +3 mm off at 450–520 mm (8 scenes)."""
    from fluoronav.detection.tube_profile import fit_tube_profile, shaft_axis_px

    cl = np.asarray(centerline_px, dtype=np.float64)
    ax = shaft_axis_px(cl)
    f = float(camera.K[0, 0])
    lo, hi = max(depth_range_mm[0] - 50.0, 1.0), depth_range_mm[1] + 50.0
    fit = fit_tube_profile(
        image,
        ax,
        outer_radius_mm=config.outer_radius_mm,
        inner_radius_mm=config.inner_radius_mm,
        px_per_mm_range=(f / hi, f / lo),
    )
    if fit is None:
        return None
    z = fit.depth_mm(f)
    return ShaftDepthCue(
        depth_mm=z,
        sigma_mm=sigma_fraction * z,
        distances_px=np.linalg.norm(ax - cl[0], axis=1),
        shaft_length_mm=float(shaft_length_mm),
    )


def _shaft_depth_residual(cue: ShaftDepthCue, K: torch.Tensor, camera_from_cm: torch.Tensor) -> torch.Tensor:
    """(N,) normalised residual ``(z_pred − z_meas)/σ`` of candidate poses (N, 4, 4): the predicted
    depth is the mean z of the shaft points (behind A along −z of the CM frame) whose images lie at the
    measured profiles' distances behind A."""
    A = camera_from_cm[:, :3, 3]
    axis = -camera_from_cm[:, :3, 2]
    eye = torch.eye(4, dtype=K.dtype, device=K.device).expand(A.shape[0], 4, 4)
    pts = torch.stack([A, A + 10.0 * axis], dim=1)  # (N, 2, 3)
    uv = project_points(K, eye, pts)
    px_per_mm = ((uv[:, 1] - uv[:, 0]).norm(dim=-1) / 10.0).clamp_min(1e-6)
    d = torch.as_tensor(cue.distances_px, dtype=K.dtype, device=K.device)
    t = (d[None, :] / px_per_mm[:, None]).clamp(0.0, cue.shaft_length_mm)
    z = A[:, 2:3] + t * axis[:, 2:3]
    return (z.mean(dim=1) - cue.depth_mm) / cue.sigma_mm


def _joint_fit(
    K: torch.Tensor,
    camera_from_cm0: torch.Tensor,
    control_points0_deg: torch.Tensor,
    landmarks_px: torch.Tensor,
    extracted_px: torch.Tensor,
    kin: CMKinematics,
    *,
    depth_range_mm: tuple[float, float],
    landmark_sigma_px: float,
    control_point_sigma_deg: float,
    centerline_sigma_px: float,
    n_model_points: int,
    depth_cue: ShaftDepthCue | None = None,
    max_evaluations: int = 60,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Robust least-squares fit of pose (rotation about A, A's position) and control points to a
    centreline, with landmark and control-point priors. Returns (camera_from_cm, control points,
    final cost). Jacobians by forward differences, all 12 evaluations in one batched call."""
    from scipy.optimize import least_squares

    from fluoronav.geometry.rotations import rotvec_to_matrix

    dt, dev = K.dtype, K.device
    R0, a0 = camera_from_cm0[:3, :3], camera_from_cm0[:3, 3]
    n_cp = control_points0_deg.shape[0]
    centre = extracted_px.mean(0)
    ext = extracted_px - centre
    # √(2/n) weights: each centreline direction counts like one landmark-sized term per σ²
    w_model = 1.0 / (centerline_sigma_px * math.sqrt(n_model_points / 8.0))
    w_ext = 1.0 / (centerline_sigma_px * math.sqrt(ext.shape[0] / 8.0))

    def residuals(X: torch.Tensor) -> torch.Tensor:  # (N, 6 + n_cp) → (N, R)
        T = torch.zeros(X.shape[0], 4, 4, dtype=dt, device=dev)
        T[:, :3, :3] = rotvec_to_matrix(X[:, :3]) @ R0
        T[:, :3, 3] = a0 + X[:, 3:6]
        T[:, 3, 3] = 1.0
        cp = control_points0_deg + X[:, 6:]
        uv = project_points(K, T, kin.centerline_cm(cp, n_points=n_model_points)) - centre
        d_model = _point_to_fixed_polyline(uv, ext)
        d_ext = _fixed_points_to_polylines(ext, uv)
        lm = project_points(K, T, kin.landmarks_cm(cp))
        parts = [
            d_model * w_model,
            d_ext * w_ext,
            ((lm - landmarks_px) / landmark_sigma_px).reshape(X.shape[0], -1),
            X[:, 6:] / control_point_sigma_deg,
        ]
        if depth_cue is not None:
            parts.append(_shaft_depth_residual(depth_cue, K, T)[:, None])
        return torch.cat(parts, dim=1)

    step = np.array([1e-4] * 3 + [1e-3] * 3 + [1e-3] * n_cp)
    cache: dict[bytes, np.ndarray] = {}

    def both(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = x.tobytes()
        if key not in cache:
            X = torch.as_tensor(np.vstack([x, x + np.diag(step)]), dtype=dt, device=dev)
            r = residuals(X).cpu().numpy()
            cache.clear()
            cache[key] = r
        r = cache[key]
        return r[0], ((r[1:] - r[0]) / step[:, None]).T

    z0 = float(a0[2])
    lo = np.full(6 + n_cp, -np.inf)
    hi = np.full(6 + n_cp, np.inf)
    lo[5], hi[5] = depth_range_mm[0] - z0, depth_range_mm[1] - z0  # A's depth stays in the range
    x0 = np.zeros(6 + n_cp)
    x0[5] = np.clip(0.0, lo[5] + 1e-6, hi[5] - 1e-6)
    sol = least_squares(
        lambda x: both(x)[0], x0, jac=lambda x: both(x)[1], bounds=(lo, hi), method="trf",
        loss="soft_l1", f_scale=2.0, max_nfev=max_evaluations,
    )  # fmt: skip
    x = torch.as_tensor(sol.x, dtype=dt, device=dev)
    T = torch.eye(4, dtype=dt, device=dev)
    T[:3, :3] = rotvec_to_matrix(x[:3]) @ R0
    T[:3, 3] = a0 + x[3:6]
    return T.cpu().numpy(), (control_points0_deg + x[6:]).cpu().numpy(), float(sol.cost)


@dataclass(frozen=True)
class MultiViewInitResult:
    """Result of :func:`centerline_initialize_multiview`.

    Attributes:
        world_from_cm: (4, 4) the best pose (world frame of the cameras).
        theta_deg: its roll about the chord (θ = 0: the CM x axis along the chord × view 0's axis).
        cost_px: its centreline cost, mean over the views (pixels).
        landmarks_world: (2, 3) triangulated A and B.
        alternatives: (S, 4, 4) poses of the local minima over θ, lowest cost first (the first is the
            best; with two candidate landmark pairs, see ``landmark_confidence``, the minima of
            both scans); alternative_costs_px: (S,) their costs.
        theta_grid_deg, theta_costs_px: the scanned θ and the cost curve (of the best pair).
        landmark_inliers: (V, 2) whether view k's A / B agreed with the others (robust triangulation).
        landmarks_px: (V, 2, 2) the given landmarks, with those that disagreed replaced by the
            projection of the triangulated point: use them for the registration's ROI and prior.
    """

    world_from_cm: np.ndarray
    theta_deg: float
    cost_px: float
    landmarks_world: np.ndarray
    alternatives: np.ndarray
    alternative_costs_px: np.ndarray
    theta_grid_deg: np.ndarray
    theta_costs_px: np.ndarray
    landmark_inliers: np.ndarray
    landmarks_px: np.ndarray


def centerline_initialize_multiview(
    cameras: list[Camera],
    landmarks_px: np.ndarray,
    centerlines_px: list[np.ndarray],
    control_points_deg: np.ndarray,
    *,
    config: CMConfig | None = None,
    n_theta: int = 360,
    n_model_points: int = 48,
    trim_fraction: float = 0.1,
    max_landmark_residual_px: float | None = None,
    landmark_confidence: np.ndarray | None = None,
) -> MultiViewInitResult:
    """Initial CM pose from two or more views: triangulated landmarks, then a scan of the roll.

    With the views' relative geometry known (e.g. from the pelvis registrations, §II-C) the landmarks
    A and B triangulate (:func:`~fluoronav.geometry.camera.triangulate_points`), which removes the
    depth ambiguity of a single view; the one remaining DoF, the roll θ about the chord, is scanned
    on ``n_theta`` values and scored by the centreline cost (:func:`centerline_cost`) averaged over
    all views, where the mirror ambiguity of one view is resolved by the others. A sits on the
    triangulated A, the model chord points at the triangulated B.

    With three or more views a landmark that disagrees with the others (a wrong detection, reprojection
    residual above ``max_landmark_residual_px``) is left out of its triangulation
    (:func:`~fluoronav.geometry.camera.triangulate_points_robust`), and that view's centreline, drawn
    to the wrong landmark, out of the roll score. Measured: a detection of B 75 px off in one of three
    views turned the roll 49° (tip 3.3 mm) in a 20-trial multi-view study.

    Args:
        cameras: V ≥ 2 cameras in one world frame.
        landmarks_px: (V, 2, 2) detected A, B per view.
        centerlines_px: V extracted centrelines (P_k, 2), ordered A → B.
        control_points_deg: (5,) FBG control points.
        config: CM geometry.
        n_theta: roll samples over 360°.
        n_model_points, trim_fraction: as :func:`centerline_initialize`.
        max_landmark_residual_px: outlier threshold of the triangulation, the cameras' pixels;
            None: 2.5 % of view 0's width (19 px at 768², ~7.5 mm on the CIOS Fusion detector).
        landmark_confidence: (V, 2) the detector's confidence of each landmark. With it, a landmark
            that only two views saw and that they disagree on (no vote possible) is taken from the
            more confident view, at the model's A–B distance from the other landmark on that view's
            ray; both intersections are scanned. Measured: a detection of A on B (confidence 0.28
            against 0.83 in the other view) turned the roll 49° (tip 3.4 mm) in a 20-trial study.

    Raises:
        InputError: malformed inputs; RegistrationFailure: coincident triangulated landmarks.
    """
    from fluoronav.geometry.camera import triangulate_points_robust

    if len(cameras) < 2 or len(centerlines_px) != len(cameras):
        raise InputError("cameras", f"need ≥ 2 views with one centreline each, got {len(cameras)}")
    lm = _as_input(landmarks_px, (len(cameras), 2, 2), "landmarks_px")
    conf = (
        None
        if landmark_confidence is None
        else _as_input(landmark_confidence, (len(cameras), 2), "landmark_confidence")
    )
    cls = [_as_input(c, None, f"centerlines_px[{k}]") for k, c in enumerate(centerlines_px)]
    cfg = config or CMConfig()
    cp = _as_input(control_points_deg, (cfg.n_control_points,), "control_points_deg")
    dt = torch.float64
    thr = 0.025 * cameras[0].cols if max_landmark_residual_px is None else float(max_landmark_residual_px)
    ab, inliers, residuals = triangulate_points_robust(cameras, lm, max_residual_px=thr)
    kin = CMKinematics(cfg)
    cp_t = torch.as_tensor(cp, dtype=dt)
    lm_cm = kin.landmarks_cm(cp_t)
    chord_mm = float((lm_cm[1] - lm_cm[0]).norm())
    candidates = [ab]
    if conf is not None:
        candidates, inliers = _two_view_landmark_candidates(
            cameras, lm, conf, ab, inliers, residuals, chord_mm=chord_mm, max_residual_px=thr
        )
    scored = [k for k in range(len(cameras)) if inliers[k].all()] or list(range(len(cameras)))
    centerline_cm = kin.centerline_cm(cp_t, n_points=n_model_points)
    theta = torch.arange(n_theta, dtype=dt) * (360.0 / n_theta)
    scans = []
    for cand in candidates:
        if np.linalg.norm(cand[1] - cand[0]) < 1e-6:
            raise RegistrationFailure("the triangulated landmarks A and B coincide")
        W, cost = _roll_scan(cameras, cls, scored, cand, lm_cm, centerline_cm, theta, trim_fraction)
        c = torch.where(torch.isfinite(cost), cost, torch.full_like(cost, math.inf))
        minima = (c <= torch.roll(c, 1)) & (c <= torch.roll(c, -1)) & torch.isfinite(c)
        scans.append((cand, W, c, torch.nonzero(minima).squeeze(-1)))
    all_minima = [(float(c[i]), s, int(i)) for s, (_, _, c, idx) in enumerate(scans) for i in idx]
    if not all_minima:
        raise RegistrationFailure("no finite centreline cost over the roll scan")
    all_minima.sort(key=lambda m: m[0])
    best_cost, best_scan, best = all_minima[0]
    ab, W_best, c_best, _ = scans[best_scan]
    consensus = lm.copy()
    for k, cam in enumerate(cameras):
        for n in range(2):
            if not inliers[k, n]:
                consensus[k, n] = cam.project(ab[n][None])[0]
    return MultiViewInitResult(
        world_from_cm=W_best[best].numpy(),
        theta_deg=float(theta[best]),
        cost_px=best_cost,
        landmarks_world=ab,
        alternatives=np.stack([scans[s][1][i].numpy() for _, s, i in all_minima]),
        alternative_costs_px=np.array([m[0] for m in all_minima]),
        theta_grid_deg=theta.numpy(),
        theta_costs_px=c_best.numpy(),
        landmark_inliers=inliers.copy(),
        landmarks_px=consensus,
    )


def _roll_scan(
    cameras: Sequence[Camera],
    centerlines_px: Sequence[np.ndarray],
    scored: Sequence[int],
    ab: np.ndarray,
    lm_cm: torch.Tensor,
    centerline_cm: torch.Tensor,
    theta_deg: torch.Tensor,
    trim_fraction: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Poses with model A on ``ab[0]`` and the model chord towards ``ab[1]`` for every roll θ, and
    their centreline cost averaged over the ``scored`` views: ``(world_from_cm (N, 4, 4), cost (N,))``."""
    dt = torch.float64
    u = _normalize(torch.as_tensor(ab[1] - ab[0], dtype=dt))
    view_axis = torch.as_tensor(cameras[0].world_from_camera[:3, 2], dtype=dt)
    ref = torch.linalg.cross(view_axis, u)
    if float(ref.norm()) < 1e-6:  # chord along view 0's axis: any perpendicular will do
        ref = torch.linalg.cross(torch.tensor([1.0, 0.0, 0.0], dtype=dt), u)
    ref = _normalize(ref)
    th = torch.deg2rad(theta_deg)[:, None]
    e2 = torch.cos(th) * ref + torch.sin(th) * torch.linalg.cross(u, ref)
    basis = torch.stack([u.expand_as(e2), e2, torch.linalg.cross(u.expand_as(e2), e2)], dim=-1)
    R = basis @ _cm_basis(lm_cm[1] - lm_cm[0]).T
    t = torch.as_tensor(ab[0], dtype=dt) - (R @ lm_cm[0])
    W = make_transform(R, t)  # (N, 4, 4) world_from_cm
    cost = torch.zeros(theta_deg.shape[0], dtype=dt)
    for k in scored:
        cam = cameras[k]
        T = torch.as_tensor(cam.camera_from_world, dtype=dt) @ W
        cost = cost + centerline_cost(
            torch.as_tensor(cam.K, dtype=dt),
            T,
            centerline_cm,
            torch.as_tensor(centerlines_px[k], dtype=dt),
            trim_fraction=trim_fraction,
        )
    return W, cost / len(scored)


def _two_view_landmark_candidates(
    cameras: Sequence[Camera],
    landmarks_px: np.ndarray,
    confidence: np.ndarray,
    ab: np.ndarray,
    inliers: np.ndarray,
    residuals_px: np.ndarray,
    *,
    chord_mm: float,
    max_residual_px: float,
) -> tuple[list[np.ndarray], np.ndarray]:
    """Where only two views saw a landmark and they disagree (a vote is impossible), trust the view
    with the more confident detection and place the landmark on its ray at the model's chord length
    from the other, agreeing landmark: the two intersections of the ray with that sphere are the
    candidate (A, B) pairs. The less confident view's landmark is marked an outlier.

    Returns ``(candidates [(2, 3) mm], inliers (V, 2))``; ``[ab]`` and the inliers unchanged where
    nothing applies (both landmarks disagree, or no intersection)."""
    inl = inliers.copy()
    for n in range(2):
        m = 1 - n
        voters = np.flatnonzero(inl[:, n])
        if len(voters) != 2 or residuals_px[voters, n].max() <= max_residual_px:
            continue
        if residuals_px[inl[:, m], m].max() > max_residual_px:
            continue  # both landmarks disagree: nothing to anchor the chord on
        trusted = int(voters[np.argmax(confidence[voters, n])])
        cam = cameras[trusted]
        origin = cam.source_world
        d = cam.ray_directions_world(landmarks_px[trusted, n][None])[0]
        # |origin + s d − P_m| = L  →  s² + 2 s d·(o − P) + |o − P|² − L² = 0
        op = origin - ab[m]
        b, c = float(d @ op), float(op @ op - chord_mm**2)
        disc = b * b - c
        if disc < 0:
            continue
        roots = [s for s in (-b - np.sqrt(disc), -b + np.sqrt(disc)) if s > 0]
        if not roots:
            continue
        out = []
        for s in roots:
            cand = ab.copy()
            cand[n] = origin + s * d
            out.append(cand)
        inl[voters[voters != trusted], n] = False
        logger.info(
            "landmark %s: two views disagree (%.1f px); the view with confidence %.2f is trusted",
            "AB"[n],
            float(residuals_px[voters, n].max()),
            float(confidence[trusted, n]),
        )
        return out, inl
    return [ab], inl


def turn_about_chord(
    world_from_cm: np.ndarray,
    control_points_deg: np.ndarray,
    angle_deg: float,
    config: CMConfig | None = None,
) -> np.ndarray:
    """The CM pose turned by ``angle_deg`` about its A→B chord: A and B stay put (on their rays), the
    bending plane turns. (4, 4), same frame as ``world_from_cm``."""
    from scipy.spatial.transform import Rotation

    kin = CMKinematics(config or CMConfig())
    ab = kin.landmarks_cm(torch.as_tensor(control_points_deg, dtype=torch.float64)).numpy()
    axis = ab[1] - ab[0]
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec(math.radians(angle_deg) * axis / np.linalg.norm(axis)).as_matrix()
    turn[:3, 3] = ab[0] - turn[:3, :3] @ ab[0]
    return np.asarray(world_from_cm, dtype=np.float64) @ turn


def mirror_about_chord(
    world_from_cm: np.ndarray, control_points_deg: np.ndarray, config: CMConfig | None = None
) -> np.ndarray:
    """The CM pose turned 180° about its A→B chord: A and B stay put, the bending plane flips.

    A centreline seen in one view hardly tells these two apart (the paper's θ ambiguity), so both are
    worth a start.

    Args:
        world_from_cm: (4, 4) CM base pose (any frame).
        control_points_deg: (5,) shape.
        config: CM geometry (default :class:`CMConfig`).

    Returns:
        (4, 4) the mirrored pose, same frame.
    """
    return turn_about_chord(world_from_cm, control_points_deg, 180.0, config)


# ----- evaluation ---------------------------------------------------------------------------------
def roll_about_axis_deg(
    camera_from_cm_est: np.ndarray | torch.Tensor,
    camera_from_cm_true: np.ndarray | torch.Tensor,
    axis_cm: np.ndarray | torch.Tensor,
) -> torch.Tensor:
    """Roll error (twist of the swing-twist decomposition) about a CM-frame axis, degrees in [0, 180].

    Args:
        camera_from_cm_est, camera_from_cm_true: (..., 4, 4).
        axis_cm: (..., 3) axis in the CM frame (the chord A→B).

    Returns:
        (...) |twist angle| of ``R_trueᵀ R_est`` about the axis.
    """
    Te = torch.as_tensor(camera_from_cm_est, dtype=torch.float64)
    Tt = torch.as_tensor(camera_from_cm_true, dtype=torch.float64, device=Te.device)
    axis = _normalize(torch.as_tensor(axis_cm, dtype=torch.float64, device=Te.device))
    rel = Tt[..., :3, :3].transpose(-1, -2) @ Te[..., :3, :3]
    q = matrix_to_quat(rel)  # (x, y, z, w), w ≥ 0
    twist = 2.0 * torch.atan2((q[..., :3] * axis).sum(-1), q[..., 3])
    twist = torch.remainder(torch.rad2deg(twist) + 180.0, 360.0) - 180.0
    return twist.abs()


@dataclass(frozen=True)
class CenterlineScene:
    """A synthetic initialisation problem (ground truth and the noisy observations)."""

    camera: Camera
    camera_from_cm: np.ndarray  # (4, 4) ground truth
    control_points_deg: np.ndarray  # (5,) ground truth
    fbg_control_points_deg: np.ndarray  # (5,) with FBG noise
    landmarks_px: np.ndarray  # (2, 2) with detection noise
    centerline_px: np.ndarray  # (P, 2)


def synthetic_centerline_scene(
    rng: np.random.Generator,
    *,
    config: CMConfig | None = None,
    source_to_isocenter_mm: tuple[float, float] = (400.0, 500.0),
    translation_mm: float = 30.0,
    rotation_deg: float = 30.0,
    roll_deg: float | None = None,
    fbg_noise_deg: float = 0.5,
    landmark_noise_px: float = 3.0,
    n_centerline_points: int = 100,
) -> CenterlineScene:
    """A random AP-view scene made from the model: projected landmarks and centreline plus noise.

    Follows the paper's CM simulation protocol (FACTS.md): AP view (CIOS Fusion) with the isocentre
    U(``source_to_isocenter_mm``) from the source; the CM nominally lies across the view (its axis in
    the image plane at a uniform in-plane angle, A at the isocentre; roll ``roll_deg``, uniform when
    None, 90° = bending plane parallel to the image plane), then is perturbed
    by a rotation of U(±``rotation_deg``) about a uniformly random axis in the CM base frame and a
    translation of U(±``translation_mm``) per axis; control points U(range of the config).
    Noise: U(±fbg_noise_deg) on the control points, U(±landmark_noise_px) per landmark coordinate;
    the centreline is the true projection from A to B, bent over the first and last 10 % of its arc
    length to start and end at the noisy landmarks (as a path traced between detected landmarks does).
    """
    from fluoronav.geometry.carm import carm_camera

    cfg = config or CMConfig()
    kin = CMKinematics(cfg)
    sid = rng.uniform(*source_to_isocenter_mm)
    camera = carm_camera(source_to_isocenter_mm=sid)
    phi, roll = rng.uniform(0.0, 2.0 * math.pi, 2)
    if roll_deg is not None:
        roll = math.radians(roll_deg)
    z_axis = np.array([math.cos(phi), math.sin(phi), 0.0])
    x0 = np.array([-math.sin(phi), math.cos(phi), 0.0])
    x_axis = math.cos(roll) * x0 + math.sin(roll) * np.cross(z_axis, x0)
    nominal = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis], axis=1)  # camera_from_cm rotation
    axis = rng.normal(size=3)
    perturb = _axis_angle(axis / np.linalg.norm(axis), math.radians(rng.uniform(-rotation_deg, rotation_deg)))
    T = np.eye(4)
    T[:3, :3] = nominal @ perturb
    T[:3, 3] = np.array([0.0, 0.0, sid]) + rng.uniform(-translation_mm, translation_mm, 3)
    lo_cp, hi_cp = cfg.control_point_range_deg
    cp = rng.uniform(lo_cp, hi_cp, cfg.n_control_points)
    fbg = cp + rng.uniform(-fbg_noise_deg, fbg_noise_deg, cp.shape)
    cp_t = torch.as_tensor(cp, dtype=torch.float64)
    lm_cm = kin.landmarks_cm(cp_t).numpy()
    cl_cm = kin.centerline_cm(cp_t, n_points=4 * n_centerline_points).numpy()
    cam_pose = camera.with_pose(T)  # points in the CM frame projected with camera_from_cm
    lm_true = cam_pose.project(lm_cm)
    lm_noisy = lm_true + rng.uniform(-landmark_noise_px, landmark_noise_px, (2, 2))
    cl = cam_pose.project(cl_cm)
    s = np.linspace(0.0, 1.0, cl.shape[0])[:, None]
    w_a, w_b = np.clip(1.0 - s / 0.1, 0.0, 1.0), np.clip((s - 0.9) / 0.1, 0.0, 1.0)
    cl = cl + w_a * (lm_noisy[0] - lm_true[0]) + w_b * (lm_noisy[1] - lm_true[1])
    return CenterlineScene(
        camera=camera,
        camera_from_cm=T,
        control_points_deg=cp,
        fbg_control_points_deg=fbg,
        landmarks_px=lm_noisy,
        centerline_px=resample_polyline(cl, n_centerline_points),
    )


def _axis_angle(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    Kx = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle_rad) * Kx + (1.0 - math.cos(angle_rad)) * Kx @ Kx


def evaluate_centerline_init(
    n: int = 20,
    seed: int = 0,
    *,
    fbg_noise_deg: float = 0.5,
    landmark_noise_px: float = 3.0,
    refine: bool = True,
    n_samples: int = 1000,
    scene_options: dict[str, Any] | None = None,
    depth_window_mm: float | None = None,
    **init_options: Any,
) -> dict[str, float]:
    """Run the initialiser on ``n`` random synthetic scenes and summarise its errors.

    ``scene_options`` go to :func:`synthetic_centerline_scene`, ``init_options`` to
    :func:`centerline_initialize`. ``depth_window_mm``: search the depth within this distance of the
    isocentre (the scenes' nominal CM position, as the femoral head in the studies).

    Returns:
        mean/std of the depth error (mm, |z_A est − z_A true|) and of the θ error (degrees, roll about
        the true chord, in [0, 180]), mean final cost (px) and mean run time per initialisation (s).
    """
    rng = np.random.default_rng(seed)
    kin = CMKinematics()
    depth_err, theta_err, costs, times = [], [], [], []
    for _ in range(n):
        sc = synthetic_centerline_scene(
            rng, fbg_noise_deg=fbg_noise_deg, landmark_noise_px=landmark_noise_px, **(scene_options or {})
        )
        t0 = time.perf_counter()
        if depth_window_mm is not None:
            init_options["depth_range_mm"] = depth_range_about(
                sc.camera, np.zeros(3), window_mm=depth_window_mm
            )
        res = centerline_initialize(
            sc.camera, sc.landmarks_px, sc.centerline_px, sc.fbg_control_points_deg,
            refine=refine, n_samples=n_samples, seed=int(rng.integers(2**31)), **init_options,
        )  # fmt: skip
        times.append(time.perf_counter() - t0)
        chord = kin.landmarks_cm(torch.as_tensor(sc.control_points_deg)).numpy()
        a_true = sc.camera_from_cm[:3, :3] @ chord[0] + sc.camera_from_cm[:3, 3]
        depth_err.append(abs(res.depth_mm - a_true[2]))
        theta_err.append(
            float(roll_about_axis_deg(res.camera_from_cm, sc.camera_from_cm, chord[1] - chord[0]))
        )
        costs.append(res.cost_px)
    return {
        "depth_error_mm_mean": float(np.mean(depth_err)),
        "depth_error_mm_std": float(np.std(depth_err)),
        "theta_error_deg_mean": float(np.mean(theta_err)),
        "theta_error_deg_std": float(np.std(theta_err)),
        "cost_px_mean": float(np.mean(costs)),
        "seconds_per_init": float(np.mean(times)),
    }


def multiview_start_poses(
    init: Any, *, max_starts: int = 2, cost_ratio: float = 1.5, slack_px: float = 0.25
) -> list[np.ndarray]:
    """Starts from a multi-view centreline initialisation: its roll minima whose cost is within
    ``cost_ratio`` × the best + ``slack_px``, at most ``max_starts``, best first. Several views
    usually leave one clear minimum (e.g. 0.45 px against 1.55 px for the next), and a start in a
    clearly worse one only costs time and risks the short screening picking it."""
    best = float(init.alternative_costs_px[0])
    keep = [
        W
        for W, c in zip(init.alternatives, init.alternative_costs_px, strict=True)
        if float(c) <= cost_ratio * best + slack_px
    ]
    return keep[:max_starts]
