"""``fluoronav deepfluoro``: one DeepFluoro image registered (pelvis, then both femurs), with its files.

The pelvis starts as in ``study deepfluoro`` (:mod:`fluoronav.studies.deepfluoro`); each femur with
a valid ground truth (``*-femur-good-fov``) is registered after it from the pelvis's estimate
(:func:`~fluoronav.registration.bone.register_femur`, one-view preset). Writes
``registration.json``, ``overlay.png`` and ``slicer/``. Frames: the registration runs with the
ground-truth camera and estimates ``world_from_patient`` (world = the CT). In ``slicer/`` the CT
stays where it is (LPS) and the X-ray is placed by the registration, ``ct_from_camera =
inv(camera_from_ct · world_from_patient)``, on the detector plane at the source-to-detector
distance as a one-slice volume; femurs by ``ct_from_femur = inv(world_from_patient) ·
world_from_femur``. The ground truth comes along (``ct_from_camera_truth.h5``, ``source_truth``).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk  # noqa: N813
import torch

from fluoronav.anatomy.deepfluoro import DeepFluoroFile
from fluoronav.anatomy.markups import write_markups
from fluoronav.anatomy.volume import Volume
from fluoronav.geometry import se3
from fluoronav.geometry.camera import Camera
from fluoronav.navigation.outputs.slicer import femur_surface, write_model, write_transform
from fluoronav.registration.bone import (
    BoneView,
    bone_excess_mu,
    femur_config,
    register_femur,
    register_pelvis,
)
from fluoronav.rendering.ct import render_line_integrals
from fluoronav.simulation.protocol import perturb_about
from fluoronav.studies.deepfluoro import PRESETS, pelvis_edge_ncc, pelvis_errors

log = logging.getLogger(__name__)

__all__ = ["ProjectionRegistration", "register_projection", "write_projection_outputs"]

#: the X-ray written for Slicer is binned to at most this side (pixels)
SLICER_IMAGE_PX = 768


@dataclass(frozen=True, eq=False)
class ProjectionRegistration:
    """One image registered.

    Attributes:
        specimen, index: the image.
        image, camera: the cropped line integral and its ground-truth camera (world = the CT).
        volume: the specimen's CT; landmarks_world: its 3D landmarks (file names).
        landmarks_px: the file's 2D landmarks in ``image``'s pixels.
        start, world_from_patient: (4, 4) the pelvis's start and estimate (truth: identity).
        world_from_femur: side → (4, 4) estimate; femur_truth: side → (4, 4) ground truth.
        errors: pelvis metrics (:func:`~fluoronav.studies.deepfluoro.pelvis_errors`), ``edge_ncc``,
            and per femur ``femur_<side>_rotation_deg`` / ``femur_<side>_head_mm``.
        seconds: stage → seconds.
    """

    specimen: str
    index: int
    image: np.ndarray
    camera: Camera
    volume: Volume
    landmarks_world: dict[str, np.ndarray]
    landmarks_px: dict[str, np.ndarray]
    start: np.ndarray
    world_from_patient: np.ndarray
    world_from_femur: dict[str, np.ndarray] = field(default_factory=dict)
    femur_truth: dict[str, np.ndarray] = field(default_factory=dict)
    errors: dict[str, float] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)


def register_projection(
    path: str | Path,
    specimen: str,
    index: int,
    *,
    seed: int,
    device: str = "cpu",
    start_rotation_deg: float = 3.0,
    start_translation_mm: float = 10.0,
    femurs: bool = True,
    xreg_texture_correction: bool = False,
) -> ProjectionRegistration:
    """Register the pelvis (the navigation's preset) and then each femur with a valid ground truth."""
    with DeepFluoroFile(path, xreg_texture_correction=xreg_texture_correction) as f:
        sid = f.resolve_specimen(specimen)
        proj = f.projection(sid, index)
        volume = f.volume(sid)
        marks = f.landmarks_world(sid)
    image, camera = proj.cropped_line_integral()
    b = (proj.camera.rows - camera.rows) // 2
    lm_px = {n: p - b for n, p in proj.landmarks_px.items()}
    center = np.asarray(volume.landmarks_world.get("pelvis_center", volume.center_world), np.float64)
    rng = np.random.default_rng(seed)
    start = perturb_about(
        np.eye(4), center, rng, rotation_deg=start_rotation_deg, translation_mm=start_translation_mm
    )
    views = [BoneView(image, camera)]
    t0 = time.perf_counter()
    pelvis = register_pelvis(
        views,
        volume,
        initial_world_from_patient=start,
        config=replace(PRESETS["navigation"], device=device),
        seed=int(rng.integers(1, 2**31 - 1)),
    )
    seconds = {"pelvis": time.perf_counter() - t0}
    errors = pelvis_errors(pelvis.world_from_bone, marks, camera, center)
    errors["edge_ncc"] = pelvis_edge_ncc(image, camera, volume, pelvis.world_from_bone)
    est: dict[str, np.ndarray] = {}
    sides = [s for s, ok in proj.femur_good_fov.items() if ok] if femurs else []
    for side in sides:
        if (
            volume.label_value(f"femur_{side}") is None
            or f"femoral_head_{side}" not in volume.landmarks_world
        ):
            continue
        t0 = time.perf_counter()
        res = register_femur(
            views,
            volume,
            side=side,
            world_from_patient=pelvis.world_from_bone,
            config=replace(femur_config(views=1), device=device),
            seed=int(rng.integers(1, 2**31 - 1)),
        )
        seconds[f"femur_{side}"] = time.perf_counter() - t0
        est[side] = res.world_from_bone
        truth = proj.world_from_femur[side]
        head = np.asarray(volume.landmarks_world[f"femoral_head_{side}"], np.float64)
        errors[f"femur_{side}_rotation_deg"] = float(
            se3.rotation_angle_deg(res.world_from_bone[:3, :3] @ truth[:3, :3].T)
        )
        errors[f"femur_{side}_head_mm"] = float(
            np.linalg.norm(se3.apply(res.world_from_bone, head) - se3.apply(truth, head))
        )
    return ProjectionRegistration(
        specimen=sid,
        index=int(index),
        image=image,
        camera=camera,
        volume=volume,
        landmarks_world=marks,
        landmarks_px=lm_px,
        start=start,
        world_from_patient=pelvis.world_from_bone,
        world_from_femur=est,
        femur_truth={s: proj.world_from_femur[s] for s in est},
        errors=errors,
        seconds=seconds,
    )


# ----- outputs --------------------------------------------------------------------------------------
def _binned(image: np.ndarray, camera: Camera, max_px: int) -> tuple[np.ndarray, Camera]:
    f = max(1, -(-max(camera.rows, camera.cols) // max_px))
    small = camera.downsample(f)
    img = np.asarray(image, np.float64)[: small.rows * f, : small.cols * f]
    return img.reshape(small.rows, f, small.cols, f).mean(axis=(1, 3)).astype(np.float32), small


def detector_image(image: np.ndarray, camera: Camera) -> sitk.Image:
    """The X-ray as a one-slice SimpleITK volume on the detector plane (world frame, LPS, mm).

    Pixel (u, v) lies at ``world_from_camera · ((u − cx)·s, (v − cy)·s, sdd)`` with ``s`` the pixel
    pitch and ``sdd = fx · s``; the volume's axes are the camera's x, y and z.
    """
    if camera.pixel_spacing_mm is None:
        raise ValueError("the camera needs its pixel pitch to place the image")
    s = float(camera.pixel_spacing_mm)
    sdd = float(camera.K[0, 0]) * s
    W = camera.world_from_camera
    corner = np.array([-camera.K[0, 2] * s, -camera.K[1, 2] * s, sdd])
    out = sitk.GetImageFromArray(np.asarray(image, np.float32)[None])
    out.SetSpacing((s, s * float(camera.K[0, 0] / camera.K[1, 1]), 1.0))
    out.SetOrigin(tuple(float(x) for x in se3.apply(W, corner)))
    out.SetDirection(tuple(float(x) for x in W[:3, :3].reshape(-1)))
    return out


def _edges(drr: np.ndarray) -> np.ndarray:
    from skimage.feature import canny  # heavy: scikit-image, for the overlay only

    top = float(np.ptp(drr))
    return canny(drr / top, sigma=1.0, low_threshold=0.02, high_threshold=0.04) if top > 0 else drr > 0


def _overlay_png(reg: ProjectionRegistration, path: Path) -> Path:
    """The image with the pelvis DRR's outline at the estimate (green) and the truth (red), the
    file's 2D landmarks (yellow +) and the 3D landmarks projected at the estimate (cyan o)."""
    import matplotlib  # heavy: matplotlib, for the figure only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after use("Agg")

    from fluoronav.htmlpage import figure_png

    img, small = _binned(reg.image, reg.camera, 512)
    mu, w_idx = bone_excess_mu(reg.volume, ["pelvis"])
    T = np.stack([small.camera_from_world @ reg.world_from_patient, small.camera_from_world])
    drr = render_line_integrals(
        torch.from_numpy(mu), w_idx, small.K[None].repeat(2, 0), T, small.rows, small.cols
    )
    lo, hi = np.percentile(img, [1, 99.5])
    rgb = np.repeat(np.clip((img - lo) / max(hi - lo, 1e-9), 0, 1)[..., None], 3, axis=-1)
    rgb[_edges(drr[1].cpu().numpy())] = (1.0, 0.2, 0.2)
    rgb[_edges(drr[0].cpu().numpy())] = (0.1, 1.0, 0.1)
    f = reg.camera.cols / small.cols
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.imshow(rgb, interpolation="nearest")
    gt = np.stack(list(reg.landmarks_px.values())) if reg.landmarks_px else np.zeros((0, 2))
    est = small.project(se3.apply(reg.world_from_patient, np.stack(list(reg.landmarks_world.values()))))
    ax.plot((gt[:, 0] + 0.5) / f - 0.5, (gt[:, 1] + 0.5) / f - 0.5, "y+", ms=9, mew=1.5)
    ax.plot(est[:, 0], est[:, 1], "o", mfc="none", mec="c", ms=8)
    ax.set_xlim(-0.5, small.cols - 0.5)
    ax.set_ylim(small.rows - 0.5, -0.5)
    ax.set_xticks([])
    ax.set_yticks([])
    e = reg.errors
    ax.set_title(
        f"{reg.specimen} / {reg.index:03d}: rotation {e['rotation_deg']:.2f}°, mTRE {e['mtre_mm']:.2f} mm "
        "(green: registered pelvis, red: truth)",
        fontsize=9,
    )
    path.write_bytes(figure_png(fig))
    return path


_README = """\
3D Slicer files of a fluoronav registration of one DeepFluoro image
====================================================================

Everything is in the specimen's CT frame (LPS, mm). Load the CT (e.g. exported from the DeepFluoro
file) and then these files into Slicer:

  xray.nrrd                the X-ray (line integral, bone bright) on the detector plane, placed by
                           the registration: seen from the source, the pelvis model covers the pelvis
  pelvis.vtk               the pelvis surface (the CT's own pose)
{femur_lines}  landmarks.mrk.json       the 14 3D landmarks
  source.mrk.json          the X-ray source: registered ("source") and ground truth ("source_truth")
  ct_from_camera.h5        transform node: the registered C-arm camera frame -> CT
  ct_from_camera_truth.h5  transform node: the ground-truth camera frame -> CT

Transform files are ITK files in LPS storing the resampling ("from parent") direction, as Slicer
reads them. Models are VTK polydata with SPACE=LPS; markups are Slicer .mrk.json files in LPS.
"""


def _write_slicer(reg: ProjectionRegistration, out: Path) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    cam_est = reg.camera.with_pose(reg.camera.camera_from_world @ reg.world_from_patient)
    img, small = _binned(reg.image, cam_est, SLICER_IMAGE_PX)
    sitk.WriteImage(detector_image(img, small), str(out / "xray.nrrd"))
    written = [out / "xray.nrrd"]
    written.append(
        write_model(out / "pelvis.vtk", *femur_surface(reg.volume, "pelvis"), description="pelvis")
    )
    femur_lines = ""
    for side, W in reg.world_from_femur.items():
        ct_from_femur = np.linalg.inv(reg.world_from_patient) @ W
        v, fc = femur_surface(reg.volume, f"femur_{side}")
        written.append(
            write_model(out / f"femur_{side}.vtk", se3.apply(ct_from_femur, v), fc, description=side)
        )
        written.append(write_transform(out / f"ct_from_femur_{side}.h5", ct_from_femur))
        name = f"femur_{side}.vtk"
        femur_lines += f"  {name:<23}  the registered {side} femur (also ct_from_femur_{side}.h5)\n"
    written.append(write_transform(out / "ct_from_camera.h5", cam_est.world_from_camera))
    written.append(write_transform(out / "ct_from_camera_truth.h5", reg.camera.world_from_camera))
    written.append(write_markups(out / "landmarks.mrk.json", reg.landmarks_world, name="landmarks"))
    sources = {"source": cam_est.source_world, "source_truth": reg.camera.source_world}
    written.append(write_markups(out / "source.mrk.json", sources, name="source", color=(0.2, 0.9, 1.0)))
    (out / "README.txt").write_text(_README.format(femur_lines=femur_lines), encoding="utf-8")
    written.append(out / "README.txt")
    return written


def _json(reg: ProjectionRegistration) -> dict[str, Any]:
    return {
        "specimen": reg.specimen,
        "projection": reg.index,
        "errors": reg.errors,
        "seconds": reg.seconds,
        "frames": "world = the specimen's CT (LPS, mm); the truth is world_from_patient = identity",
        "start_world_from_patient": reg.start.tolist(),
        "world_from_patient": reg.world_from_patient.tolist(),
        "world_from_femur": {s: W.tolist() for s, W in reg.world_from_femur.items()},
        "world_from_femur_truth": {s: W.tolist() for s, W in reg.femur_truth.items()},
        "camera_truth": reg.camera.to_dict(),
    }


def write_projection_outputs(reg: ProjectionRegistration, out: Path) -> list[Path]:
    """``registration.json`` (errors, poses, seconds), ``overlay.png`` and ``slicer/``."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / "registration.json"
    path.write_text(json.dumps(_json(reg), indent=1, allow_nan=False) + "\n", encoding="utf-8")
    written = [path, _overlay_png(reg, out / "overlay.png")]
    return written + _write_slicer(reg, out / "slicer")
