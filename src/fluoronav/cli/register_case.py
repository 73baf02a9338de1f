"""Case files of ``fluoronav register`` (JSON; documented in docs/registration.md).

:func:`load_case` reads one into a :class:`~fluoronav.registration.cm.case.CMCase`, raising
:class:`~fluoronav.errors.InputError` naming the file for anything malformed; views without
landmarks get the shipped detector's (:func:`detect_landmarks`, also used by ``fluoronav
calibrate``). :func:`write_example_case` writes a physics-simulated case
(:func:`~fluoronav.simulation.cm_case.simulate_cm_case`) in this format.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from fluoronav.detection.detector import Detector, load_image
from fluoronav.errors import InputError, read_json_object
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.dicom import camera_from_dicom
from fluoronav.registration.centerline.single import centerline_initialize
from fluoronav.registration.cm.case import CMCase
from fluoronav.registration.cm.config import CM_COARSE_LEVEL, CMRegistrationConfig, default_cm_levels
from fluoronav.registration.cm.roll_scan import roll_scan_initialization
from fluoronav.registration.cm.views import CMView
from fluoronav.simulation.cm_case import CM_WORKFLOWS, CMWorkflow, simulate_cm_case

__all__ = ["CONFIG_KEYS", "detect_landmarks", "load_case", "write_example_case"]

#: the keys of a case file's ``config`` object
CONFIG_KEYS = frozenset(
    {"popsize", "refine", "landmark_sigma_full_px", "roi_size_full_px", "use_background", "cm_mu_per_mm"}
)


def _matrix(value: Any, shape: tuple[int, ...], what: str, source: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(source, f"{what} is not a numeric array") from None
    if arr.shape != shape or not np.all(np.isfinite(arr) | (what.startswith("landmarks") & np.isnan(arr))):
        raise InputError(source, f"{what} must be a finite array of shape {shape}, got {arr.shape}")
    return arr


def _config_from(d: Any, source: str) -> CMRegistrationConfig:
    if d is None:
        return CMRegistrationConfig()
    if not isinstance(d, dict):
        raise InputError(source, "'config' must be an object")
    unknown = set(d) - CONFIG_KEYS
    if unknown:
        raise InputError(source, f"unknown config keys {sorted(unknown)}; known: {sorted(CONFIG_KEYS)}")
    try:
        levels = default_cm_levels(
            popsize=int(d.get("popsize", CM_COARSE_LEVEL.popsize)), refine=bool(d.get("refine", True))
        )
        sigma = d.get("landmark_sigma_full_px", CMRegistrationConfig.landmark_sigma_full_px)
        return CMRegistrationConfig(
            levels=levels,
            roi_size_full_px=int(d.get("roi_size_full_px", CMRegistrationConfig.roi_size_full_px)),
            landmark_sigma_full_px=None if sigma is None else float(sigma),
            use_background=bool(d.get("use_background", CMRegistrationConfig.use_background)),
            cm_mu_per_mm=float(d.get("cm_mu_per_mm", CMRegistrationConfig.cm_mu_per_mm)),
        )
    except (TypeError, ValueError) as exc:
        raise InputError(source, f"bad config value ({exc})") from None


def detect_landmarks(image: np.ndarray, source: str, pixel_spacing_mm: float | None = None) -> np.ndarray:
    """The shipped detector's landmarks A, B (2, 2) in a view that a case file gives none for.

    Raises:
        InputError: naming ``source``, when the detector is unavailable or its detection unusable.
    """
    try:
        det = Detector.load().detect(image, pixel_spacing_mm=pixel_spacing_mm)
    except InputError as exc:
        raise InputError(
            source, f"no landmarks given and the detector is unavailable ({exc.problem})"
        ) from None
    if not det.usable:
        why = det.unusable_reason
        raise InputError(source, f"no landmarks given and the detector: {why}; add 'landmarks_px'")
    return np.asarray(det.landmarks_px, dtype=np.float64)


def _view(v: Any, k: int, root: Path, src: str) -> CMView:
    """``views[k]`` of a case file (paths relative to ``root``)."""
    if not isinstance(v, dict) or "image" not in v or "camera" not in v:
        raise InputError(src, f"views[{k}] must be an object with 'image' and 'camera'")
    if not isinstance(v["image"], str) or not v["image"]:
        raise InputError(src, f"views[{k}].image must be a file name")
    cam_entry = v["camera"]
    if not isinstance(cam_entry, (str, dict)) or cam_entry == "":
        raise InputError(src, f"views[{k}].camera must be a camera file name, 'dicom' or a camera object")
    img, _spacing = load_image(root / v["image"])
    if isinstance(cam_entry, dict):
        camera = Camera.from_dict(cam_entry, source=f"{src} views[{k}].camera")
    elif cam_entry == "dicom":  # the geometry tags of the (DICOM) image itself
        camera = camera_from_dicom(root / v["image"])
    else:
        camera = Camera.load(root / str(cam_entry))
    if img.shape != (camera.rows, camera.cols):
        raise InputError(
            src, f"views[{k}]: image {img.shape} does not match camera {camera.rows}x{camera.cols}"
        )
    lm = (
        _matrix(v["landmarks_px"], (2, 2), f"landmarks_px of views[{k}]", src)
        if v.get("landmarks_px") is not None
        else detect_landmarks(img, src, camera.pixel_spacing_mm)
    )
    binning = v.get("binning")
    if binning is not None and (not isinstance(binning, int) or binning < 1):
        raise InputError(src, f"views[{k}].binning must be a positive integer")
    bg = None
    if v.get("background") is not None:
        bg, _ = load_image(root / str(v["background"]))
        if bg.shape != img.shape:
            raise InputError(src, f"views[{k}]: background shape {bg.shape} differs from the image's")
    return CMView(
        image=img,
        camera=camera,
        landmarks_px=lm,
        background=bg,
        binning=binning,
        name=str(v.get("name", f"view{k}")),
    )


def _views(d: dict[str, Any], workflow: str, root: Path, src: str) -> list[CMView]:
    """The case file's ``views``, their names unique."""
    vlist = d.get("views")
    if not isinstance(vlist, list) or not vlist:
        raise InputError(src, "'views' must be a non-empty list")
    if workflow == "single-view" and len(vlist) != 1:
        raise InputError(src, f"single-view needs exactly one view, got {len(vlist)}")
    views = [_view(v, k, root, src) for k, v in enumerate(vlist)]
    names = [v.name for v in views]
    if len(set(names)) != len(names):
        raise InputError(src, f"view names must be unique, got {names}")
    return views


def _base_from_cm(d: dict[str, Any], n_views: int, src: str) -> np.ndarray:
    """Multiple-CM: the (M, 4, 4) relative poses robot FK × hand-eye."""
    mc = d.get("multi_cm")
    if not isinstance(mc, dict) or "base_from_ee" not in mc or "ee_from_cm" not in mc:
        raise InputError(src, "multi-cm needs 'multi_cm': {'base_from_ee': [M 4x4], 'ee_from_cm': 4x4}")
    bfe = _matrix(mc["base_from_ee"], (n_views, 4, 4), "multi_cm.base_from_ee (one per view)", src)
    efc = _matrix(mc["ee_from_cm"], (4, 4), "multi_cm.ee_from_cm", src)
    return bfe @ efc


def _ground_truth(gt: Any, n_poses: int, src: str) -> tuple[np.ndarray, np.ndarray]:
    """``ground_truth`` → (world_from_cm (M, 4, 4), control_points_deg (5,))."""
    if not isinstance(gt, dict) or "world_from_cm" not in gt or "control_points_deg" not in gt:
        raise InputError(src, "'ground_truth' needs 'world_from_cm' and 'control_points_deg'")
    W = np.asarray(gt["world_from_cm"], dtype=np.float64) if isinstance(gt["world_from_cm"], list) else None
    W_true = _matrix(
        W.reshape(-1, 4, 4) if W is not None and W.size == 16 * n_poses else W,
        (n_poses, 4, 4),
        "ground_truth.world_from_cm",
        src,
    )
    return W_true, _matrix(gt["control_points_deg"], (5,), "ground_truth.control_points_deg", src)


def _centerline_initial_pose(view: CMView, entry: dict[str, Any], cp0: np.ndarray, src: str) -> np.ndarray:
    """Initial pose from the centreline initialisation of the first view (needs its centreline), its
    roll about the chord from the image (:func:`~fluoronav.registration.cm.roll_scan`)."""
    if entry.get("centerline_px") is None:
        raise InputError(src, "give 'initial_world_from_cm' or 'centerline_px' in the first view")
    cl = np.asarray(entry["centerline_px"], dtype=np.float64)
    if cl.ndim != 2 or cl.shape[1] != 2 or len(cl) < 2 or not np.all(np.isfinite(cl)):
        raise InputError(src, "views[0].centerline_px must be a (P >= 2, 2) array")
    assert view.landmarks_px is not None
    init = centerline_initialize(view.camera, view.landmarks_px, cl, cp0, image=view.image)
    # the roll about the chord, which the centreline leaves open, from the image (as the studies)
    return roll_scan_initialization(view, init, cl, cp0).world_from_cm


def load_case(path: str | Path) -> CMCase:
    """Read a case file (JSON, see docs/registration.md); paths inside are relative to its folder.

    Raises:
        InputError: naming the file, for any malformed or missing entry.
    """
    p = Path(path)
    src = str(p)
    d = read_json_object(p, what="case file")
    workflow = d.get("workflow")
    if workflow not in CM_WORKFLOWS:
        raise InputError(src, f"'workflow' must be one of {', '.join(CM_WORKFLOWS)}, got {workflow!r}")
    views = _views(d, workflow, p.parent, src)
    if "initial_control_points_deg" not in d:
        raise InputError(src, "'initial_control_points_deg' (5 values, the FBG reading) is required")
    cp0 = _matrix(d["initial_control_points_deg"], (5,), "initial_control_points_deg", src)
    base_from_cm = _base_from_cm(d, len(views), src) if workflow == "multi-cm" else None
    if d.get("initial_world_from_cm") is not None:
        T0 = _matrix(d["initial_world_from_cm"], (4, 4), "initial_world_from_cm", src)
    else:
        T0 = _centerline_initial_pose(views[0], d["views"][0], cp0, src)
    W_true = cp_true = None
    if d.get("ground_truth") is not None:
        n_poses = len(views) if workflow == "multi-cm" else 1
        W_true, cp_true = _ground_truth(d["ground_truth"], n_poses, src)
    return CMCase(
        workflow=workflow,
        views=views,
        initial_world_from_cm=T0,
        initial_control_points_deg=cp0,
        base_from_cm=base_from_cm,
        world_from_cm_true=W_true,
        control_points_true_deg=cp_true,
        config=_config_from(d.get("config"), src),
        source=src,
    )


def write_example_case(
    out_dir: str | Path, *, seed: int = 0, workflow: CMWorkflow = "single-view", image_size: int = 384
) -> Path:
    """Simulate a case with the physics simulator and write it as a case file (+ images, cameras).

    Returns:
        path of ``case.json`` in ``out_dir``.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    case = simulate_cm_case(workflow, seed=seed, image_size=image_size)
    entries = []
    for v in case.views:
        np.savez_compressed(out / f"{v.name}.npz", image=v.image.astype(np.float32))
        v.camera.save(out / f"{v.name}_camera.json")
        entries.append(
            {
                "name": v.name,
                "image": f"{v.name}.npz",
                "camera": f"{v.name}_camera.json",
                "landmarks_px": np.asarray(v.landmarks_px).tolist(),
                "binning": v.binning,
            }
        )
    d: dict[str, Any] = {
        "workflow": workflow,
        "views": entries,
        "initial_control_points_deg": case.initial_control_points_deg.tolist(),
        "initial_world_from_cm": case.initial_world_from_cm.tolist(),
        "ground_truth": {
            "world_from_cm": np.asarray(case.world_from_cm_true).tolist(),
            "control_points_deg": np.asarray(case.control_points_true_deg).tolist(),
        },
    }
    if case.base_from_cm is not None:
        # any split of base_from_cm into FK × hand-eye works; use the identity hand-eye
        d["multi_cm"] = {"base_from_ee": case.base_from_cm.tolist(), "ee_from_cm": np.eye(4).tolist()}
    path = out / "case.json"
    path.write_text(json.dumps(d, indent=1), encoding="utf-8")
    return path
