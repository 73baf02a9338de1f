"""Navigation benchmarks (``fluoronav bench``): the pelvis on one view, the preflight and ``navigate``.

The case is a simulated phantom case as ``fluoronav demo`` makes it (seed :data:`BENCH_SEED`, 768²
views, the shipped detector). Keys: ``register_bone_view_s`` (the pelvis on the first view with the
navigation's preset), ``navigate_s`` (:func:`~fluoronav.navigation.pipeline.navigate`, detection to
robot command, three views), ``preflight_s`` and ``preflight_cross_checks_s`` (:func:`preflight_times`),
``navigate_verify_s`` and ``navigate_verify2_s`` (the case run to its end with three or two
verification views: the pipeline's stages summed, each run simulating its own verification images).
The registrations have a ``_reference`` (the reference settings, ``reference-0.4.1``), a
``_speedup`` and their errors against the truth (``*_pelvis_mm``, ``*_tip_mm``,
``*_corrected_tip_mm``): a faster setting that got worse shows (docs/validation.md, "Speed").
"""

from __future__ import annotations

import logging
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace

import numpy as np

from fluoronav.bench.registration import REFERENCE_CONFIG
from fluoronav.geometry import se3
from fluoronav.navigation.case.model import NavigationCase
from fluoronav.navigation.checks.preflight import check_shared_inputs, preflight
from fluoronav.navigation.checks.preflight_config import PreflightConfig
from fluoronav.navigation.checks.side import check_side
from fluoronav.navigation.config import NavigationConfig, shipped_settings
from fluoronav.navigation.pipeline import navigate
from fluoronav.registration.bone import BoneView, register_pelvis
from fluoronav.registration.bone.presets import PELVIS_CMAES_PRESET, BoneRegistrationConfig, femur_config
from fluoronav.simulation.navigation.loop import SimulatedNavigationConfig, run_simulated_navigation

__all__ = ["BENCH_SEED", "REFERENCE_SETTINGS", "navigate_startup", "preflight_times", "run"]

log = logging.getLogger(__name__)

#: the simulated case's seed
BENCH_SEED = 3

#: the shipped settings file of ``navigate_verify_s_reference`` (the settings of fluoronav 0.4.1)
REFERENCE_SETTINGS = "reference-0.4.1"


def _reference(preset: BoneRegistrationConfig) -> BoneRegistrationConfig:
    """The reference of a bone preset: no empty-space skipping, the similarity's torch ops."""
    levels = tuple(
        replace(lv, optimizer=lv.optimizer.with_(similarity_backend="torch")) for lv in preset.levels
    )
    return replace(preset, levels=levels, skip_empty=False)


def run(quick: bool = False, device: str = "cpu") -> dict[str, float]:
    """Seconds of one pelvis view and of one navigation, each with its reference (one repeat:
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
        ("register_bone_view_s", NavigationConfig().views.pelvis),
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
                views=replace(
                    NavigationConfig().views,
                    pelvis=reference_pelvis,
                    femur=reference_femur,
                    cm=REFERENCE_CONFIG,
                ),
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
    out.update(preflight_times(case))
    out.update(_navigate_verify(device))
    for key in ("register_bone_view_s", "navigate_s", "navigate_verify_s"):
        out[f"{key}_speedup"] = out[f"{key}_reference"] / out[key]
    out["navigate_verify2_s_speedup"] = out["navigate_verify_s_reference"] / out["navigate_verify2_s"]
    out.update(navigate_startup(quick))
    return out


def preflight_times(case: NavigationCase, repeats: int = 3) -> dict[str, float]:
    """``preflight_s``: seconds of the whole preflight of ``case``; ``preflight_cross_checks_s``: of
    its checks of the inputs against each other (:func:`check_shared_inputs`, :func:`check_side`);
    each the median of ``repeats``."""
    cfg = PreflightConfig()
    whole, cross = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        preflight(case, cfg)
        t1 = time.perf_counter()
        check_shared_inputs(case, cfg)
        check_side(case)
        cross.append(time.perf_counter() - t1)
        whole.append(t1 - t0)
    out = {"preflight_s": statistics.median(whole), "preflight_cross_checks_s": statistics.median(cross)}
    log.info("preflight_s: %.2f s (cross checks %.2f s)", out["preflight_s"], out["preflight_cross_checks_s"])
    return out


def _navigate_verify(device: str) -> dict[str, float]:
    """``navigate_verify_s`` and its reference (module docstring)."""
    out: dict[str, float] = {}
    reference = shipped_settings(REFERENCE_SETTINGS, NavigationConfig(device=device, seed=BENCH_SEED))
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


#: a process's code up to where ``fluoronav navigate`` starts its work: the command on a case that is
#: not there loads what it runs, then stops at reading the case (exit status 2 as 0 here)
_NAVIGATE_UNTIL_WORK = """
import sys
from fluoronav.cli.main import main
try:
    main(["navigate", sys.argv[1], "--out", sys.argv[2]])
except SystemExit as exc:
    sys.exit(0 if exc.code == 2 else 1)
"""

#: the reference's start: what fluoronav 0.9.0's navigate loaded, every module of the package and
#: the libraries those imported at the top (now imported at their first use: cma, roma)
_IMPORT_EVERY_MODULE = """
import importlib, pkgutil, fluoronav, cma, roma
for module in pkgutil.walk_packages(fluoronav.__path__, "fluoronav."):
    importlib.import_module(module.name)
"""


def navigate_startup(quick: bool = False) -> dict[str, float]:
    """``navigate_startup_s``: seconds from a process's start until ``fluoronav navigate`` would start
    its work, the median of 5 processes (1 with ``quick``); ``_reference`` the same with every module
    of the package imported first; ``_speedup``."""
    repeats = 1 if quick else 5
    with tempfile.TemporaryDirectory() as tmp:
        args = [f"{tmp}/no_case/navigation.json", f"{tmp}/out"]
        if not quick:
            _process_s(_IMPORT_EVERY_MODULE + _NAVIGATE_UNTIL_WORK, args)  # untimed: bytecode caches
        own, reference = [], []
        for _ in range(repeats):  # interleaved: a busy machine slows both alike
            own.append(_process_s(_NAVIGATE_UNTIL_WORK, args))
            reference.append(_process_s(_IMPORT_EVERY_MODULE + _NAVIGATE_UNTIL_WORK, args))
    out = {
        "navigate_startup_s": float(statistics.median(own)),
        "navigate_startup_s_reference": float(statistics.median(reference)),
    }
    out["navigate_startup_s_speedup"] = out["navigate_startup_s_reference"] / out["navigate_startup_s"]
    log.info(
        "navigate_startup_s: %.2f s (reference %.2f s)",
        out["navigate_startup_s"],
        out["navigate_startup_s_reference"],
    )
    return out


def _process_s(code: str, args: list[str]) -> float:
    """Wall seconds of one ``python -c code *args`` process, which must end where the navigate
    command refuses the missing case."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, encoding="utf-8")
    seconds = time.perf_counter() - t0
    if proc.returncode != 0 or "navigation case not found" not in proc.stderr:
        raise RuntimeError(f"the navigate command did not reach its case: {proc.stderr.strip()[-400:]}")
    return seconds
