"""Navigation benchmarks (``fluoronav bench``): the pelvis on one view and the whole ``navigate``
pipeline, each beside the same work with the registration settings of fluoronav 0.1.0.

The problem is a simulated phantom case as ``fluoronav demo`` makes it (seed :data:`BENCH_SEED`,
768² physics-simulated views, the shipped detector), without its verification views:

- ``register_bone_view_s``: the pelvis registered to the case's first view with the navigation
  pipeline's preset (:data:`~fluoronav.registration.bone.presets.PELVIS_LINEARIZED_PRESET`);
  ``_reference``: the CMA-ES ladder (:data:`~fluoronav.registration.bone.presets.PELVIS_CMAES_PRESET`)
  without empty-space skipping and with the similarity's torch ops, the settings of 0.1.0.
- ``navigate_s``: :func:`~fluoronav.navigation.pipeline.navigate` from detection through the robot
  command on the three views with the default settings; ``_reference``: the pelvis, femur and CM of
  0.1.0 (CMA-ES ladders without skipping, the CM's CMA-ES levels
  (:data:`~fluoronav.bench.registration.REFERENCE_CONFIG`), the similarity's torch ops).
- ``navigate_verify_s``: the same case with its three verification views (the simulated navigation
  run to its end): the pipeline's stages of the first images and of the verification, summed
  (the simulation's own stages are not counted); ``_reference``: with the settings of 0.4.1 (the
  CM's CMA-ES levels, every verification view's bones registered with the whole ladders, the
  verification's CM from the images alone: :meth:`VerificationConfig.reference`). Each run
  simulates its own verification images where its own command took the robot, so both are
  complete navigations; ``*_corrected_tip_mm`` is each one's true tip to plan after the correction.
- ``navigate_verify2_s``: the same with two verification views (the two orbits: the demo's 3 + 2),
  against the same reference (3 + 3 with the settings of 0.4.1).

Each ``_speedup`` is the reference over the figure. The errors of every run against the
simulation's truth are reported too (``*_pelvis_mm``: the pelvis centre in the camera frame;
``*_tip_mm``: the registered CM tip), so that a faster setting that got worse shows.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from fluoronav.bench.registration import REFERENCE_CONFIG
from fluoronav.geometry import se3
from fluoronav.navigation.pipeline import navigate
from fluoronav.navigation.result import NavigationConfig, VerificationConfig, reference_cm_config
from fluoronav.registration.bone import BoneView, register_pelvis
from fluoronav.registration.bone.presets import PELVIS_CMAES_PRESET, BoneRegistrationConfig, femur_config
from fluoronav.simulation.navigation.loop import SimulatedNavigationConfig, run_simulated_navigation

__all__ = ["BENCH_SEED", "run"]

log = logging.getLogger(__name__)

#: the simulated case's seed
BENCH_SEED = 3


def _reference(preset: BoneRegistrationConfig) -> BoneRegistrationConfig:
    """A bone preset as fluoronav 0.1.0 ran it: no empty-space skipping, the similarity's torch ops."""
    levels = tuple(
        replace(lv, optimizer=lv.optimizer.with_(similarity_backend="torch")) for lv in preset.levels
    )
    return replace(preset, levels=levels, skip_empty=False)


def run(quick: bool = False, device: str = "cpu") -> dict[str, float]:
    """Seconds of one pelvis view and of one navigation, each with its 0.1.0 reference (one repeat:
    a navigation takes minutes at the reference settings; ``quick`` changes nothing)."""
    sim = run_simulated_navigation(SimulatedNavigationConfig(seed=BENCH_SEED, device=device), until="case")
    case = replace(sim.artifacts["case"], verification=None)
    truth = sim.truth
    out: dict[str, float] = {}

    view = case.views[0]
    true_camera_from_ct = np.asarray(next(iter(truth["carm_from_ct"].values())))
    centre = np.asarray(case.volume.landmarks_world.get("pelvis_center", case.volume.center_world))
    reference_pelvis = _reference(PELVIS_CMAES_PRESET)
    for key, preset in (
        ("register_bone_view_s", NavigationConfig().pelvis),
        ("register_bone_view_s_reference", reference_pelvis),
    ):
        t0 = time.perf_counter()
        res = register_pelvis(
            [BoneView(np.asarray(view.image, np.float32), view.camera, None)],
            case.volume,
            initial_world_from_patient=np.eye(4),
            config=replace(preset, device=device),
            seed=BENCH_SEED,
        )
        out[key] = time.perf_counter() - t0
        err = se3.apply(res.camera_from_bone[0], centre) - se3.apply(true_camera_from_ct, centre)
        out[key.replace("_s", "_pelvis_mm", 1)] = float(np.linalg.norm(err))
        log.info("%s: %.2f s", key, out[key])

    reference_femur = _reference(femur_config(views=len(case.views)))
    for key, nav in (
        ("navigate_s", NavigationConfig(device=device, seed=BENCH_SEED)),
        (
            "navigate_s_reference",
            NavigationConfig(
                device=device,
                seed=BENCH_SEED,
                pelvis=reference_pelvis,
                femur=reference_femur,
                cm=REFERENCE_CONFIG,
            ),
        ),
    ):
        t0 = time.perf_counter()
        result = navigate(case, nav)
        out[key] = time.perf_counter() - t0
        if result.first is not None:
            out[key.replace("_s", "_tip_mm", 1)] = float(
                np.linalg.norm(np.asarray(result.first.tip_ct_mm) - np.asarray(truth["tip_ct_mm"]))
            )
        log.info("%s: %.1f s (%s)", key, out[key], result.status)
    out.update(_navigate_verify(device))
    for key in ("register_bone_view_s", "navigate_s", "navigate_verify_s"):
        out[f"{key}_speedup"] = out[f"{key}_reference"] / out[key]
    out["navigate_verify2_s_speedup"] = out["navigate_verify_s_reference"] / out["navigate_verify2_s"]
    return out


def _navigate_verify(device: str) -> dict[str, float]:
    """``navigate_verify_s`` and its reference (module docstring)."""
    out: dict[str, float] = {}
    reference = NavigationConfig(
        device=device,
        seed=BENCH_SEED,
        cm=reference_cm_config(),
        verify_cm=reference_cm_config(),
        verification=VerificationConfig.reference(),
    )
    default = NavigationConfig(device=device, seed=BENCH_SEED)
    for key, nav, k in (
        ("navigate_verify_s", default, 3),
        ("navigate_verify2_s", default, 2),
        ("navigate_verify_s_reference", reference, 3),
    ):
        sim = run_simulated_navigation(
            SimulatedNavigationConfig(seed=BENCH_SEED, device=device, verify_views=k), navigation=nav
        )
        res = sim.result
        assert res is not None
        out[key] = float(sum(rec.seconds for rec in res.stages.values()))
        out[key.replace("_s", "_corrected_tip_mm", 1)] = float(
            sim.errors.get("corrected_tip_mm", float("nan"))
        )
        log.info("%s: %.1f s (%s)", key, out[key], res.status)
    return out
