"""Physics-simulated CM registration cases: images, cameras, landmarks and the truth.

The cases follow the authors' protocol (Gao et al. 2022, sec. III-B, and their code) with AP-ish
views (:class:`CMCaseProtocol`): LAO/RAO U(−10°, 10°), CRAN/CAUD U(80°, 100°), source-to-isocentre
450 mm, control points U(−5°, 5°), the CM in the femur towards the femoral head. The images come
from :class:`~fluoronav.simulation.xray.XraySimulator`, never from the registration's analytic CM
renderer. The start is the truth perturbed in the CM base frame (rotation U(−r, r) about a random
axis, translation U(−t, t) per axis; authors: 10°/10 mm), control points truth + U(−0.5°, 0.5°),
landmarks truth + U(−3, 3) full-detector pixels. :func:`simulate_cm_case` gives a
:class:`SimulatedCMCase`; :func:`cm_case_from_simulation` assembles the registration's case from it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.carm import orbit_camera
from fluoronav.registration.cm.background import CTBackground
from fluoronav.registration.cm.case import CMCase
from fluoronav.registration.cm.config import CMRegistrationConfig
from fluoronav.registration.cm.views import CMView
from fluoronav.simulation.physics import XrayPhysics
from fluoronav.simulation.scene import Scene, SceneSampling, sample_scene
from fluoronav.simulation.xray import SimulationConfig, XraySimulator

__all__ = [
    "CM_WORKFLOWS",
    "CMCaseProtocol",
    "CMWorkflow",
    "SimulatedCMCase",
    "SimulatedCMView",
    "cm_case_from_simulation",
    "default_volume",
    "perturb_pose",
    "simulate_cm_case",
]

#: the CM registration workflows (:mod:`fluoronav.registration.cm`)
CM_WORKFLOWS = ("single-view", "multi-view", "multi-cm")
CMWorkflow = Literal["single-view", "multi-view", "multi-cm"]


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


@dataclass(frozen=True, eq=False)
class SimulatedCMView:
    """One simulated X-ray of a CM case.

    Attributes:
        name: ``view<k>`` (single- and multi-view) or ``pose<k>`` (multiple-CM).
        image: (H, W) float32 −log intensity image (bone and metal bright).
        camera: its camera (world = CT frame).
        landmarks_px: (2, 2) landmarks A, B as (u, v) in this image's pixels: the truth + noise.
        binning: full-detector pixels per image pixel.
    """

    name: str
    image: np.ndarray
    camera: Camera
    landmarks_px: np.ndarray
    binning: int


@dataclass(frozen=True, eq=False)
class SimulatedCMCase:
    """A simulated CM registration case (:func:`simulate_cm_case`).

    Attributes:
        workflow: one of :data:`CM_WORKFLOWS`.
        views: the images.
        volume: the CT they were simulated from (HU).
        initial_world_from_cm: (4, 4) initial pose (multiple-CM: of the CM in ``views[0]``).
        initial_control_points_deg: (5,).
        base_from_cm: (M, 4, 4) multiple-CM relative poses (robot base frame), else None.
        world_from_cm_true: (M, 4, 4) true poses (M = 1 but for multiple-CM).
        control_points_true_deg: (5,).
    """

    workflow: str
    views: list[SimulatedCMView]
    volume: Volume
    initial_world_from_cm: np.ndarray
    initial_control_points_deg: np.ndarray
    base_from_cm: np.ndarray | None
    world_from_cm_true: np.ndarray
    control_points_true_deg: np.ndarray


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
    key = (seed, spacing_mm)
    if key not in _VOLUMES:
        _VOLUMES[key] = hip_phantom(seed=seed, spacing_mm=spacing_mm)
    return _VOLUMES[key]


def _same_cm(scene: Scene, volume: Volume, camera: Camera, world_from_cm: np.ndarray) -> Scene:
    """``scene``'s CM shape and side seen by ``camera`` at ``world_from_cm``."""
    return Scene(
        camera,
        world_from_cm,
        scene.control_points_deg,
        volume_name=volume.name,
        side=scene.side,
        cm_config=scene.cm_config,
    )


def _workflow_scenes(
    workflow: str,
    scene: Scene,
    volume: Volume,
    rng: np.random.Generator,
    protocol: CMCaseProtocol,
    n_poses: int,
) -> tuple[list[Scene], np.ndarray | None]:
    """The workflow's scenes from the first one → (scenes, base_from_cm (M, 4, 4) for multiple-CM)."""
    scenes: list[Scene] = [scene]
    if workflow == "multi-view":
        # isocentre of the C-arm: the point on the central ray nearest the CM base
        cam = scene.camera
        src = cam.source_world
        cdir = cam.ray_directions_world(np.array([[(cam.cols - 1) / 2, (cam.rows - 1) / 2]]))[0]
        iso = src + cdir * float(np.dot(scene.world_from_cm[:3, 3] - src, cdir))
        for a in tuple(mean + rng.uniform(-h, h) for mean, h in protocol.view_orbits_deg):
            orbited = orbit_camera(cam, angle_deg=a, isocenter_world=iso)
            scenes.append(_same_cm(scene, volume, orbited, scene.world_from_cm))
        return scenes, None
    if workflow == "multi-cm":
        for _ in range(n_poses - 1):
            T = perturb_pose(
                scene.world_from_cm,
                rng,
                rotation_deg=protocol.multi_cm_rotation_deg,
                translation_mm=protocol.multi_cm_translation_mm,
            )
            scenes.append(_same_cm(scene, volume, scene.camera, T))
        world_from_base = perturb_pose(
            np.eye(4),
            rng,
            rotation_deg=protocol.robot_base_rotation_deg,
            translation_mm=protocol.robot_base_translation_mm,
        )
        return scenes, np.stack([np.linalg.inv(world_from_base) @ s.world_from_cm for s in scenes])
    return scenes, None


def simulate_cm_case(
    workflow: CMWorkflow,
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
    device: str = "cpu",
) -> SimulatedCMCase:
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
        device: simulation device.
    """
    if workflow not in CM_WORKFLOWS:
        raise ValueError(f"unknown workflow {workflow!r}; use one of {CM_WORKFLOWS}")
    pc = protocol or CMCaseProtocol()
    rotation_deg = pc.rotation_deg if rotation_deg is None else rotation_deg
    translation_mm = pc.translation_mm if translation_mm is None else translation_mm
    cp_noise = pc.control_point_noise_deg if control_point_noise_deg is None else control_point_noise_deg
    lm_noise = pc.landmark_noise_full_px if landmark_noise_full_px is None else landmark_noise_full_px
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
    n_poses = pc.n_cm_poses if n_cm_poses is None else n_cm_poses
    scenes, base_from_cm = _workflow_scenes(workflow, scene, vol, rng, pc, n_poses)
    views = []
    for k, s in enumerate(scenes):
        im = sim.simulate(s, seed=seed * 100 + k)
        assert im.landmarks_px is not None
        lm = im.landmarks_px + rng.uniform(-lm_noise, lm_noise, (2, 2)) / binning
        name = f"view{k}" if workflow != "multi-cm" else f"pose{k}"
        views.append(SimulatedCMView(name, im.image, im.camera, lm, binning))
    cp_true = np.asarray(scene.control_points_deg, np.float64)
    initial = perturb_pose(scene.world_from_cm, rng, rotation_deg=rotation_deg, translation_mm=translation_mm)
    return SimulatedCMCase(
        workflow=workflow,
        views=views,
        volume=vol,
        initial_world_from_cm=initial,
        initial_control_points_deg=cp_true + rng.uniform(-cp_noise, cp_noise, 5),
        base_from_cm=base_from_cm,
        world_from_cm_true=np.stack(
            [s.world_from_cm for s in (scenes if workflow == "multi-cm" else scenes[:1])]
        ),
        control_points_true_deg=cp_true,
    )


def cm_case_from_simulation(
    simulated: SimulatedCMCase,
    *,
    background: bool = False,
    config: CMRegistrationConfig | None = None,
    device: str = "cpu",
) -> CMCase:
    """The registration case of a simulated one.

    Args:
        simulated: from :func:`~fluoronav.simulation.cm_case.simulate_cm_case`.
        background: attach the anatomy DRR of the simulated CT at the true CT pose to each view (the
            bone registration result in the studies).
        config: registration settings stored in the case (default :class:`CMRegistrationConfig`).
        device: the background renderer's device.
    """
    bg_renderer = CTBackground(simulated.volume, device=device) if background else None
    views = [
        CMView(
            image=v.image,
            camera=v.camera,
            landmarks_px=v.landmarks_px,
            background=bg_renderer,
            binning=v.binning,
            name=v.name,
        )
        for v in simulated.views
    ]
    return CMCase(
        workflow=simulated.workflow,
        views=views,
        initial_world_from_cm=simulated.initial_world_from_cm,
        initial_control_points_deg=simulated.initial_control_points_deg,
        base_from_cm=simulated.base_from_cm,
        world_from_cm_true=simulated.world_from_cm_true,
        control_points_true_deg=simulated.control_points_true_deg,
        config=config or CMRegistrationConfig(),
    )
