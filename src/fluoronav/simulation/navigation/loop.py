"""The navigation loop in simulation, as ``fluoronav demo`` and ``fluoronav study navigation`` run it.

Stages: ``scene`` (:mod:`fluoronav.simulation.navigation.scenario`: the patient, a UR-10 with errors holding
the CM, three C-arm views); ``simulate`` (physics X-rays → a
:class:`~fluoronav.navigation.case.model.NavigationCase`, optionally written to files and read back so that
the pipeline sees only what a user's files give); :func:`~fluoronav.navigation.pipeline.navigate`; ``move``
(the *true* robot to the commanded joints: the repositioning error); ``verify_simulate`` (the C-arm slid to
centre the femoral head and the planned CM as registered, ± ``aim_error_mm``, images of the CM where the robot
took it), :func:`~fluoronav.navigation.pipeline.verify` and ``correct_move``. Frames: ``world`` is the
simulation's (the CT frame before the patient moved), ``ct`` the pipeline's. CM and femur errors are measured
in the AP view's C-arm frame (as the paper's), repositioning in the world frame.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from fluoronav.errors import InputError
from fluoronav.geometry import se3
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.carm import centre_on, orbit_camera
from fluoronav.manipulator.robot import UR10
from fluoronav.navigation.case.model import (
    CaseView,
    NavigationCase,
    VerificationViews,
    load_navigation_case,
    write_navigation_case,
)
from fluoronav.navigation.pipeline import EventCallback, NavigationConfig, NavigationResult, navigate, verify
from fluoronav.registration.metrics import axis_error_deg
from fluoronav.registration.stages import StageRecord, StageTimer
from fluoronav.simulation.navigation.causes import refusal_causes, refused_at
from fluoronav.simulation.navigation.faults import (
    apply_case_fault,
    apply_first_fault,
    apply_verification_fault,
    get_fault,
    view_without_cm,
)
from fluoronav.simulation.navigation.scenario import (
    Scenario,
    SimulatedNavigationConfig,
    build_scenario,
    verification_view_indices,
)
from fluoronav.simulation.navigation.truth_errors import (
    first_registration_errors,
    robot_only_error,
    verification_errors,
)
from fluoronav.simulation.robot_scene import verification_view_centre
from fluoronav.simulation.world import case_fbg_reading
from fluoronav.simulation.world_anatomy import world_anatomy

log = logging.getLogger(__name__)

__all__ = [
    "SIMULATION_STAGES",
    "SimulatedNavigation",
    "SimulatedNavigationConfig",
    "run_simulated_navigation",
]

#: the loop's own stages around the pipeline's (those are in ``NavigationResult.stages``)
SIMULATION_STAGES = ("anatomy", "scene", "simulate", "move", "verify_simulate", "correct_move")


@dataclass
class SimulatedNavigation:
    """What a simulated navigation measured.

    ``errors`` is a flat dict of floats (against the truth); ``truth`` holds the true poses with the
    keys of ``navigation.json`` (JSON-ready); ``causes``, where the navigation refused (or an
    injected fault made the case bad input), the cause the simulation knows against the one the
    refusal named (:func:`~fluoronav.simulation.navigation.causes.refusal_causes`); ``loop_stages``
    the loop's own stages (the pipeline's are ``result.stages``), their seconds in ``timings_s``;
    ``artifacts`` holds arrays for the report (not serialised).
    """

    config: SimulatedNavigationConfig
    result: NavigationResult | None = None
    errors: dict[str, float] = field(default_factory=dict)
    truth: dict[str, Any] = field(default_factory=dict)
    causes: dict[str, Any] = field(default_factory=dict)
    loop_stages: dict[str, StageRecord] = field(default_factory=dict)
    artifacts: dict[str, Any] = field(default_factory=dict)

    @property
    def timings_s(self) -> dict[str, float]:
        """Seconds of the loop's own stages, in the order they ran."""
        return {name: rec.seconds for name, rec in self.loop_stages.items()}

    @property
    def status(self) -> str:
        return "failed" if self.result is None else self.result.status

    @property
    def reason(self) -> str:
        return "" if self.result is None else self.result.reason


def _views(
    images: list[Any],
    names: list[str],
    world_from_ct_initial: np.ndarray,
    *,
    oracle: bool,
    rng: np.random.Generator,
    cameras: list[Camera] | None = None,
) -> tuple[CaseView, ...]:
    """Case views of simulated images: each camera (the image's, or the case's ``cameras`` at the
    stored size) with the CT where the registration starts."""
    out = []
    for k, (im, name) in enumerate(zip(images, names, strict=True)):
        given = im.camera if cameras is None else cameras[k]
        cam: Camera = given.with_pose(given.camera_from_world @ world_from_ct_initial)
        lm = mask = None
        if oracle:
            binning = max(1, round(1536 / cam.cols))
            lm = im.landmarks_px + rng.uniform(-3.0, 3.0, (2, 2)) / binning
            mask = im.mask.astype(bool)
        out.append(CaseView(name, np.asarray(im.image, np.float32), cam, landmarks_px=lm, mask=mask))
    return tuple(out)


def _truth_poses(
    world_from_ct: np.ndarray,
    world_from_cm: np.ndarray,
    world_from_femur: np.ndarray,
    control_points_deg: np.ndarray,
    tip_cm: np.ndarray,
    cameras: list[Camera],
    names: list[str],
) -> dict[str, Any]:
    ct_from_world = np.linalg.inv(world_from_ct)
    return {
        "ct_from_cm": (ct_from_world @ world_from_cm).tolist(),
        "control_points_deg": np.asarray(control_points_deg).tolist(),
        "tip_ct_mm": se3.apply(ct_from_world @ world_from_cm, tip_cm).tolist(),
        "ct_from_femur": (ct_from_world @ world_from_femur).tolist(),
        "carm_from_ct": {
            n: (c.camera_from_world @ world_from_ct).tolist() for n, c in zip(names, cameras, strict=True)
        },
    }


def _first_case(
    s: Scenario, run: SimulatedNavigation, rng: np.random.Generator, seed: int, case_dir: Path | None
) -> tuple[NavigationCase, list[Any]]:
    """Stage ``simulate``: the images with the robot at its working pose → (the case, the images);
    the truth into ``run.truth``."""
    cfg, tr = s.config, s.sc.trial
    images = s.simulate(s.W_regi, s.cams, seed)
    fbg = case_fbg_reading(
        tr.initial_control_points_deg, s.cp_true, cfg.world.fbg, s.world_rng, built=s.built
    )
    W0 = tr.initial_world_from_patient
    case = NavigationCase(
        volume=s.volume,
        plan=s.plan,
        side=tr.side,
        cm_config=s.sc.cm_config,
        fbg_control_points_deg=np.asarray(fbg, np.float64),
        fbg_sigma_deg=cfg.world.fbg.stated_sigma(),
        robot=UR10,
        joints_deg=np.asarray(s.q_regi, np.float64),
        ee_from_cm=s.ee_from_cm_used,
        views=_views(
            images, s.names, W0, oracle=cfg.oracle_landmarks, rng=rng, cameras=s.case_cameras(s.cams)
        ),
    )
    case = _first_fault(s, case, seed)
    run.truth = _truth_poses(
        tr.world_from_patient,
        s.W_regi,
        tr.world_from_femur,
        s.cp_true,
        s.tip_cm,
        [i.camera for i in images],
        s.names,
    )
    if case_dir is not None:
        path = write_navigation_case(case, case_dir)
        _write_truth(run, case_dir)
        case = load_navigation_case(path)
    return case, images


def _move(
    s: Scenario, run: SimulatedNavigation, res: NavigationResult, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stage ``move``: the true robot to the commanded joints → (world_from_cm after the move, the
    planned tip in the world, the planned pose in the world)."""
    assert res.joints_target_deg is not None and res.plan is not None
    tr, E = s.sc.trial, run.errors
    W_after = s.sc.execute(res.joints_target_deg, rng=rng)
    planned_tip_world = se3.apply(tr.world_from_femur, res.plan.tip_target_world_mm)
    W_plan_true = tr.world_from_femur @ res.femur_from_cm_target
    E["reposition_tip_mm"] = float(np.linalg.norm(se3.apply(W_after, s.tip_cm) - planned_tip_world))
    E["reposition_axis_deg"] = axis_error_deg(W_after[:3, 2], W_plan_true[:3, 2])
    E["joint_motion_deg"] = float(res.stages["robot"].diagnostics["joint_motion_deg"])
    E["reposition_robot_mm"] = robot_only_error(
        s.sc, res, s.q_regi, s.W_regi, s.ee_from_cm_used, rng, s.tip_cm
    )
    return W_after, planned_tip_world, W_plan_true


def _verification_case(
    s: Scenario,
    run: SimulatedNavigation,
    case: NavigationCase,
    W_after: np.ndarray,
    rng: np.random.Generator,
    seed: int,
    case_dir: Path | None,
    moved: np.ndarray,
) -> tuple[NavigationCase, list[Any]]:
    """Stage ``verify_simulate``: the C-arm aimed where the registrations put the femoral head and
    the planned CM, images of the CM after the move, the patient moved by ``moved`` (4, 4,
    ``moved_from_world``) since the first images → (the case with them, the images)."""
    cfg, tr, res = s.config, s.sc.trial, run.result
    assert res is not None and res.joints_target_deg is not None
    first, target = res.first, res.femur_from_cm_target
    assert first is not None and target is not None
    carm_est_from_ct = first.cameras_ct[0].camera_from_world
    centre_ct = se3.apply(first.ct_from_femur, verification_view_centre(target, tr.femoral_head_ct))
    # where the person aims the C-arm, in the world (through the estimated AP C-arm frame)
    centre = se3.apply(np.linalg.inv(s.cams[0].camera_from_world) @ carm_est_from_ct, centre_ct)
    centre = centre + rng.uniform(-cfg.aim_error_mm, cfg.aim_error_mm, 3)
    ap2 = centre_on(s.cams[0], centre)
    cams2 = [ap2] + [orbit_camera(ap2, angle_deg=a, isocenter_world=centre) for a in cfg.orbit_deg]
    fault = get_fault(cfg.fault)
    # the fault's verification images show the CM where it was before the move
    images2 = s.simulate(
        s.W_regi if fault is not None and fault.verify_images_before_move else W_after,
        cams2,
        seed,
        moved_from_world=moved,
    )
    names2 = [f"{n} after the move" for n in s.names]
    W0 = tr.initial_world_from_patient
    views2 = _views(images2, names2, W0, oracle=cfg.oracle_landmarks, rng=rng, cameras=s.case_cameras(cams2))
    # the C-arm's own account of where it went from each first position (its nominal motion)
    views2 = tuple(
        dataclasses.replace(
            v2,
            moved_from=v1.name,
            carm_motion=v2.camera.camera_from_world @ se3.inv(v1.camera.camera_from_world),
        )
        for v1, v2 in zip(case.views, views2, strict=True)
    )
    keep = verification_view_indices(len(views2), cfg.verify_views)
    images2, names2, views2 = (
        [images2[k] for k in keep],
        [names2[k] for k in keep],
        tuple(views2[k] for k in keep),
    )
    case = dataclasses.replace(
        case, verification=VerificationViews(np.asarray(res.joints_target_deg), views2)
    )
    case = apply_verification_fault(case, fault)
    run.truth["verification"] = _truth_poses(
        moved @ tr.world_from_patient,
        W_after,
        moved @ tr.world_from_femur,
        s.cp_true,
        s.tip_cm,
        [im.camera for im in images2],
        names2,
    )
    if case_dir is not None:
        path = write_navigation_case(case, case_dir, ct_path=_ct_path(case_dir))
        _write_truth(run, case_dir)
        case = load_navigation_case(path)
    return case, images2


def _navigate_first(
    s: Scenario,
    run: SimulatedNavigation,
    case: NavigationCase,
    images: list[Any],
    nav_cfg: NavigationConfig,
    *,
    on_stage: Callable[[str, str], None] | None,
    on_event: EventCallback | None,
) -> NavigationResult | None:
    """The pipeline on the first case and its registrations' true errors → its result (also
    ``run.result``); None where an injected fault made the case invalid input (recorded in
    ``run.artifacts["input_error"]``)."""
    try:
        res = navigate(case, nav_cfg, on_stage=on_stage, on_event=on_event)
    except InputError as exc:
        if s.config.fault is None:
            raise
        run.artifacts["input_error"] = {"reason": str(exc), "check": getattr(exc, "check", "")}
        _causes(s, run, "preflight", str(getattr(exc, "check", "")), case.views, images, "detect")
        return None
    run.result = res
    if res.status == "refused":
        _causes(s, run, *refused_at(res.reason), case.views, images, "detect")
    first_registration_errors(
        run.result,
        run.errors,
        run.truth["tip_ct_mm"],
        s.sc,
        dict(zip(s.names, images, strict=True)),
        s.W_regi,
        s.cp_true,
        tip_cm_true=s.tip_cm_true,
    )
    return res


def _verification_errors(
    s: Scenario,
    run: SimulatedNavigation,
    case: NavigationCase,
    images2: list[Any],
    W_after: np.ndarray,
    moved: np.ndarray,
) -> None:
    """The verification's true errors (``run.errors``): its images named as the case's verification
    views, the CM at ``W_after`` (4, 4) world, the patient moved by ``moved`` (4, 4)."""
    names2 = [v.name for v in case.verification.views] if case.verification is not None else []
    verification_errors(
        run.result,
        run.errors,
        s.sc,
        dict(zip(names2, images2, strict=True)),
        W_after,
        moved_from_world=moved,
        tip_cm_true=s.tip_cm_true,
    )


def run_simulated_navigation(
    config: SimulatedNavigationConfig | None = None,
    *,
    ct: str = "phantom",
    case_dir: Path | None = None,
    navigation: NavigationConfig | None = None,
    on_stage: Callable[[str, str], None] | None = None,
    on_event: EventCallback | None = None,
    until: Literal["case", "end"] = "end",
) -> SimulatedNavigation:
    """Simulate a case, navigate on it, move, verify and correct; measure everything (module docstring).

    Args:
        config: the simulation (default :class:`SimulatedNavigationConfig`).
        ct: ``"phantom"`` or a labelled CT path (labels ``pelvis``, ``femur_left``; landmarks
            ``femoral_head_left``, ``entry_left``).
        case_dir: when given, the case is written there (``navigation.json`` and its files, the truth
            to ``truth.json`` beside it) and read back before the pipeline runs on it.
        navigation: the pipeline's settings (default: device and seed of ``config``).
        on_stage: called with (stage name, "start" | "done") for the loop's and the pipeline's stages.
        on_event: passed to the pipeline (:data:`fluoronav.navigation.pipeline.EventCallback`).
        until: ``"case"`` stops once the first case is simulated (``artifacts["case"]``, the
            truth in ``truth``), before the pipeline runs.
    """
    cfg = config or SimulatedNavigationConfig()
    nav_cfg = navigation or NavigationConfig(device=cfg.device, seed=cfg.seed)
    rng_seed = abs(int(cfg.seed))
    run = SimulatedNavigation(config=cfg)
    T, E, A = StageTimer(run.loop_stages, on_stage), run.errors, run.artifacts
    torch.manual_seed(rng_seed % 2**63)
    rng = np.random.default_rng(rng_seed)
    seeds = rng.integers(2**31, size=8)

    s = build_scenario(cfg, ct, T, rng, int(seeds[0]), int(seeds[3]))
    with T("simulate"):
        case, images = _first_case(s, run, rng, int(seeds[1]), case_dir)
    A.update(volume=s.volume, scene=s.sc, images=images, names=s.names, case=case)
    if until == "case":
        return run

    res = _navigate_first(s, run, case, images, nav_cfg, on_stage=on_stage, on_event=on_event)
    if res is None or res.status != "ok" or res.joints_target_deg is None:
        return run
    with T("move"):
        W_after, planned_tip_world, W_plan_true = _move(s, run, res, rng)
    run.truth["world_from_cm_after"] = W_after.tolist()
    A.update(W_after=W_after, W_plan_true=W_plan_true)
    if not cfg.verify:
        return run

    with T("verify_simulate"):
        # the patient between the two sets of images (the robot's base stays)
        motion = cfg.world.motion
        moved = s.patient_motion(motion.between_sets_mm, motion.between_sets_deg)
        case, images2 = _verification_case(s, run, case, W_after, rng, int(seeds[2]), case_dir, moved)
    A.update(images2=images2, case=case)
    verify(case, res, on_stage=on_stage, on_event=on_event)
    _verification_errors(s, run, case, images2, W_after, moved)
    if res.status == "refused" and case.verification is not None:
        _causes(s, run, *refused_at(res.reason), case.verification.views, images2, "verify_detect")
    if res.status != "ok" or res.joints_correction_deg is None:
        return run
    with T("correct_move"):
        W_final = s.sc.execute(res.joints_correction_deg, rng=rng)
        # the plan moved with the femur
        E["corrected_tip_mm"] = float(
            np.linalg.norm(se3.apply(W_final, s.tip_cm) - se3.apply(moved, planned_tip_world))
        )
        E["corrected_axis_deg"] = axis_error_deg(W_final[:3, 2], (moved @ W_plan_true)[:3, 2])
    run.truth["world_from_cm_corrected"] = W_final.tolist()
    A["W_final"] = W_final
    return run


def _causes(
    s: Scenario,
    run: SimulatedNavigation,
    stage: str,
    check: str,
    case_views: Any,
    images: list[Any],
    detect_stage: str,
) -> None:
    """``run.causes`` of a refusal at ``stage`` with ``check`` in the set of images ``images`` (the
    case's ``case_views``, detected in ``detect_stage``)."""
    st = {} if run.result is None else run.result.stages
    run.causes = refusal_causes(
        stage,
        check,
        fault=get_fault(s.config.fault),
        handeye_error_mm=s.config.handeye_error_mm,
        handeye_error_deg=s.config.handeye_error_deg,
        case_views=list(case_views),
        images=images,
        detect_diagnostics=st[detect_stage].diagnostics if detect_stage in st else {},
    )


def _first_fault(s: Scenario, case: NavigationCase, seed: int) -> NavigationCase:
    """The case with the config's fault (:mod:`fluoronav.simulation.navigation.faults`) in its first views, CT
    labels or plan; a view without the CM is simulated anew (its seed as the first images')."""
    fault = get_fault(s.config.fault)
    if fault is None:
        return case
    if fault.without_cm and fault.view_index is not None:
        k, tr = fault.view_index, s.sc.trial
        bare = s.simulator.simulate(
            s.cams[k],
            world_from_patient=tr.world_from_patient,
            world_from_femur=tr.world_from_femur,
            cm=None,
            seed=seed + k,
            image_size=s.config.image_size,
            cm_config=s.sc.cm_config,
        )
        views = list(case.views)
        views[k] = view_without_cm(views[k], bare.image)
        case = dataclasses.replace(case, views=tuple(views))
    if fault.other_patient and fault.view_index is not None:
        case = _other_patient_view(s, case, fault.view_index, seed)
    return apply_case_fault(apply_first_fault(case, fault), fault)


def _other_patient_view(s: Scenario, case: NavigationCase, k: int, seed: int) -> NavigationCase:
    """The case with view ``k``'s image made of another patient (the next phantom seed, in the same
    world), the CM, the C-arm and the patient's pose as they are."""
    if not s.volume.name.startswith("phantom"):
        raise InputError("--fault", "view_other_patient needs the phantom (--ct phantom)")
    cfg, tr = s.config, s.sc.trial
    other_seed = (cfg.seed if cfg.phantom_seed is None else cfg.phantom_seed) + 1
    other = world_anatomy(
        "phantom",
        other_seed,
        cfg.world.ct,
        image_size=cfg.image_size,
        device=cfg.device,
        rng=np.random.default_rng(other_seed),
    )
    img = other.simulator.simulate(
        s.cams[k],
        world_from_patient=tr.world_from_patient,
        world_from_femur=tr.world_from_femur,
        cm=(s.W_regi, s.cp_true),
        seed=seed + k,
        image_size=cfg.image_size,
        cm_config=s.sc.cm_config,
        built_cm=s.built,
    )
    views = list(case.views)
    views[k] = dataclasses.replace(views[k], image=np.asarray(img.image, np.float32))
    return dataclasses.replace(case, views=tuple(views))


def _ct_path(case_dir: Path) -> str | None:
    """The CT file an earlier write of the case left in ``case_dir`` (not written twice)."""
    try:
        d = json.loads((case_dir / "navigation.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    ct = d.get("ct")
    return str(case_dir / ct) if isinstance(ct, str) and (case_dir / ct).is_file() else None


def _write_truth(run: SimulatedNavigation, case_dir: Path) -> None:
    path = case_dir.parent / "truth.json"
    path.write_text(json.dumps(run.truth, indent=1) + "\n", encoding="utf-8")
