"""CM registration benchmark (speed) and accuracy study on physics-simulated images.

- :func:`run` (``fluoronav bench``): ``register_single_view_s`` and ``register_multi_view_s``, the
  median seconds of one registration from the default initialisation (truth perturbed 10°/10 mm,
  control points ±0.5°) on a fixed simulated scene (768² image = the 1536² CIOS detector binned 2×,
  5,000 photons per pixel) with the default settings. ``_reference``, timed in the same run on the
  same problem and seed: :data:`REFERENCE_CONFIG` (CMA-ES at both levels, the similarity's torch
  ops, every pixel of each CM link's box). ``_tip_mm``: the registered tip's distance from the
  truth, so that a faster setting that got worse shows.
- :func:`evaluate_cm_registration`: the accuracy study (tip, base, notch errors, seconds).
"""

from __future__ import annotations

import logging
import statistics
import time
from dataclasses import replace
from typing import Any

import numpy as np
import torch

from fluoronav.detection.centerline import extract_centerline
from fluoronav.registration.centerline.single import centerline_initialize
from fluoronav.registration.cm.case import CMCase
from fluoronav.registration.cm.config import CMRegistrationConfig, default_cm_levels
from fluoronav.registration.cm.problem import CMProblem
from fluoronav.registration.cm.result import cm_pose_errors
from fluoronav.rendering.cm import CMRenderer
from fluoronav.simulation.cm_case import cm_case_from_simulation, simulate_cm_case
from fluoronav.simulation.xray import envelope_config

__all__ = ["REFERENCE_CONFIG", "evaluate_cm_registration", "run", "summarize"]

logger = logging.getLogger(__name__)


#: the CM registration settings of fluoronav 0.1.0 (the benchmark's reference)
REFERENCE_CONFIG = CMRegistrationConfig(
    levels=tuple(lv.with_(similarity_backend="torch") for lv in default_cm_levels()), row_spans=False
)


def _problem(case: CMCase, config: CMRegistrationConfig) -> CMProblem:
    return CMProblem(
        case.views,
        initial_world_from_cm=case.initial_world_from_cm,
        initial_control_points_deg=case.initial_control_points_deg,
        base_from_cm=case.base_from_cm,
        config=config,
        seed=0,
    )


def _time_registration(case: CMCase, config: CMRegistrationConfig, repeats: int) -> tuple[float, float]:
    """(median seconds, tip error mm of the last run)."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = _problem(case, config).run()
        times.append(time.perf_counter() - t0)
    assert case.world_from_cm_true is not None and case.control_points_true_deg is not None
    err = cm_pose_errors(
        res.world_from_cm[0], res.control_points_deg, case.world_from_cm_true[0], case.control_points_true_deg
    )
    return statistics.median(times), float(err["tip_error_mm"])


def run(quick: bool = False, device: str = "cpu") -> dict[str, float]:
    """Median seconds per single-view and multi-view registration on ``device``, with the
    reference (:data:`REFERENCE_CONFIG`, same device).

    ``quick`` runs one repeat instead of three; the problems are the same (simulated on the CPU).
    """
    # torch keeps its default threads, as `fluoronav register` and the demo run: with one thread a
    # registration took ~1.4x as long once an earlier stage in the process had run torch on every core
    size, repeats = 768, (1 if quick else 3)
    config = CMRegistrationConfig(device=device)
    reference = REFERENCE_CONFIG.with_(device=device)
    out: dict[str, float] = {}
    for key, workflow in (
        ("register_single_view_s", "single-view"),
        ("register_multi_view_s", "multi-view"),
    ):
        case = cm_case_from_simulation(simulate_cm_case(workflow, seed=11, image_size=size))  # type: ignore[arg-type]
        fast, tip = _time_registration(case, config, repeats)
        slow, tip_ref = _time_registration(case, reference, 1)
        tip_key = key.removesuffix("_s") + "_tip_mm"
        out.update({key: fast, f"{key}_reference": slow, f"{key}_speedup": slow / fast})
        out.update({tip_key: tip, f"{tip_key}_reference": tip_ref})
        logger.info("%s: %.2f s (0.1.0 settings %.2f s)", key, fast, slow)
    return out


def evaluate_cm_registration(
    workflow: str,
    n: int,
    seed: int,
    *,
    config: CMRegistrationConfig | None = None,
    image_size: int = 768,
    photons_per_pixel: float | None = 5000.0,
    init: str = "perturb",
    background: bool = False,
) -> list[dict[str, Any]]:
    """Register ``n`` simulated cases of a workflow and report errors and time per case.

    Args:
        workflow: "single-view", "multi-view" or "multi-cm".
        n: number of cases; case i uses seed ``seed + i``.
        config: registration settings (default :class:`CMRegistrationConfig`).
        image_size, photons_per_pixel, background: simulation settings (see ``simulate_cm_case``).
        init: "perturb" (truth perturbed 10°/10 mm, the authors' code) or "centerline" (the
            centreline initialisation from the true mask's centreline, first view).

    Returns:
        one row per case: ``seed``, the errors of :func:`cm_pose_errors` (mean over CM poses for
        multiple-CM), ``initial_tip_error_mm``, ``seconds``, ``converged``, ``reason``, ``n_evals``.
    """
    cfg = config or CMRegistrationConfig()
    rows = []
    for i in range(n):
        simulated = simulate_cm_case(
            workflow,  # type: ignore[arg-type]
            seed=seed + i,
            image_size=image_size,
            photons_per_pixel=photons_per_pixel,
        )
        case = cm_case_from_simulation(simulated, background=background)
        if init == "centerline":
            case = _centerline_init(case)
        prob = _problem(case, cfg)
        res = prob.run()
        assert case.world_from_cm_true is not None and case.control_points_true_deg is not None
        errs = [
            cm_pose_errors(W, res.control_points_deg, Wt, case.control_points_true_deg)
            for W, Wt in zip(res.world_from_cm, case.world_from_cm_true, strict=True)
        ]
        e0 = cm_pose_errors(
            case.initial_world_from_cm,
            case.initial_control_points_deg,
            case.world_from_cm_true[0],
            case.control_points_true_deg,
        )
        row: dict[str, Any] = {k: float(np.mean([e[k] for e in errs])) for k in errs[0]}
        row.update(
            seed=seed + i,
            workflow=workflow,
            initial_tip_error_mm=e0["tip_error_mm"],
            seconds=res.seconds,
            converged=res.converged,
            reason=res.reason,
            n_evals=res.trace.n_evals,
        )
        logger.info("case %d: tip %.2f mm in %.1f s", seed + i, row["tip_error_mm"], res.seconds)
        rows.append(row)
    return rows


def _centerline_init(case: CMCase) -> CMCase:
    """Replace the initial pose by the centreline initialisation of the first view (true mask)."""
    v = case.views[0]
    assert case.world_from_cm_true is not None and v.landmarks_px is not None
    env = CMRenderer(envelope_config(case.config.cm_config), mu_per_mm=1.0)
    T = torch.as_tensor(v.camera.camera_from_world @ case.world_from_cm_true[0])[None, None]
    cp = torch.as_tensor(case.control_points_true_deg)[None]
    mask = env.mask(T, cp, torch.as_tensor(v.camera.K)[None], v.camera.rows, v.camera.cols)[0, 0].numpy()
    centerline = extract_centerline(mask, v.landmarks_px[0], v.landmarks_px[1])
    init = centerline_initialize(
        v.camera, v.landmarks_px, centerline, case.initial_control_points_deg, image=v.image
    )
    return replace(case, initial_world_from_cm=v.camera.world_from_camera @ init.camera_from_cm)


def summarize(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Mean and median of the errors and seconds of :func:`evaluate_cm_registration` rows."""
    keys = (
        "tip_error_mm",
        "base_translation_error_mm",
        "base_rotation_error_deg",
        "notch_rotation_error_deg",
        "seconds",
    )
    out: dict[str, float] = {"n": float(len(rows))}
    for k in keys:
        vals = np.array([r[k] for r in rows], dtype=np.float64)
        out[f"{k}_mean"] = float(vals.mean())
        out[f"{k}_median"] = float(np.median(vals))
    out["converged_fraction"] = float(np.mean([r["converged"] for r in rows]))
    return out
