"""The roll of the CM about its A→B chord scored against one image (:func:`roll_scan`): the degree of
freedom one view's centreline leaves open (Gao et al., IEEE TBME 69(1), 2022: θ, 31° mean error)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fluoronav.detection.centerline import resample_polyline
from fluoronav.registration.centerline.cost import centerline_cost
from fluoronav.registration.centerline.geometry import turn_about_chord
from fluoronav.registration.centerline.single import CenterlineInitConfig
from fluoronav.registration.cm.config import CMRegistrationConfig
from fluoronav.registration.cm.problem import CMProblem
from fluoronav.registration.cm.views import CMView

__all__ = [
    "CENTERLINE_SAMPLING",
    "ROLL_SCAN_ANGLES",
    "ROLL_SCAN_CENTERLINE_MARGIN_PX",
    "RollScanResult",
    "roll_scan",
    "roll_scan_initialization",
]

#: turns scanned over 360°
ROLL_SCAN_ANGLES = 36
#: turns whose centreline cost is within this margin of the best turn's compete, pixels
ROLL_SCAN_CENTERLINE_MARGIN_PX = 1.0
#: the centreline gate samples the model and the extracted centreline as the centreline
#: initialisation does
CENTERLINE_SAMPLING = CenterlineInitConfig()


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
    n_angles: int = ROLL_SCAN_ANGLES,
    alternatives: Sequence[np.ndarray] = (),
    centerline_px: np.ndarray | None = None,
    centerline_margin_px: float = ROLL_SCAN_CENTERLINE_MARGIN_PX,
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
        f64 = torch.float64
        sampling = CENTERLINE_SAMPLING
        cl_cm = prob.kinematics.centerline_cm(
            torch.as_tensor(control_points_deg, dtype=f64), n_points=sampling.n_model_points
        )
        cam_from_cm = np.stack([view.camera.camera_from_world @ W for W in poses])
        cl_cost = centerline_cost(
            torch.as_tensor(view.camera.K, dtype=f64),
            torch.as_tensor(cam_from_cm, dtype=f64),
            cl_cm,
            torch.as_tensor(
                resample_polyline(np.asarray(centerline_px, np.float64), sampling.n_extracted_points),
                dtype=f64,
            ),
            trim_fraction=sampling.trim_fraction,
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
