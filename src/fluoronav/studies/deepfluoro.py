"""``fluoronav study deepfluoro``: the pelvis registration on the DeepFluoro cadaver images.

Per trial one real image of the user's DeepFluoro file (:mod:`fluoronav.anatomy.deepfluoro`; trial ``i`` takes
image ``i mod n`` of the selected specimens): its collimator border cropped, log-transformed, registered with
the navigation's pelvis preset (:data:`~fluoronav.registration.bone.PELVIS_LINEARIZED_PRESET`) from the ground
truth perturbed as in Gao et al. 2022 (3° about a random axis through the pelvis centre, 10 mm in a random
direction). Frames: the world is the specimen's CT (LPS), the camera the ground-truth one, so the truth is
``world_from_patient`` = identity. The metrics (:func:`pelvis_errors`), the check (:func:`pelvis_edge_ncc`,
passed at :attr:`DeepFluoroStudyConfig.min_edge_ncc`), the frames' check ``gt_landmark_residual_px`` and the
published figures on the same data (:data:`ANCHORS`): docs/real-data.md.
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
from fluoronav.anatomy.deepfluoro import DeepFluoroFile
from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError
from fluoronav.geometry import se3
from fluoronav.geometry.camera import Camera
from fluoronav.registration.bone import (
    PELVIS_CMAES_PRESET,
    PELVIS_LINEARIZED_PRESET,
    BoneRegistrationConfig,
    BoneView,
    bone_excess_mu,
    pelvis_config,
    register_pelvis,
)
from fluoronav.registration.similarity import edge_ncc
from fluoronav.rendering.ct import render_line_integrals
from fluoronav.runner import CsvLog, finish_row, mark_failed, new_row, run_tasks
from fluoronav.simulation.protocol import perturb_about
from fluoronav.studies.deepfluoro_report import ANCHORS, WORKFLOW
from fluoronav.studies.summary import summarize, write_summary

log = logging.getLogger(__name__)

__all__ = [
    "ANCHORS",
    "METRICS",
    "MTRE_THRESHOLDS_MM",
    "PRESETS",
    "WORKFLOW",
    "DeepFluoroStudyConfig",
    "deepfluoro_summary",
    "pelvis_edge_ncc",
    "pelvis_errors",
    "run_deepfluoro_study",
    "run_deepfluoro_trial",
]

METRICS = ("rotation_deg", "translation_mm", "mtre_mm", "reprojection_mm")
#: mTRE thresholds (mm) of the summary's success fractions; 1 mm: "sub-millimetre", as DiffPose and
#: xvr state their accuracy
MTRE_THRESHOLDS_MM = (1.0, 2.0, 5.0, 10.0)
#: the pelvis presets the study can run (``navigation``: the navigation pipeline's)
PRESETS: dict[str, BoneRegistrationConfig] = {
    "navigation": PELVIS_LINEARIZED_PRESET,
    "cmaes": PELVIS_CMAES_PRESET,
    "authors": pelvis_config(authors=True),
}
_COLUMNS = [
    "trial",
    "seed",
    "workflow",
    "status",
    "reason",
    "specimen",
    "projection",
    "start_index",
    "rot_180_for_up",
    *METRICS,
    "start_rotation_deg",
    "start_translation_mm",
    "start_mtre_mm",
    "edge_ncc",
    "checks_passed",
    "gt_landmark_residual_px",
    "cost",
    "converged",
    "seconds",
    "seconds_registration",
    "est_world_from_patient",
]


@dataclasses.dataclass(frozen=True)
class DeepFluoroStudyConfig:
    """Settings of a DeepFluoro study run (recorded in ``DIR/config.json``).

    Attributes:
        data: the DeepFluoro HDF5 file.
        seed: run seed (each trial's seed derives from it).
        trials: number of trials; None: one per selected image.
        specimen: one specimen (ID or the paper's number 1–6); None: all.
        start_rotation_deg, start_translation_mm: the start's perturbation (exact sizes, random
            directions).
        preset: a key of :data:`PRESETS`.
        device: torch device.
        xreg_texture_correction: shift the ground truth as xReg's samples do
            (:class:`~fluoronav.anatomy.deepfluoro.DeepFluoroFile`).
        border_px: collimator border cropped per side; None: 50 px of 1536, scaled.
        min_edge_ncc: the check's threshold on :func:`pelvis_edge_ncc`, between its values on the
            phantom at the truth (near 1) and at the start's error (near 0); not tuned on real images.
    """

    data: str
    seed: int
    trials: int | None = None
    specimen: str | None = None
    start_rotation_deg: float = 3.0
    start_translation_mm: float = 10.0
    preset: str = "navigation"
    device: str = "cpu"
    xreg_texture_correction: bool = False
    border_px: int | None = None
    min_edge_ncc: float = 0.5


# ----- per-process caches (each Dask worker opens the file itself) ---------------------------------
@functools.lru_cache(maxsize=2)
def _file(path: str, correction: bool) -> DeepFluoroFile:
    return DeepFluoroFile(path, xreg_texture_correction=correction)


@functools.lru_cache(maxsize=2)
def _volume(path: str, correction: bool, specimen: str) -> Volume:
    return _file(path, correction).volume(specimen)


def _images(cfg: DeepFluoroStudyConfig) -> list[tuple[str, int]]:
    f = _file(cfg.data, cfg.xreg_texture_correction)
    specimens = [f.resolve_specimen(cfg.specimen)] if cfg.specimen else list(f.specimens)
    images = [(s, i) for s in specimens for i in f.projection_indices(s)]
    if not images:
        raise InputError(cfg.data, "no projections in the selected specimens")
    return images


# ----- metrics and the check ------------------------------------------------------------------------
def pelvis_errors(
    world_from_patient: np.ndarray,
    landmarks_world: dict[str, np.ndarray],
    camera: Camera,
    center_world: np.ndarray,
) -> dict[str, float]:
    """Errors of a pelvis estimate whose truth is the identity (world = the CT).

    Args:
        world_from_patient: (4, 4) the estimate.
        landmarks_world: the 3D landmarks (mm).
        camera: the ground-truth camera (its ``pixel_spacing_mm``: the detector pitch; None: mm
            errors at the detector are NaN).
        center_world: (3,) the pelvis centre (mm).

    Returns:
        ``rotation_deg``, ``translation_mm`` (at ``center_world``), ``mtre_mm`` (mean 3D landmark
        error), ``reprojection_mm`` (mean 2D landmark error at the detector).
    """
    W = np.asarray(world_from_patient, np.float64)
    pts = np.stack(list(landmarks_world.values()))
    moved = se3.apply(W, pts)
    d_px = np.linalg.norm(camera.project(moved) - camera.project(pts), axis=1)
    pitch = camera.pixel_spacing_mm
    c = np.asarray(center_world, np.float64)
    return {
        "rotation_deg": float(se3.rotation_angle_deg(W[:3, :3])),
        "translation_mm": float(np.linalg.norm(se3.apply(W, c) - c)),
        "mtre_mm": float(np.linalg.norm(moved - pts, axis=1).mean()),
        "reprojection_mm": float(d_px.mean() * pitch) if pitch else float("nan"),
    }


def pelvis_edge_ncc(
    image: np.ndarray, camera: Camera, volume: Volume, world_from_patient: np.ndarray, *, size_px: int = 256
) -> float:
    """Gradient NCC (−1 … 1) of ``image`` and the pelvis DRR at ``world_from_patient`` on the DRR's
    outline, both binned to about ``size_px`` (:func:`~fluoronav.registration.similarity.edge_ncc`)."""
    f = max(1, camera.cols // size_px)
    small = camera.downsample(f)
    img = np.asarray(image, np.float64)[: small.rows * f, : small.cols * f]
    img = img.reshape(small.rows, f, small.cols, f).mean(axis=(1, 3))
    mu, w_idx = bone_excess_mu(volume, ["pelvis"])
    T = (small.camera_from_world @ np.asarray(world_from_patient, np.float64))[None]
    drr = render_line_integrals(torch.from_numpy(mu), w_idx, small.K[None], T, small.rows, small.cols)[0]
    return float(edge_ncc(img, drr.cpu().numpy().astype(np.float64)))


# ----- one trial ------------------------------------------------------------------------------------
def run_deepfluoro_trial(
    trial_id: int, seed: int, *, cfg: DeepFluoroStudyConfig, images: list[tuple[str, int]]
) -> dict[str, Any]:
    """Register the pelvis in image ``trial_id mod len(images)`` from a seeded perturbed start."""
    t0 = time.perf_counter()
    specimen, index = images[trial_id % len(images)]
    row = new_row(trial_id, seed, WORKFLOW)
    row.update(specimen=specimen, projection=index, start_index=trial_id // len(images))
    try:
        f = _file(cfg.data, cfg.xreg_texture_correction)
        volume = _volume(cfg.data, cfg.xreg_texture_correction, specimen)
        proj = f.projection(specimen, index)
        marks = f.landmarks_world(specimen)
        row["rot_180_for_up"] = proj.rot_180_for_up
        row["gt_landmark_residual_px"] = proj.landmark_residual_px(marks)
        image, camera = proj.cropped_line_integral(cfg.border_px)
        center = np.asarray(volume.landmarks_world.get("pelvis_center", volume.center_world), np.float64)
        rng = np.random.default_rng(seed)
        start = perturb_about(
            np.eye(4),
            center,
            rng,
            rotation_deg=cfg.start_rotation_deg,
            translation_mm=cfg.start_translation_mm,
        )
        for k, v in pelvis_errors(start, marks, camera, center).items():
            if k != "reprojection_mm":
                row[f"start_{k}"] = v
        config = dataclasses.replace(PRESETS[cfg.preset], device=cfg.device)
        res = register_pelvis(
            [BoneView(image, camera)],
            volume,
            initial_world_from_patient=start,
            config=config,
            seed=int(rng.integers(1, 2**31 - 1)),
        )
        row.update(pelvis_errors(res.world_from_bone, marks, camera, center))
        row["edge_ncc"] = pelvis_edge_ncc(image, camera, volume, res.world_from_bone)
        row["checks_passed"] = bool(res.converged) and row["edge_ncc"] >= cfg.min_edge_ncc
        row.update(
            cost=float(res.cost),
            converged=bool(res.converged),
            seconds_registration=float(res.seconds),
            est_world_from_patient=np.round(res.world_from_bone, 9).tolist(),
        )
    except Exception as exc:  # a failed image is recorded with its reason, never dropped
        mark_failed(row, exc, trial_id)
    return finish_row(row, t0)


# ----- the run --------------------------------------------------------------------------------------
def _fraction(flags: list[bool]) -> float | None:
    return float(np.mean(flags)) if flags else None


def _value(row: dict[str, Any], key: str) -> float:
    try:
        return float(row.get(key))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return float("nan")


def deepfluoro_summary(
    rows: list[dict[str, Any]], cfg: DeepFluoroStudyConfig, *, trials: int
) -> dict[str, Any]:
    """``summary.json``: the study summary plus ``within_1deg`` and ``within_mtre_mm`` (fractions of
    the completed trials; a failed trial is not within), the checks' outcome, the frame check and
    :data:`ANCHORS`."""
    rot = [_value(r, "rotation_deg") for r in rows]
    mtre = [_value(r, "mtre_mm") for r in rows]
    passed = [str(r.get("checks_passed")) == "True" for r in rows]
    gt_px = [v for v in (_value(r, "gt_landmark_residual_px") for r in rows) if np.isfinite(v)]
    extra = {
        "within_1deg": _fraction([v < 1.0 for v in rot]),
        "within_mtre_mm": {f"{t:g}": _fraction([v < t for v in mtre]) for t in MTRE_THRESHOLDS_MM},
        "checks": {
            "passed": int(sum(passed)),
            "passed_within_1deg": _fraction([v < 1.0 for v, p in zip(rot, passed, strict=True) if p]),
            "passed_but_mtre_over_10mm": int(
                sum(p and not v < 10.0 for v, p in zip(mtre, passed, strict=True))
            ),
            "min_edge_ncc": cfg.min_edge_ncc,
        },
        "gt_landmark_residual_px": {"median": float(np.median(gt_px)), "max": float(np.max(gt_px))}
        if gt_px
        else None,
        "protocol": f"start: ground truth + {cfg.start_rotation_deg:g}° about a random axis through the "
        f"pelvis centre and {cfg.start_translation_mm:g} mm in a random direction (Gao et al., TBME "
        f"2022); pelvis preset {cfg.preset!r}",
        "data": str(cfg.data),
        "specimen": cfg.specimen,
        "seed": cfg.seed,
        "xreg_texture_correction": cfg.xreg_texture_correction,
        "anchors": ANCHORS,
    }
    return summarize(WORKFLOW, rows, list(METRICS), trials=trials, device=cfg.device, extra=extra)


def run_deepfluoro_study(
    cfg: DeepFluoroStudyConfig, out: Path, *, scheduler: str | None = None, workers: int | None = None
) -> dict[str, Any]:
    """Run (or resume) the study into ``out``: trials.csv, summary.json, config.json, figures/."""
    if cfg.preset not in PRESETS:
        raise InputError("--preset", f"unknown preset {cfg.preset!r}; use one of {', '.join(PRESETS)}")
    images = _images(cfg)
    trials = cfg.trials if cfg.trials is not None else len(images)
    out.mkdir(parents=True, exist_ok=True)
    cfg_path = out / "config.json"
    cfg_dict = {**dataclasses.asdict(cfg), "trials": trials, "workflow": WORKFLOW, "version": __version__}
    if cfg_path.exists():
        old = json.loads(cfg_path.read_text(encoding="utf-8"))
        keep = ["seed", "specimen", "start_rotation_deg", "start_translation_mm", "preset"]
        keep += ["xreg_texture_correction", "border_px", "min_edge_ncc"]
        if old.get("workflow") != WORKFLOW or any(old.get(k) != cfg_dict.get(k) for k in keep):
            raise InputError(cfg_path, "this directory holds a study with other settings; use another --out")
    cfg_path.write_text(json.dumps(cfg_dict, indent=2), encoding="utf-8")
    csv_log = CsvLog(out / "trials.csv", _COLUMNS)
    task = functools.partial(run_deepfluoro_trial, cfg=cfg, images=images)
    run_tasks(
        task, trials, cfg.seed, csv_log, scheduler=scheduler, workers=workers, description="study deepfluoro"
    )
    rows = sorted(csv_log.read(), key=lambda r: int(r["trial"]))
    summary = deepfluoro_summary(rows, cfg, trials=trials)
    write_summary(out / "summary.json", summary)
    _figure(rows, out / "figures")
    return summary


def _figure(rows: list[dict[str, Any]], out_dir: Path) -> None:
    """``figures/deepfluoro_errors.png``: rotation and mTRE per trial against the thresholds."""
    import matplotlib  # heavy: matplotlib, for the figure only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after use("Agg")

    from fluoronav.htmlpage import figure_png

    rot = np.array([_value(r, "rotation_deg") for r in rows])
    mtre = np.array([_value(r, "mtre_mm") for r in rows])
    ok = np.isfinite(rot) & np.isfinite(mtre)
    if not ok.any():
        return
    out_dir.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for ax, v, t, label in (
        (axes[0], rot[ok], 1.0, "rotation error (°)"),
        (axes[1], mtre[ok], 1.0, "mTRE (mm)"),
    ):
        ax.hist(np.clip(v, 1e-3, None), bins=np.logspace(-3, 2, 41))
        ax.set_xscale("log")
        ax.axvline(t, color="k", lw=1, ls="--")
        ax.set_xlabel(label)
    axes[0].set_ylabel("images")
    fig.suptitle(f"DeepFluoro pelvis registration ({int(ok.sum())} trials)", fontsize=10)
    (out_dir / "deepfluoro_errors.png").write_bytes(figure_png(fig))
