"""Benchmark of the analytic CM DRR (called by :mod:`fluoronav.bench.rendering`)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

import numpy as np
import torch

from fluoronav.bench.timing import time_ms
from fluoronav.geometry.camera import CIOS_FUSION, Camera
from fluoronav.geometry.rotations import rotvec_to_matrix
from fluoronav.geometry.transforms import transform_from_params
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.rendering.cm import CMRenderer

__all__ = ["cm_benchmark_scene", "run_cm"]

logger = logging.getLogger(__name__)

#: nitinol at ~60 keV, 1/mm (order of magnitude; the timing does not depend on it)
_MU_NITINOL_PER_MM = 2.0


def cm_benchmark_scene(
    *,
    population: int = 50,
    seed: int = 0,
    source_to_cm_mm: float = 450.0,
    crop_px: int = 512,
    factor: int = 4,
) -> tuple[Camera, torch.Tensor, torch.Tensor]:
    """A CMA-ES-like population around an oblique CM pose in a CIOS Fusion ROI.

    The ROI is a ``crop_px``² crop of the 1536² CIOS Fusion image around the CM, binned by
    ``factor``, centred on the mean candidate's mid-axis point. Candidates perturb the pose (2°
    rotation, 2 mm translation, 1σ) and a moderately bent mean shape (1° per control point, 1σ).

    Returns:
        ``(camera, camera_from_cm (population, 1, 4, 4), control_points_deg (population, 5))``.
    """
    rng = np.random.default_rng(seed)
    config = CMConfig()
    full = Camera.from_detector(CIOS_FUSION)
    R = rotvec_to_matrix(torch.tensor([0.4, 1.2, 0.3], dtype=torch.float64)).numpy()  # oblique axis
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.array([0.0, 0.0, source_to_cm_mm]) - R @ np.array([0.0, 0.0, config.tip_z_mm / 2.0])
    mean_cp = np.array([3.0, 2.0, -1.0, 4.0, 2.0])[: config.n_control_points]
    mid = CMKinematics(config).centerline_cm(torch.tensor(mean_cp), n_points=3, to_z_mm=config.tip_z_mm)[1]
    center_uv = full.project(mid.numpy() @ T[:3, :3].T + T[:3, 3])
    camera = full.crop_around(center_uv, crop_px)[0].downsample(factor)
    sigma = np.array([math.radians(2.0)] * 3 + [2.0] * 3)
    params = torch.tensor(rng.normal(0.0, sigma, (population, 6)))
    camera_from_cm = (torch.tensor(T) @ transform_from_params(params))[:, None]
    lo, hi = config.control_point_range_deg
    cp = torch.tensor(np.clip(mean_cp + rng.normal(0.0, 1.0, (population, mean_cp.size)), lo, hi))
    return camera, camera_from_cm, cp


def run_cm(quick: bool, device: str = "cpu") -> dict[str, float]:
    """Time the analytic CM DRR of a 50-candidate population at 128×128 on ``device``.

    Returns ``cm_drr_128_ms_per_candidate`` (the ROI renderer: numba on the CPU, the torch backend
    in float64 on CUDA) and, measured in the same run on the same device,
    ``cm_drr_128_ms_per_candidate_baseline`` (the same kernel evaluating every pixel for every link,
    i.e. without the projected-box ROI) and ``cm_drr_128_ms_per_candidate_speedup``. On the CPU the
    torch backend's time is logged beside them.
    """
    camera, camera_from_cm, cp = cm_benchmark_scene()
    K = torch.tensor(camera.K)[None]
    B = cp.shape[0]
    fast = CMRenderer(mu_per_mm=_MU_NITINOL_PER_MM, device=device)
    rows, cols = camera.rows, camera.cols

    def timed(fn: Callable[[], object], repeats: int) -> float:
        return time_ms(fn, repeats=repeats, device=device)

    fast_ms = timed(lambda: fast.render(camera_from_cm, cp, K, rows, cols), 5 if quick else 30)
    base_ms = timed(lambda: fast.render(camera_from_cm, cp, K, rows, cols, roi=False), 2 if quick else 5)
    logger.info(
        "CM DRR %dx%d, %d candidates on %s (%s backend): %.2f ms ROI, %.2f ms every pixel",
        rows,
        cols,
        B,
        device,
        fast.backend,
        fast_ms,
        base_ms,
    )
    if fast.backend == "numba":
        tiled = CMRenderer(mu_per_mm=_MU_NITINOL_PER_MM, backend="torch")
        torch_ms = timed(lambda: tiled.render(camera_from_cm, cp, K, rows, cols), 1 if quick else 3)
        logger.info("CM DRR, the ROI torch backend in float64 on the CPU: %.2f ms", torch_ms)
    return {
        "cm_drr_128_ms_per_candidate": fast_ms / B,
        "cm_drr_128_ms_per_candidate_baseline": base_ms / B,
        "cm_drr_128_ms_per_candidate_speedup": base_ms / fast_ms,
    }
