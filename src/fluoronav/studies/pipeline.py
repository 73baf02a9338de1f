"""The paper's simulation studies, one trial at a time (``fluoronav study``).

A trial (§III-B; :mod:`fluoronav.simulation.protocol`) samples the ground truth, simulates the X-ray
images with the physics simulator (never the registration's renderer), finds the CM landmarks (the
shipped detector, or ``--oracle-landmarks``: the truth plus U(−3, 3) px), registers pelvis and
femur, initialises the CM from its centreline, registers it and records the paper's metrics.
Frames: single-view and multiple-CM work in the world frame of the (known) C-arm view; multi-view
relates the views through the pelvis (each view's ``camera_k_from_ct``) and registers femur and CM
in the CT frame. Errors are computed in the C-arm frame of the first view. A study may run in a
simulated world (``StudyConfig.world``; :mod:`fluoronav.studies.world_trials`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fluoronav import __version__
from fluoronav.anatomy.io import resolve_ct
from fluoronav.anatomy.volume import Volume
from fluoronav.detection.centerline import extract_centerline
from fluoronav.errors import FluoronavError, InputError
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.registration.bone import PELVIS_PRESET, static_view_composite
from fluoronav.registration.centerline import (
    centerline_initialize,
    depth_range_about,
    mirror_about_chord,
    roll_about_axis_deg,
)
from fluoronav.registration.cm import (
    CMRegistrationConfig,
    CMRegistrationResult,
    CMView,
    fbg_shape_prior,
    register_cm,
    register_cm_multistart,
    roll_scan_initialization,
)
from fluoronav.registration.metrics import cm_errors, point_error_mm, relative_error_mm
from fluoronav.registration.view_set import (
    FluoroView,
    ViewDetection,
    ViewSetBones,
    ViewSetSeeds,
    ViewSetSettings,
    bone_views,
    register_view_set,
    register_view_set_bones,
    register_view_set_cm,
)
from fluoronav.runner import CsvLog, finish_row, mark_failed, new_row, run_tasks
from fluoronav.simulation.world import IDEAL, World
from fluoronav.studies.bone_errors import bone_registration_errors
from fluoronav.studies.check_values import check_values
from fluoronav.studies.figures import study_figures
from fluoronav.studies.study_ct import TRIAL_CT, check_study_ct
from fluoronav.studies.summary import summarize, write_summary
from fluoronav.studies.world_trials import simulate_world_trial, world_rng

log = logging.getLogger(__name__)

__all__ = ["METRICS", "STUDY_WORKFLOWS", "StudyConfig", "bone_registration_errors", "run_study", "run_trial"]

STUDY_WORKFLOWS = ("centerline", "single-view", "multi-view", "multi-cm")
BASE_METRICS = (
    "tip_mm",
    "entry_mm",
    "relative_mm",
    "base_translation_mm",
    "base_rotation_deg",
    "notch_rotation_deg",
)
AXIS_METRICS = (
    "base_tx_mm",
    "base_ty_mm",
    "base_tz_mm",
    "base_rx_deg",
    "base_ry_deg",
    "base_rz_deg",
    "base_depth_mm",
)
METRICS = {
    "centerline": ("depth_mm", "theta_deg", "theta_centerline_deg", *BASE_METRICS),
    "single-view": BASE_METRICS,
    "multi-view": BASE_METRICS,
    "multi-cm": BASE_METRICS,
}


@dataclasses.dataclass(frozen=True)
class StudyConfig:
    """Settings of a study run (recorded in ``DIR/config.json``)."""

    workflow: str
    trials: int
    seed: int
    ct: str = "phantom"
    oracle_landmarks: bool = False
    image_size: int = 768
    device: str = "cpu"
    n_phantoms: int = 1
    register_bones: bool = True
    #: CM start: "centerline" (the paper) or "perturbed" (truth + 10°/10 mm, the authors' code)
    init: str = "centerline"
    #: after the centreline initialisation, turn the CM about its chord to the best image score
    #: (:func:`~fluoronav.registration.cm.roll_scan`); the centreline study records θ before it too
    roll_scan: bool = True
    #: the simulated world's error sources (:mod:`fluoronav.studies.world_trials`); ideal: none
    world: World = IDEAL


# ----- per-process caches ---------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def _detector(device: str) -> Any:
    from fluoronav.detection.detector import Detector  # heavy: monai; oracle landmarks need no detector

    return Detector.load(None, device=device)


def _with_bones(volume: Volume, cfg: StudyConfig) -> bool:
    """Bones are registered (the centreline study's depth search too is centred on the femoral head)."""
    return (
        cfg.register_bones
        and volume.label_value("pelvis") is not None
        and volume.label_value("femur_left") is not None
        and "entry_left" in volume.landmarks_world
    )


def _full_to_image_px(uv_full: np.ndarray, binning: int) -> np.ndarray:
    """Full-detector pixel (centre convention) → binned image pixel."""
    return (np.asarray(uv_full, np.float64) + 0.5) / binning - 0.5


def _detect(
    images: list[Any], cameras: tuple[Camera, ...], oracle_px: np.ndarray, cfg: StudyConfig, binning: int
) -> list[FluoroView]:
    """Per image a view named ``view<k>`` with the registration's camera and the CM found in it:
    landmarks (2, 2), centreline, confidences (2,) (1 for oracle landmarks: ``oracle_px``, full
    detector) and segmentation; no detection where the detector found no CM or one cut by the image
    border (:attr:`~fluoronav.detection.detector.Detection.usable`)."""
    views: list[FluoroView] = []
    for i, (sim, camera) in enumerate(zip(images, cameras, strict=True)):
        if cfg.oracle_landmarks:
            lm = _full_to_image_px(oracle_px[i], binning)
            mask, cl, conf, source = sim.mask.astype(bool), None, np.ones(2), "oracle"
        else:
            det = _detector(cfg.device).detect(sim.image, pixel_spacing_mm=sim.camera.pixel_spacing_mm)
            if not det.usable:  # no CM, or a CM cut by the image border (a landmark at the cut)
                # the view still counts in the registration (ROI at the initial pose's projection);
                # the initialisation needs view 0 (one-view workflows) or two views (multi-view)
                views.append(FluoroView(f"view{i}", sim.image, camera))
                continue
            lm, mask, cl, source = det.landmarks_px, det.mask, det.centerline_px, "detector"
            conf = np.asarray(det.landmark_confidence, dtype=np.float64)
        cl = cl if cl is not None else extract_centerline(mask, lm[0], lm[1])
        views.append(FluoroView(f"view{i}", sim.image, camera, ViewDetection(lm, cl, mask, conf, source)))
    return views


def _theta_error_deg(camera_from_cm: np.ndarray, images: list[Any], trial: Any) -> float:
    """θ error: the roll about the true A→B chord between an estimated pose (view 0's camera frame)
    and the true pose, degrees in [0, 180]."""
    carm0_true = images[0].camera.camera_from_world @ trial.world_from_cm[0]
    ab = (
        CMKinematics(trial.cm_config)
        .landmarks_cm(torch.as_tensor(trial.control_points_deg, dtype=torch.float64))
        .numpy()
    )
    return float(roll_about_axis_deg(camera_from_cm, carm0_true, ab[1] - ab[0]))


class _TrialFailure(FluoronavError):
    """A trial that cannot go on (the CM not found where the workflow needs it)."""


@dataclasses.dataclass(frozen=True, eq=False)
class _Simulated:
    """A trial's truth, its simulated images and the CM found in each (``views``); ``volume`` and
    ``cameras`` are the CT and cameras the registration is given, ``tip_cm_true`` (3,) mm the tip of
    the instrument as built (None: the model's)."""

    volume: Volume
    trial: Any
    images: list[Any]
    views: list[FluoroView]
    cameras: tuple[Camera, ...]
    tip_cm_true: np.ndarray | None = None


@dataclasses.dataclass(frozen=True, eq=False)
class _Bones:
    """The bones registered in a trial: the views' cameras (CT frame in the multi-view workflow),
    the femoral entry and head estimates (world frame of the cameras) and the run time."""

    cameras: tuple[Any, ...]
    entry_world_est: np.ndarray
    head_world_est: np.ndarray
    seconds: float

    @classmethod
    def of(cls, bones: ViewSetBones, trial: Any) -> _Bones:
        world_from_femur = bones.femur.world_from_bone
        return cls(
            bones.cameras,
            (world_from_femur @ np.append(trial.entry_ct, 1.0))[:3],
            (world_from_femur @ np.append(trial.femoral_head_ct, 1.0))[:3],
            sum(p.seconds for p in bones.pelvis) + bones.femur.seconds,
        )


@dataclasses.dataclass(frozen=True, eq=False)
class _Estimate:
    """The CM estimate in view 0's true C-arm frame, its control points, the estimated frames'
    ``world_est_from_world`` and the bones (None when not registered)."""

    carm_from_cm: np.ndarray
    control_points_deg: np.ndarray
    world_est_from_world: np.ndarray
    bones: _Bones | None


def _view_set_settings(cfg: StudyConfig) -> ViewSetSettings:
    """The studies' registrations: the library's pelvis and femur presets, the CM registration's
    default levels, unchecked (a study measures every registration against the truth)."""
    return ViewSetSettings(
        device=cfg.device,
        pelvis=PELVIS_PRESET,
        pelvis_refine=None,
        cm=fbg_shape_prior(CMRegistrationConfig(), cfg.world.fbg.stated_sigma()),
        cm_checks=None,
    )


def _seeds(bone_seed: int, cm_seed: int = 0) -> ViewSetSeeds:
    return ViewSetSeeds(pelvis=bone_seed, femur=bone_seed + 1, pelvis_refine=bone_seed + 2, cm=cm_seed)


def _simulate(cfg: StudyConfig, rng: np.random.Generator, world_generator: np.random.Generator) -> _Simulated:
    """The phantom, the trial's truth (§III-B), its physics-simulated images in the config's world
    (drawn from ``world_generator``, never ``rng``) and the CM found in each."""
    phantom_seed = 1000 * cfg.seed + int(rng.integers(cfg.n_phantoms))
    protocol_wf = "single-view" if cfg.workflow == "centerline" else cfg.workflow
    w = simulate_world_trial(
        protocol_wf,
        cfg.ct,
        phantom_seed,
        cfg.world,
        image_size=cfg.image_size,
        device=cfg.device,
        rng=rng,
        world_rng=world_generator,
    )
    binning = max(1, round(w.trial.cameras[0].cols / w.images[0].camera.cols))
    views = _detect(w.images, w.cameras, w.oracle_landmarks_px, cfg, binning)
    return _Simulated(w.case_ct, w.trial, w.images, views, w.cameras, w.tip_cm_true)


def _register_multi_view(
    sim: _Simulated, cfg: StudyConfig, rng: np.random.Generator, row: dict[str, Any]
) -> _Estimate:
    """The multi-view workflow (centreline start): bones and CM in the CT frame of the
    pelvis-estimated views (:func:`~fluoronav.registration.view_set.register_view_set`), or the CM
    alone in the true cameras' frame where no bones are registered."""
    bone_seed = int(rng.integers(2**31)) if _with_bones(sim.volume, cfg) else None
    found = [k for k, v in enumerate(sim.views) if v.detection is not None]
    row["views_detected"] = len(found)
    if len(found) < 2:
        raise _TrialFailure(f"the detector found the CM in {len(found)} of {len(sim.views)} views (need 2)")
    cm_seed = int(rng.integers(2**31))
    tr, settings = sim.trial, _view_set_settings(cfg)
    bones: _Bones | None = None
    if bone_seed is not None:
        vs = register_view_set(
            sim.views,
            sim.volume,
            side=tr.side,
            cm_config=tr.cm_config,
            initial_control_points_deg=tr.initial_control_points_deg,
            settings=settings,
            seed=_seeds(bone_seed, cm_seed),
            initial_world_from_pelvis=tr.initial_world_from_patient,
        )
        bones = _Bones.of(ViewSetBones(vs.pelvis, vs.cameras_ct, vs.femur), tr)
        res, init = vs.cm, vs.cm_init
        cams = list(vs.cameras_ct)
    else:
        cams = list(sim.cameras)
        res, init = register_view_set_cm(
            sim.views,
            cams,
            cm_config=tr.cm_config,
            initial_control_points_deg=tr.initial_control_points_deg,
            settings=settings,
            seed=cm_seed,
        )
    assert init is not None  # two views with a CM
    # landmarks that disagreed with the other views were replaced by the triangulated consensus
    row["landmark_outliers"] = int((~init.landmark_inliers).sum())
    # the CM was registered in the CT frame of the pelvis-estimated views
    world_est_from_world = np.linalg.inv(cams[0].camera_from_world) @ sim.images[0].camera.camera_from_world
    row.update(check_values(res, sim.views, sim.trial.initial_control_points_deg, _view_set_settings(cfg).cm))
    return _cm_estimate(row, sim, res, world_est_from_world, bones)


def _cm_estimate(
    row: dict[str, Any],
    sim: _Simulated,
    res: CMRegistrationResult,
    world_est_from_world: np.ndarray,
    bones: _Bones | None,
) -> _Estimate:
    """A CM registration's row entries and its estimate in view 0's true C-arm frame."""
    row["seconds_registration"] = res.seconds
    if not res.success:
        row["status"] = "failed"
        row["reason"] = res.reason
    # C-arm frame of view 0 (true camera), mapping the estimate through the estimated frames
    carm_from_cm_est = (
        sim.images[0].camera.camera_from_world @ np.linalg.inv(world_est_from_world) @ res.world_from_cm[0]
    )
    row["est_control_points_deg"] = np.round(res.control_points_deg, 4).tolist()
    return _Estimate(carm_from_cm_est, res.control_points_deg, world_est_from_world, bones)


def _register_bones(sim: _Simulated, cfg: StudyConfig, seed: int) -> _Bones:
    """Pelvis, then femur (:func:`~fluoronav.registration.view_set.register_view_set_bones`) with
    the CM and its shaft left out of the similarity: in the CT frame of the pelvis-estimated views
    (multi-view), or in the known C-arm view's world frame (one view; multiple-CM: one static view
    whose images show the same anatomy and the CM elsewhere)."""
    views = bone_views(sim.views)
    if cfg.workflow == "multi-cm":
        views = [static_view_composite(views)]
    bones = register_view_set_bones(
        views,
        sim.volume,
        side=sim.trial.side,
        settings=_view_set_settings(cfg),
        seeds=_seeds(seed),
        initial_world_from_pelvis=sim.trial.initial_world_from_patient,
        in_ct_frame=cfg.workflow == "multi-view",
    )
    return _Bones.of(bones, sim.trial)


def _centerline_start(
    sim: _Simulated, cfg: StudyConfig, cams: list[Any], bones: _Bones | None, seed: int, row: dict[str, Any]
) -> Any:
    """The centreline initialisation in the first (AP) view, its depth within reach of the femoral
    head, turned to the best image score about the chord (``cfg.roll_scan``)."""
    tr, view = sim.trial, sim.views[0]
    assert view.detection is not None
    lm, cl = view.detection.landmarks_px, view.detection.centerline_px
    depth_range = None if bones is None else depth_range_about(cams[0], bones.head_world_est)
    init = centerline_initialize(
        cams[0],
        lm,
        cl,
        tr.initial_control_points_deg,
        depth_range_mm=depth_range,
        seed=seed,
        image=sim.images[0].image,
    )
    row["theta_centerline_deg"] = _theta_error_deg(init.camera_from_cm, sim.images, tr)
    if cfg.roll_scan:
        scan = roll_scan_initialization(
            CMView(sim.images[0].image, cams[0], landmarks_px=lm),
            init,
            cl,
            tr.initial_control_points_deg,
            config=fbg_shape_prior(
                CMRegistrationConfig(device=cfg.device, cm_config=tr.cm_config), cfg.world.fbg.stated_sigma()
            ),
        )
        T_scan = cams[0].camera_from_world @ scan.world_from_cm
        # A is the CM origin: its depth is the pose's z; θ in the init's own convention is not
        # defined for a turned alternative (the study measures θ against the truth)
        init = dataclasses.replace(
            init, camera_from_cm=T_scan, depth_mm=float(T_scan[2, 3]), theta_deg=float("nan")
        )
    return init


def _register_one_view(
    sim: _Simulated, cfg: StudyConfig, rng: np.random.Generator, row: dict[str, Any], t0: float
) -> _Estimate:
    """The workflows that start from one view (single-view, multiple-CM, the centreline study) and
    the multi-view workflow from a perturbed truth."""
    tr, images = sim.trial, sim.images
    bones = _register_bones(sim, cfg, int(rng.integers(2**31))) if _with_bones(sim.volume, cfg) else None
    cams, world_est_from_world = list(sim.cameras), np.eye(4)
    if cfg.workflow == "multi-view":  # the CM is registered in the CT frame of the pelvis-estimated views
        cams = list(bones.cameras) if bones is not None else cams
        world_est_from_world = np.linalg.inv(cams[0].camera_from_world) @ images[0].camera.camera_from_world
    row["views_detected"] = sum(v.detection is not None for v in sim.views)
    if sim.views[0].detection is None:
        raise _TrialFailure("detector found no usable CM in image 0 (none, or cut by the border)")
    init_seed = int(rng.integers(2**31))  # drawn either way: the trial's later draws stay put
    init = None
    if cfg.init != "perturbed" or cfg.workflow == "centerline":
        init = _centerline_start(sim, cfg, cams, bones, init_seed, row)
    if cfg.workflow == "centerline":
        assert init is not None
        carm0_true = images[0].camera.camera_from_world @ tr.world_from_cm[0]
        row["depth_mm"] = abs(init.depth_mm - carm0_true[2, 3])
        row["theta_deg"] = _theta_error_deg(init.camera_from_cm, images, tr)
        row["seconds_registration"] = time.perf_counter() - t0
        return _Estimate(init.camera_from_cm, tr.initial_control_points_deg, world_est_from_world, bones)
    lms = [None if v.detection is None else v.detection.landmarks_px for v in sim.views]
    views = [
        CMView(v.image, c, landmarks_px=lm, name=v.name)
        for v, c, lm in zip(sim.views, cams, lms, strict=True)
    ]
    base_from_cm = tr.world_from_cm if cfg.workflow == "multi-cm" else None
    cm_seed = int(rng.integers(2**31))
    if init is None:  # perturbed
        res = register_cm(
            views,
            initial_control_points_deg=tr.initial_control_points_deg,
            initial_world_from_cm=world_est_from_world @ tr.initial_world_from_cm[0],
            base_from_cm=base_from_cm,
            config=fbg_shape_prior(CMRegistrationConfig(device=cfg.device), cfg.world.fbg.stated_sigma()),
            seed=cm_seed,
        )
    else:
        res = register_cm_multistart(
            views,
            cm_start_poses(init, cams[0], tr.initial_control_points_deg, tr.cm_config),
            initial_control_points_deg=tr.initial_control_points_deg,
            base_from_cm=base_from_cm,
            config=fbg_shape_prior(CMRegistrationConfig(device=cfg.device), cfg.world.fbg.stated_sigma()),
            seed=cm_seed,
        )
    return _cm_estimate(row, sim, res, world_est_from_world, bones)


def _record_errors(row: dict[str, Any], sim: _Simulated, est: _Estimate) -> None:
    """The paper's metrics of the estimate against the truth (view 0's true C-arm frame)."""
    tr, cam0 = sim.trial, sim.images[0].camera.camera_from_world
    carm0_true = cam0 @ tr.world_from_cm[0]
    errs = cm_errors(
        carm_from_cm_est=est.carm_from_cm,
        carm_from_cm_true=carm0_true,
        control_points_est_deg=est.control_points_deg,
        control_points_true_deg=tr.control_points_deg,
        config=tr.cm_config,
    )
    row.update(errs)
    # the estimate in the true world frame (view 0's true camera maps it there)
    row["est_world_from_cm"] = np.round(np.linalg.inv(cam0) @ est.carm_from_cm, 5).tolist()
    cps = torch.as_tensor(np.stack([est.control_points_deg, tr.control_points_deg]), dtype=torch.float64)
    tips = CMKinematics(tr.cm_config).tip_cm(cps).numpy()
    tip_est = (est.carm_from_cm @ np.append(tips[0], 1.0))[:3]
    tip_cm_true = tips[1] if sim.tip_cm_true is None else sim.tip_cm_true
    tip_true = (carm0_true @ np.append(tip_cm_true, 1.0))[:3]
    if sim.tip_cm_true is not None:  # the instrument as built, not the model: its own tip
        row["tip_mm"] = point_error_mm(tip_est, tip_true)
    if est.bones is None:
        return
    entry_true_c = (cam0 @ np.append(tr.entry_world, 1.0))[:3]
    entry_est_c = (
        cam0 @ np.linalg.inv(est.world_est_from_world) @ np.append(est.bones.entry_world_est, 1.0)
    )[:3]
    row["entry_mm"] = point_error_mm(entry_est_c, entry_true_c)
    row["relative_mm"] = relative_error_mm(entry_est_c, tip_est, entry_true_c, tip_true)
    row["seconds_bones"] = est.bones.seconds


def cm_start_poses(
    init: Any, camera: Any, control_points_deg: np.ndarray, cm_config: Any, *, n_alternatives: int = 1
) -> list[np.ndarray]:
    """World-frame starts from a centreline initialisation: its best ``n_alternatives`` local minima
    and the mirror of each about the A→B chord (the roll a single centreline hardly fixes).

    One by default: a second centreline minimum, often at another depth, can win the intensity
    screening and end far off (docs/validation.md): one view does not tell depth from tilt, at the
    centreline's nor at the 4× intensity level."""
    alts = init.alternatives if init.alternatives is not None else init.camera_from_cm[None]
    poses = [init.camera_from_cm]
    for T in alts:
        if len(poses) >= n_alternatives:
            break
        if np.linalg.norm(T[:3, 3] - poses[0][:3, 3]) > 1e-6 or not np.allclose(T[:3, :3], poses[0][:3, :3]):
            poses.append(T)
    world = [camera.world_from_camera @ T for T in poses]
    return [w for W in world for w in (W, mirror_about_chord(W, control_points_deg, cm_config))]


def run_trial(trial_id: int, seed: int, *, cfg: StudyConfig) -> dict[str, Any]:
    """One trial → one ``trials.csv`` row (status ``ok`` or ``failed`` with its reason)."""
    t0 = time.perf_counter()
    torch.set_num_threads(1)  # one trial per worker process; numba kernels keep their own threads
    rng = np.random.default_rng(seed)
    row = new_row(trial_id, seed, cfg.workflow)
    try:
        sim = _simulate(cfg, rng, world_rng(seed))
        row["true_control_points_deg"] = np.round(sim.trial.control_points_deg, 4).tolist()
        row["true_world_from_cm"] = np.round(sim.trial.world_from_cm[0], 5).tolist()
        if cfg.workflow == "multi-view" and cfg.init != "perturbed":
            est = _register_multi_view(sim, cfg, rng, row)
        else:
            est = _register_one_view(sim, cfg, rng, row, t0)
        _record_errors(row, sim, est)
    except Exception as exc:  # a failed trial is recorded with its reason, never dropped
        mark_failed(row, exc, trial_id)
    return finish_row(row, t0)


def _columns(workflow: str) -> list[str]:
    return [
        "trial",
        "seed",
        "workflow",
        "status",
        "reason",
        *METRICS[workflow],
        *AXIS_METRICS,
        "seconds",
        "seconds_registration",
        "seconds_bones",
        "views_detected",
        "landmark_outliers",
        "check_edge_ncc",
        "check_landmark_residual_mm",
        "check_fbg_departure_sigmas",
        "true_control_points_deg",
        "est_control_points_deg",
        "true_world_from_cm",
        "est_world_from_cm",
    ]


def run_study(
    cfg: StudyConfig, out: Path, *, scheduler: str | None = None, workers: int | None = None
) -> dict[str, Any]:
    """Run (or resume) a study into ``out``: trials.csv, summary.json, config.json, figures/."""
    if cfg.workflow not in STUDY_WORKFLOWS:
        raise InputError(
            "WORKFLOW", f"unknown workflow {cfg.workflow!r}; use one of {', '.join(STUDY_WORKFLOWS)}"
        )
    out.mkdir(parents=True, exist_ok=True)
    cfg_path = out / "config.json"
    cfg_dict = {**dataclasses.asdict(cfg), "world": cfg.world.to_dict(), "version": __version__}
    if cfg_path.exists():
        old = json.loads(cfg_path.read_text(encoding="utf-8"))
        old.setdefault("world", IDEAL.to_dict())  # a study from before worlds ran in the ideal one
        keep = ["workflow", "seed", "ct", "oracle_landmarks", "image_size", "n_phantoms", "register_bones"]
        keep += ["init", "world"]
        if any(old.get(k) != cfg_dict.get(k) for k in keep):
            raise InputError(cfg_path, "this directory holds a study with other settings; use another --out")
    if cfg.ct != "phantom":
        # fail early, in this process, on a bad CT or one without what the trials simulate
        check_study_ct(resolve_ct(cfg.ct), cfg.ct, TRIAL_CT)
    if not cfg.oracle_landmarks:
        # fail early when no detector model is available; the precision its networks run in
        # (bfloat16 on a CPU with native bfloat16) is part of the record
        cfg_dict["detector_precision"] = _detector(cfg.device).precision
    cfg_path.write_text(json.dumps(cfg_dict, indent=2), encoding="utf-8")
    csv_log = CsvLog(out / "trials.csv", _columns(cfg.workflow))
    task = functools.partial(run_trial, cfg=cfg)
    run_tasks(
        task,
        cfg.trials,
        cfg.seed,
        csv_log,
        scheduler=scheduler,
        workers=workers,
        description=f"study {cfg.workflow}",
    )
    rows = sorted(csv_log.read(), key=lambda r: int(r["trial"]))
    summary = summarize(
        cfg.workflow,
        rows,
        list(METRICS[cfg.workflow]),
        trials=cfg.trials,
        device=cfg.device,
        extra={
            "oracle_landmarks": cfg.oracle_landmarks,
            "seed": cfg.seed,
            "ct": cfg.ct,
            "world": cfg.world.to_dict(),
        },
    )
    write_summary(out / "summary.json", summary)
    study_figures(rows, out / "figures", workflow=cfg.workflow)
    return summary
