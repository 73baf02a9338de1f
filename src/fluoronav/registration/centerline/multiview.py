"""Multi-view centreline initialisation of the CM pose: triangulated landmarks, then a roll scan
(Gao et al., IEEE TBME 69(1), 2022, sec. II-C: the views related through the pelvis registration)."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fluoronav.errors import InputError, RegistrationFailure
from fluoronav.geometry.camera import Camera, triangulate_points_robust
from fluoronav.geometry.transforms import make_transform
from fluoronav.manipulator import CMConfig, CMKinematics
from fluoronav.registration.centerline.cost import centerline_cost, checked_array
from fluoronav.registration.centerline.geometry import cm_basis, normalize

__all__ = [
    "MultiViewInitConfig",
    "MultiViewInitResult",
    "centerline_initialize_multiview",
    "multiview_start_poses",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MultiViewInitConfig:
    """Settings of :func:`centerline_initialize_multiview`.

    Attributes:
        n_theta: roll samples over 360°.
        n_model_points: points on the model centreline A → B.
        trim_fraction: robust cost, fraction of the largest distances dropped (each direction).
        max_landmark_residual_px: outlier threshold of the triangulation, the cameras' pixels; None:
            ``landmark_residual_fraction`` of view 0's width.
        landmark_residual_fraction: the default threshold as a fraction of the image width (2.5 %:
            19 px at 768², ~7.5 mm on the CIOS Fusion detector).
        prior_gate_mm: with landmarks predicted in 3D (``landmark_prior_world``), a detection whose
            pixel lies farther than this from the prediction's, in mm at the prediction's depth, is
            left out (docs/validation.md, "The checks' thresholds").
        min_landmark_confidence: with the detector's confidences, a landmark detected less
            confidently than this is left out of its triangulation where at least one view detected
            it confidently (with one such view, it lies on that view's ray at the model's A–B
            distance from the other landmark: both intersections are scanned). Where no view is
            confident, all are used (the confidences of wrong and right detections:
            docs/validation.md, "Unsure landmarks"). None: confidences only break two-view ties.
    """

    n_theta: int = 360
    n_model_points: int = 48
    trim_fraction: float = 0.1
    max_landmark_residual_px: float | None = None
    landmark_residual_fraction: float = 0.025
    prior_gate_mm: float = 6.0
    min_landmark_confidence: float | None = 0.5


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
    init_config: MultiViewInitConfig | None = None,
    landmark_confidence: np.ndarray | None = None,
    landmark_prior_world: np.ndarray | None = None,
) -> MultiViewInitResult:
    """Initial CM pose from two or more views: triangulated landmarks, then a scan of the roll.

    With the views' relative geometry known (e.g. from the pelvis registrations, §II-C) the landmarks
    A and B triangulate (:func:`~fluoronav.geometry.camera.triangulate_points`), which removes the
    depth ambiguity of a single view; the one remaining DoF, the roll θ about the chord, is scanned
    on ``n_theta`` values and scored by the centreline cost
    (:func:`~fluoronav.registration.centerline.cost.centerline_cost`) averaged over all views, where
    the mirror ambiguity of one view is resolved by the others. A sits on the triangulated A, the
    model chord points at the triangulated B.

    With three or more views a landmark that disagrees with the others (a wrong detection, reprojection
    residual above the threshold) is left out of its triangulation
    (:func:`~fluoronav.geometry.camera.triangulate_points_robust`), and that view's centreline, drawn
    to the wrong landmark, out of the roll score: one wrong detection otherwise turns the roll by tens
    of degrees (docs/validation.md).

    Args:
        cameras: V ≥ 2 cameras in one world frame.
        landmarks_px: (V, 2, 2) detected A, B per view.
        centerlines_px: V extracted centrelines (P_k, 2), ordered A → B.
        control_points_deg: (5,) FBG control points.
        config: CM geometry.
        init_config: scan settings (default :class:`MultiViewInitConfig`).
        landmark_confidence: (V, 2) the detector's confidence of each landmark. With it, a landmark
            that only two views saw and that they disagree on (no vote possible) is taken from the
            more confident view, at the model's A–B distance from the other landmark on that view's
            ray; both intersections are scanned (docs/validation.md: a detection of A on B).
        landmark_prior_world: (2, 3) where A and B are expected (the verification: the CM where the
            robot's kinematics put it). Detections farther than ``prior_gate_mm`` from it are left
            out before the vote, so two wrong views cannot outvote a right one; a landmark that one
            view keeps lies on that view's ray nearest the prediction, one that none keeps at the
            prediction.

    Raises:
        InputError: malformed inputs; RegistrationFailure: coincident triangulated landmarks.
    """
    opt = init_config or MultiViewInitConfig()
    lm, conf, cls = _checked_inputs(cameras, landmarks_px, centerlines_px, landmark_confidence)
    cfg = config or CMConfig()
    cp = checked_array(control_points_deg, (cfg.n_control_points,), "control_points_deg")
    kin = CMKinematics(cfg)
    cp_t = torch.as_tensor(cp, dtype=torch.float64)
    lm_cm = kin.landmarks_cm(cp_t)
    candidates, inliers = _landmark_candidates(cameras, lm, conf, landmark_prior_world, lm_cm, opt)
    scored = [k for k in range(len(cameras)) if inliers[k].all()] or list(range(len(cameras)))
    centerline_cm = kin.centerline_cm(cp_t, n_points=opt.n_model_points)
    theta = torch.arange(opt.n_theta, dtype=torch.float64) * (360.0 / opt.n_theta)
    scans, all_minima = _scan_candidates(cameras, cls, scored, candidates, lm_cm, centerline_cm, theta, opt)
    best_cost, best_scan, best = all_minima[0]
    ab, W_best, c_best, _ = scans[best_scan]
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
        landmarks_px=_consensus_landmarks(cameras, lm, ab, inliers),
    )


def _checked_inputs(
    cameras: Sequence[Camera],
    landmarks_px: np.ndarray,
    centerlines_px: Sequence[np.ndarray],
    landmark_confidence: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray | None, list[np.ndarray]]:
    """The views' inputs checked: ``(landmarks (V, 2, 2), confidences (V, 2) or None, centrelines)``;
    InputError where malformed."""
    if len(cameras) < 2 or len(centerlines_px) != len(cameras):
        raise InputError("cameras", f"need ≥ 2 views with one centreline each, got {len(cameras)}")
    lm = checked_array(landmarks_px, (len(cameras), 2, 2), "landmarks_px")
    conf = (
        None
        if landmark_confidence is None
        else checked_array(landmark_confidence, (len(cameras), 2), "landmark_confidence")
    )
    cls = [checked_array(c, None, f"centerlines_px[{k}]") for k, c in enumerate(centerlines_px)]
    return lm, conf, cls


_Scan = tuple[np.ndarray, torch.Tensor, torch.Tensor, torch.Tensor]


def _scan_candidates(
    cameras: Sequence[Camera],
    centerlines_px: Sequence[np.ndarray],
    scored: Sequence[int],
    candidates: Sequence[np.ndarray],
    lm_cm: torch.Tensor,
    centerline_cm: torch.Tensor,
    theta: torch.Tensor,
    opt: MultiViewInitConfig,
) -> tuple[list[_Scan], list[tuple[float, int, int]]]:
    """The roll scan of each candidate landmark pair ``(ab, world_from_cm, cost, minima)`` and the
    local minima of all scans ``(cost, scan, θ index)``, cheapest first."""
    scans = []
    for cand in candidates:
        if np.linalg.norm(cand[1] - cand[0]) < 1e-6:
            raise RegistrationFailure("the triangulated landmarks A and B coincide")
        W, cost = _roll_scan(
            cameras, centerlines_px, scored, cand, lm_cm, centerline_cm, theta, opt.trim_fraction
        )
        c = torch.where(torch.isfinite(cost), cost, torch.full_like(cost, math.inf))
        minima = (c <= torch.roll(c, 1)) & (c <= torch.roll(c, -1)) & torch.isfinite(c)
        scans.append((cand, W, c, torch.nonzero(minima).squeeze(-1)))
    all_minima = [(float(c[i]), s, int(i)) for s, (_, _, c, idx) in enumerate(scans) for i in idx]
    if not all_minima:
        raise RegistrationFailure("no finite centreline cost over the roll scan")
    all_minima.sort(key=lambda m: m[0])
    return scans, all_minima


def _landmark_candidates(
    cameras: Sequence[Camera],
    lm: np.ndarray,
    conf: np.ndarray | None,
    landmark_prior_world: np.ndarray | None,
    lm_cm: torch.Tensor,
    opt: MultiViewInitConfig,
) -> tuple[list[np.ndarray], np.ndarray]:
    """The triangulated landmark pairs to scan (see :func:`centerline_initialize_multiview`) and
    which detections agreed: ``(candidates [(2, 3) mm], inliers (V, 2))``."""
    thr = (
        opt.landmark_residual_fraction * cameras[0].cols
        if opt.max_landmark_residual_px is None
        else float(opt.max_landmark_residual_px)
    )
    lonely: list[tuple[int, int]] = []  # (landmark, its one confident view)
    if landmark_prior_world is None and conf is not None and opt.min_landmark_confidence is not None:
        ab, inliers, residuals, lonely = _triangulate_confident(
            cameras, lm, conf, min_confidence=opt.min_landmark_confidence, max_residual_px=thr
        )
    elif landmark_prior_world is None:
        ab, inliers, residuals = triangulate_points_robust(cameras, lm, max_residual_px=thr)
    else:
        prior = checked_array(landmark_prior_world, (2, 3), "landmark_prior_world")
        ab, inliers, residuals = _triangulate_near_prior(
            cameras, lm, prior, gate_mm=opt.prior_gate_mm, max_residual_px=thr
        )
    if conf is None or landmark_prior_world is not None:
        return [ab], inliers
    chord_mm = float((lm_cm[1] - lm_cm[0]).norm())
    if lonely:
        n, k = lonely[0]
        cands = _on_ray_at_chord(cameras[k], lm[k, n], ab, n, chord_mm)
        if cands:
            logger.info("landmark %s: only view %d detected it confidently; placed on its ray", "AB"[n], k)
            return cands, inliers
    return _two_view_landmark_candidates(
        cameras, lm, conf, ab, inliers, residuals, chord_mm=chord_mm, max_residual_px=thr
    )


def _consensus_landmarks(
    cameras: Sequence[Camera], lm: np.ndarray, ab: np.ndarray, inliers: np.ndarray
) -> np.ndarray:
    """(V, 2, 2) the detections, those that disagreed replaced by the projections of ``ab``."""
    consensus = lm.copy()
    for k, cam in enumerate(cameras):
        for n in range(2):
            if not inliers[k, n]:
                consensus[k, n] = cam.project(ab[n][None])[0]
    return consensus


def _triangulate_near_prior(
    cameras: Sequence[Camera], lm: np.ndarray, prior: np.ndarray, *, gate_mm: float, max_residual_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Robust triangulation of the detections within ``gate_mm`` of the predicted points (see
    :func:`centerline_initialize_multiview`): ``(points (2, 3), inliers (V, 2), residuals_px (V, 2))``."""
    V = len(cameras)
    near = np.zeros((V, 2), dtype=bool)
    for k, cam in enumerate(cameras):
        depth = cam.to_camera(prior)[:, 2]
        off_mm = np.linalg.norm(lm[k] - cam.project(prior), axis=1) * depth / float(cam.K[0, 0])
        near[k] = off_mm <= gate_mm
    pts, inliers = prior.astype(np.float64).copy(), near.copy()
    for n in range(2):
        use = np.flatnonzero(near[:, n])
        if len(use) >= 2:
            X, inl, _ = triangulate_points_robust(
                [cameras[int(v)] for v in use], lm[use][:, n : n + 1], max_residual_px=max_residual_px
            )
            pts[n], inliers[use, n] = X[0], inl[:, 0]
        elif len(use) == 1:
            cam = cameras[int(use[0])]
            d = cam.ray_directions_world(lm[use[0], n])
            pts[n] = cam.source_world + d * float((prior[n] - cam.source_world) @ d)
        if len(use) < V:
            logger.info(
                "landmark %s: %d of %d views within %.1f mm of the prediction", "AB"[n], len(use), V, gate_mm
            )
    residuals = np.stack([np.linalg.norm(cam.project(pts) - lm[k], axis=1) for k, cam in enumerate(cameras)])
    return pts, inliers, residuals


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
    u = normalize(torch.as_tensor(ab[1] - ab[0], dtype=dt))
    view_axis = torch.as_tensor(cameras[0].world_from_camera[:3, 2], dtype=dt)
    ref = torch.linalg.cross(view_axis, u)
    if float(ref.norm()) < 1e-6:  # chord along view 0's axis: any perpendicular will do
        ref = torch.linalg.cross(torch.tensor([1.0, 0.0, 0.0], dtype=dt), u)
    ref = normalize(ref)
    th = torch.deg2rad(theta_deg)[:, None]
    e2 = torch.cos(th) * ref + torch.sin(th) * torch.linalg.cross(u, ref)
    basis = torch.stack([u.expand_as(e2), e2, torch.linalg.cross(u.expand_as(e2), e2)], dim=-1)
    R = basis @ cm_basis(lm_cm[1] - lm_cm[0]).T
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


def _on_ray_at_chord(
    camera: Camera, pixel: np.ndarray, ab: np.ndarray, n: int, chord_mm: float
) -> list[np.ndarray]:
    """Landmark ``n`` on ``camera``'s ray through ``pixel`` at ``chord_mm`` from the other landmark
    ``ab[1 − n]``: the candidate (A, B) pairs, one per intersection in front of the source (none
    where the ray misses that sphere)."""
    m = 1 - n
    origin = camera.source_world
    d = camera.ray_directions_world(np.asarray(pixel, np.float64)[None])[0]
    # |origin + s d − P_m| = L  →  s² + 2 s d·(o − P) + |o − P|² − L² = 0
    op = origin - ab[m]
    b, c = float(d @ op), float(op @ op - chord_mm**2)
    disc = b * b - c
    if disc < 0:
        return []
    out = []
    for s in (-b - np.sqrt(disc), -b + np.sqrt(disc)):
        if s > 0:
            cand = ab.copy()
            cand[n] = origin + s * d
            out.append(cand)
    return out


def _triangulate_confident(
    cameras: Sequence[Camera],
    lm: np.ndarray,
    conf: np.ndarray,
    *,
    min_confidence: float,
    max_residual_px: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """Each landmark triangulated (robustly) from all views; where they disagree, from the views that
    detected it confidently (two or more), or from all where none did. ``(points (2, 3), inliers
    (V, 2), residuals_px (V, 2), lonely)``: ``lonely`` lists (landmark, view) where one view alone
    was confident (its point is then the all-view triangulation, to be replaced on that view's
    ray)."""
    V = len(cameras)
    ab, inliers, residuals = triangulate_points_robust(cameras, lm, max_residual_px=max_residual_px)
    lonely: list[tuple[int, int]] = []
    for n in range(2):
        sure = np.flatnonzero(conf[:, n] >= min_confidence)
        if residuals[:, n].max() <= max_residual_px or len(sure) == V or len(sure) == 0:
            continue  # every view agrees, or confidence tells nothing apart
        if len(sure) == 1:
            lonely.append((n, int(sure[0])))
            inliers[:, n] = np.arange(V) == sure[0]
            continue
        pts, inl, _ = triangulate_points_robust(
            [cameras[int(k)] for k in sure], lm[sure][:, n : n + 1], max_residual_px=max_residual_px
        )
        ab[n] = pts[0]
        inliers[:, n] = False
        inliers[sure, n] = inl[:, 0]
    for n in range(2):
        residuals[:, n] = [
            np.linalg.norm(c.project(ab[n][None])[0] - lm[k, n]) for k, c in enumerate(cameras)
        ]
    return ab, inliers, residuals, lonely


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
        out = _on_ray_at_chord(cameras[trusted], landmarks_px[trusted, n], ab, n, chord_mm)
        if not out:
            continue
        inl[voters[voters != trusted], n] = False
        logger.info(
            "landmark %s: two views disagree (%.1f px); the view with confidence %.2f is trusted",
            "AB"[n],
            float(residuals_px[voters, n].max()),
            float(confidence[trusted, n]),
        )
        return out, inl
    return [ab], inl


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
