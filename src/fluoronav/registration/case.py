"""CM registration cases: simulated test cases (physics simulator) and case files for ``fluoronav register``.

Simulated cases (:func:`simulate_cm_case`) follow the authors' simulation protocol (Gao et al., IEEE
TBME 69(1), 2022, sec. III-B, and the authors' code) with AP-ish views (:class:`CMCaseProtocol`):
LAO/RAO U(−10°, 10°), CRAN/CAUD U(80°, 100°), source-to-isocentre 450 mm, control points U(−5°, 5°),
the CM in the femur towards the femoral head. The images come from
:class:`~fluoronav.simulation.xray.XraySimulator` (voxelised nitinol CM over the CT, polychromatic
physics), never from the analytic CM renderer used by the registration. The initial pose is the
truth perturbed in the CM base frame (rotation U(−r, r) about a random axis, translation U(−t, t)
per axis; authors: 10°/10 mm), initial control points truth + U(−0.5°, 0.5°), landmarks truth +
U(−3, 3) full-detector pixels.

Case files (JSON; documented in docs/registration.md) are read by :func:`load_case`, which raises
:class:`~fluoronav.errors.InputError` naming the file for anything malformed.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError, read_json_object
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.carm import orbit_camera
from fluoronav.geometry.dicom import camera_from_dicom
from fluoronav.registration.centerline.single import centerline_initialize
from fluoronav.registration.cm.background import CTBackground
from fluoronav.registration.cm.config import CM_COARSE_LEVEL, CMRegistrationConfig, default_cm_levels
from fluoronav.registration.cm.roll_scan import roll_scan_initialization
from fluoronav.registration.cm.views import CMView

__all__ = [
    "WORKFLOWS",
    "CMCase",
    "CMCaseProtocol",
    "detect_landmarks",
    "load_case",
    "perturb_pose",
    "simulate_cm_case",
    "write_example_case",
]

logger = logging.getLogger(__name__)

WORKFLOWS = ("single-view", "multi-view", "multi-cm")
Workflow = Literal["single-view", "multi-view", "multi-cm"]


@dataclass(frozen=True, eq=False)
class CMCase:
    """Everything :func:`~fluoronav.registration.cm.register_cm` needs, plus optional ground truth.

    Attributes:
        workflow: "single-view", "multi-view" or "multi-cm".
        views: the images.
        initial_world_from_cm: (4, 4) initial pose (multiple-CM: of the CM in ``views[0]``).
        initial_control_points_deg: (5,).
        base_from_cm: (M, 4, 4) multiple-CM relative poses (robot FK × hand-eye), else None.
        world_from_cm_true: (M, 4, 4) true poses or None; control_points_true_deg: (5,) or None.
        config: registration settings.
        source: file the case came from ("" for simulated cases).
    """

    workflow: str
    views: list[CMView]
    initial_world_from_cm: np.ndarray
    initial_control_points_deg: np.ndarray
    base_from_cm: np.ndarray | None = None
    world_from_cm_true: np.ndarray | None = None
    control_points_true_deg: np.ndarray | None = None
    config: CMRegistrationConfig = field(default_factory=CMRegistrationConfig)
    source: str = ""


# ----- simulation -----------------------------------------------------------------------------
@dataclass(frozen=True)
class CMCaseProtocol:
    """The distributions of :func:`simulate_cm_case` (the authors' protocol; see the module docstring).

    Attributes:
        control_point_range_deg: true control points U(range).
        source_to_isocenter_mm, lao_rao_deg, cran_caud_deg: C-arm pose U(range) each.
        energy_bin_keV: spectrum bin width of the polychromatic simulation.
        view_orbits_deg: multi-view: each further view orbited by mean + U(−h, h) degrees, (mean, h).
        n_cm_poses: multiple-CM: CM poses (images) in the AP view.
        multi_cm_rotation_deg, multi_cm_translation_mm: multiple-CM: each further pose is the first
            perturbed in its own frame by these (rotation U(−r, r), translation U(−t, t) per axis).
        robot_base_rotation_deg, robot_base_translation_mm: multiple-CM: the robot base frame is the
            world perturbed by these.
        rotation_deg, translation_mm: initial pose = truth perturbed in the CM base frame by these.
        control_point_noise_deg: initial control points = truth + U(−x, x).
        landmark_noise_full_px: landmarks = truth + U(−x, x) full-detector pixels.
    """

    control_point_range_deg: tuple[float, float] = (-5.0, 5.0)
    source_to_isocenter_mm: tuple[float, float] = (450.0, 450.0)
    lao_rao_deg: tuple[float, float] = (-10.0, 10.0)
    cran_caud_deg: tuple[float, float] = (80.0, 100.0)
    energy_bin_keV: float = 3.0  # noqa: N815 (unit suffix)
    view_orbits_deg: tuple[tuple[float, float], ...] = ((20.0, 3.0), (-15.0, 3.0))
    n_cm_poses: int = 4
    multi_cm_rotation_deg: float = 30.0
    multi_cm_translation_mm: float = 10.0
    robot_base_rotation_deg: float = 180.0
    robot_base_translation_mm: float = 500.0
    rotation_deg: float = 10.0
    translation_mm: float = 10.0
    control_point_noise_deg: float = 0.5
    landmark_noise_full_px: float = 3.0


def _rotvec_matrix(v: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(v))
    if th < 1e-15:
        return np.eye(3)
    k = v / th
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * Kx + (1 - math.cos(th)) * Kx @ Kx


def perturb_pose(
    world_from_cm: np.ndarray, rng: np.random.Generator, *, rotation_deg: float, translation_mm: float
) -> np.ndarray:
    """Perturb a pose in its own (CM base) frame: rotation U(−r, r) about a random axis through the
    origin, translation U(−t, t) per axis."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    D = np.eye(4)
    D[:3, :3] = _rotvec_matrix(axis * math.radians(rng.uniform(-rotation_deg, rotation_deg)))
    D[:3, 3] = rng.uniform(-translation_mm, translation_mm, 3)
    return np.asarray(world_from_cm, np.float64) @ D


_VOLUMES: dict[tuple[int, float], Volume] = {}


def default_volume(seed: int = 0, spacing_mm: float = 2.0) -> Volume:
    """The hip phantom (cached per process; 2 mm voxels keep simulation fast)."""
    from fluoronav.anatomy.phantom import hip_phantom  # heavy import, needed only without a CT

    key = (seed, spacing_mm)
    if key not in _VOLUMES:
        _VOLUMES[key] = hip_phantom(seed=seed, spacing_mm=spacing_mm)
    return _VOLUMES[key]


def simulate_cm_case(
    workflow: Workflow,
    *,
    seed: int,
    volume: Volume | None = None,
    image_size: int = 768,
    photons_per_pixel: float | None = 5000.0,
    protocol: CMCaseProtocol | None = None,
    rotation_deg: float | None = None,
    translation_mm: float | None = None,
    control_point_noise_deg: float | None = None,
    landmark_noise_full_px: float | None = None,
    n_cm_poses: int | None = None,
    background: bool = False,
    config: CMRegistrationConfig | None = None,
    device: str = "cpu",
) -> CMCase:
    """A physics-simulated CM registration case (see the module docstring for the distributions).

    Args:
        workflow: "single-view" (one AP-ish view), "multi-view" (the AP view plus views orbited by
            ``protocol.view_orbits_deg``: +20 ± 3° and −15 ± 3°) or "multi-cm" (``n_cm_poses`` CM
            poses in the AP view, the first as sampled and the others ±10 mm, ±30° about random axes;
            the robot base frame is a random rigid transform of the world).
        seed: everything random derives from it.
        volume: CT in HU (default: the hip phantom at 2 mm).
        image_size: stored image side; the 1536² CIOS detector is binned to it (768 → binning 2).
        photons_per_pixel: Poisson noise level (None: noise-free).
        protocol: the distributions (default :class:`CMCaseProtocol`).
        rotation_deg, translation_mm: initial pose perturbation (CM base frame); None: the protocol's.
        control_point_noise_deg: initial control points = truth + U(−x, x); None: the protocol's.
        landmark_noise_full_px: landmarks = truth + U(−x, x) full-detector pixels; None: the
            protocol's.
        n_cm_poses: multiple-CM poses; None: the protocol's.
        background: attach the anatomy DRR at the true CT pose to each view (the bone registration
            result in the study).
        config: registration settings stored in the case.
        device: simulation device.
    """
    # the physics simulator is heavy to import (numba kernels, xraylib) and needed only here
    from fluoronav.simulation.physics import XrayPhysics
    from fluoronav.simulation.scene import Scene, SceneSampling, sample_scene
    from fluoronav.simulation.xray import SimulationConfig, XraySimulator

    if workflow not in WORKFLOWS:
        raise ValueError(f"unknown workflow {workflow!r}; use one of {WORKFLOWS}")
    pc = protocol or CMCaseProtocol()
    rotation_deg = pc.rotation_deg if rotation_deg is None else rotation_deg
    translation_mm = pc.translation_mm if translation_mm is None else translation_mm
    cp_noise = pc.control_point_noise_deg if control_point_noise_deg is None else control_point_noise_deg
    lm_noise = pc.landmark_noise_full_px if landmark_noise_full_px is None else landmark_noise_full_px
    n_poses = pc.n_cm_poses if n_cm_poses is None else n_cm_poses
    rng = np.random.default_rng(seed)
    vol = volume if volume is not None else default_volume()
    sampling = SceneSampling(
        control_point_range_deg=pc.control_point_range_deg,
        source_to_isocenter_mm=pc.source_to_isocenter_mm,
        lao_rao_deg=pc.lao_rao_deg,
        cran_caud_deg=pc.cran_caud_deg,
    )
    scene = sample_scene(vol, rng, sampling=sampling)
    physics = XrayPhysics(energy_bin_keV=pc.energy_bin_keV, photons_per_pixel=photons_per_pixel)
    sim = XraySimulator(vol, config=SimulationConfig(physics=physics, image_size=image_size), device=device)
    binning = max(1, round(scene.camera.cols / image_size))
    # isocentre of the C-arm: the point on the central ray nearest the CM base
    src = scene.camera.source_world
    cdir = scene.camera.ray_directions_world(
        np.array([[(scene.camera.cols - 1) / 2, (scene.camera.rows - 1) / 2]])
    )[0]
    iso = src + cdir * float(np.dot(scene.world_from_cm[:3, 3] - src, cdir))

    scenes: list[Scene] = [scene]
    base_from_cm = None
    if workflow == "multi-view":
        for a in tuple(mean + rng.uniform(-h, h) for mean, h in pc.view_orbits_deg):
            cam = orbit_camera(scene.camera, angle_deg=a, isocenter_world=iso)
            scenes.append(
                Scene(
                    cam,
                    scene.world_from_cm,
                    scene.control_points_deg,
                    volume_name=vol.name,
                    side=scene.side,
                    cm_config=scene.cm_config,
                )
            )
    elif workflow == "multi-cm":
        for _ in range(n_poses - 1):
            T = perturb_pose(
                scene.world_from_cm,
                rng,
                rotation_deg=pc.multi_cm_rotation_deg,
                translation_mm=pc.multi_cm_translation_mm,
            )
            scenes.append(
                Scene(
                    scene.camera,
                    T,
                    scene.control_points_deg,
                    volume_name=vol.name,
                    side=scene.side,
                    cm_config=scene.cm_config,
                )
            )
        world_from_base = perturb_pose(
            np.eye(4),
            rng,
            rotation_deg=pc.robot_base_rotation_deg,
            translation_mm=pc.robot_base_translation_mm,
        )
        base_from_cm = np.stack([np.linalg.inv(world_from_base) @ s.world_from_cm for s in scenes])

    bg_renderer = None
    if background:
        bg_renderer = CTBackground(vol, device=device)
    views = []
    for k, s in enumerate(scenes):
        im = sim.simulate(s, seed=seed * 100 + k)
        assert im.landmarks_px is not None
        lm = im.landmarks_px + rng.uniform(-lm_noise, lm_noise, (2, 2)) / binning
        views.append(
            CMView(
                image=im.image,
                camera=im.camera,
                landmarks_px=lm,
                background=bg_renderer,
                binning=binning,
                name=f"view{k}" if workflow != "multi-cm" else f"pose{k}",
            )
        )
    cp_true = np.asarray(scene.control_points_deg, np.float64)
    return CMCase(
        workflow=workflow,
        views=views,
        initial_world_from_cm=perturb_pose(
            scene.world_from_cm, rng, rotation_deg=rotation_deg, translation_mm=translation_mm
        ),
        initial_control_points_deg=cp_true + rng.uniform(-cp_noise, cp_noise, 5),
        base_from_cm=base_from_cm,
        world_from_cm_true=np.stack(
            [s.world_from_cm for s in (scenes if workflow == "multi-cm" else scenes[:1])]
        ),
        control_points_true_deg=cp_true,
        config=config or CMRegistrationConfig(),
    )


# ----- case files -----------------------------------------------------------------------------
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
    known = {
        "popsize",
        "refine",
        "landmark_sigma_full_px",
        "roi_size_full_px",
        "use_background",
        "cm_mu_per_mm",
    }
    unknown = set(d) - known
    if unknown:
        raise InputError(source, f"unknown config keys {sorted(unknown)}; known: {sorted(known)}")
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
    try:  # the detector (a trained network) is heavy and optional
        from fluoronav.detection.detector import Detector
    except ImportError:
        raise InputError(source, "no landmarks given and no detector available; add 'landmarks_px'") from None
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


def load_case(path: str | Path) -> CMCase:
    """Read a case file (JSON, see docs/registration.md); paths inside are relative to its folder.

    Raises:
        InputError: naming the file, for any malformed or missing entry.
    """
    from fluoronav.detection.detector import load_image  # heavy (the detector's network stack)

    p = Path(path)
    src = str(p)
    d = read_json_object(p, what="case file")
    workflow = d.get("workflow")
    if workflow not in WORKFLOWS:
        raise InputError(src, f"'workflow' must be one of {', '.join(WORKFLOWS)}, got {workflow!r}")
    vlist = d.get("views")
    if not isinstance(vlist, list) or not vlist:
        raise InputError(src, "'views' must be a non-empty list")
    if workflow == "single-view" and len(vlist) != 1:
        raise InputError(src, f"single-view needs exactly one view, got {len(vlist)}")
    root = p.parent
    views = []
    for k, v in enumerate(vlist):
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
        views.append(
            CMView(
                image=img,
                camera=camera,
                landmarks_px=lm,
                background=bg,
                binning=binning,
                name=str(v.get("name", f"view{k}")),
            )
        )
    names = [v.name for v in views]
    if len(set(names)) != len(names):
        raise InputError(src, f"view names must be unique, got {names}")
    if "initial_control_points_deg" not in d:
        raise InputError(src, "'initial_control_points_deg' (5 values, the FBG reading) is required")
    cp0 = _matrix(d["initial_control_points_deg"], (5,), "initial_control_points_deg", src)
    base_from_cm = None
    if workflow == "multi-cm":
        mc = d.get("multi_cm")
        if not isinstance(mc, dict) or "base_from_ee" not in mc or "ee_from_cm" not in mc:
            raise InputError(src, "multi-cm needs 'multi_cm': {'base_from_ee': [M 4x4], 'ee_from_cm': 4x4}")
        bfe = _matrix(mc["base_from_ee"], (len(views), 4, 4), "multi_cm.base_from_ee (one per view)", src)
        efc = _matrix(mc["ee_from_cm"], (4, 4), "multi_cm.ee_from_cm", src)
        base_from_cm = bfe @ efc
    if d.get("initial_world_from_cm") is not None:
        T0 = _matrix(d["initial_world_from_cm"], (4, 4), "initial_world_from_cm", src)
    else:
        T0 = _centerline_initial_pose(views[0], vlist[0], cp0, src)
    gt = d.get("ground_truth")
    W_true = cp_true = None
    if gt is not None:
        if not isinstance(gt, dict) or "world_from_cm" not in gt or "control_points_deg" not in gt:
            raise InputError(src, "'ground_truth' needs 'world_from_cm' and 'control_points_deg'")
        m = len(views) if workflow == "multi-cm" else 1
        W = (
            np.asarray(gt["world_from_cm"], dtype=np.float64)
            if isinstance(gt["world_from_cm"], list)
            else None
        )
        W_true = _matrix(
            W.reshape(-1, 4, 4) if W is not None and W.size == 16 * m else W,
            (m, 4, 4),
            "ground_truth.world_from_cm",
            src,
        )
        cp_true = _matrix(gt["control_points_deg"], (5,), "ground_truth.control_points_deg", src)
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


def write_example_case(
    out_dir: str | Path, *, seed: int = 0, workflow: Workflow = "single-view", image_size: int = 384
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
        assert v.landmarks_px is not None
        entries.append(
            {
                "name": v.name,
                "image": f"{v.name}.npz",
                "camera": f"{v.name}_camera.json",
                "landmarks_px": np.asarray(v.landmarks_px).tolist(),
                "binning": v.image_binning,
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
