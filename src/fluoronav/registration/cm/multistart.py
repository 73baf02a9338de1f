"""CM registration from several start poses (:func:`register_cm_multistart`)."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from fluoronav.registration.cm.config import CMRegistrationConfig
from fluoronav.registration.cm.problem import cm_workflow, register_cm
from fluoronav.registration.cm.result import CMRegistrationResult
from fluoronav.registration.cm.views import CMView

__all__ = ["SCREEN_ITERATIONS", "register_cm_multistart"]

logger = logging.getLogger(__name__)

#: CMA-ES generations of the screening of each start: 15 are too few to rank a start 70° off in roll
#: below the right one (docs/validation.md)
SCREEN_ITERATIONS = 40


def register_cm_multistart(
    views: Sequence[CMView],
    starts_world_from_cm: Sequence[np.ndarray],
    *,
    initial_control_points_deg: np.ndarray | Sequence[float],
    base_from_cm: np.ndarray | None = None,
    config: CMRegistrationConfig | None = None,
    seed: int = 0,
    screen_iterations: int | None = SCREEN_ITERATIONS,
) -> CMRegistrationResult:
    """Register from several start poses: screen every start on the first level, finish the best.

    Use it with the centreline initialisation's alternatives and their mirrors
    (:func:`~fluoronav.registration.centerline.mirror_about_chord`): a single view hardly tells
    the roll about the A→B chord apart, and a wrong basin cannot be left by a local optimiser.

    Screening runs the first (coarsest, cheapest) level from every start for at most
    ``screen_iterations`` CMA-ES generations (None: to convergence; default
    :data:`SCREEN_ITERATIONS`); the start with the lowest cost (NaN/inf count as worst) then runs all
    levels from where its screening ended.

    Args:
        views, initial_control_points_deg, base_from_cm, config, seed: as
            :func:`~fluoronav.registration.cm.problem.register_cm`.
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
    first = cfg.levels_for(cm_workflow(len(views), multiple_cm=base_from_cm is not None))[0]
    screen = cfg.with_(levels=(first.with_(max_iters=screen_iterations, restarts=0),))
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
