"""Scenes: a CT volume, a C-arm view and a CM pose/shape, sampled as in the paper's data set.

Sampling (Gao et al. 2022, §III-A): control points U[−7.9°, 7.9°], source-to-isocentre
U[400, 500] mm, LAO/RAO U[0°, 360°], CRAN/CAUD U[75°, 105°], volume translation U[−20, 20] mm per
axis (applied here as the opposite shift of the isocentre, which is the same relative geometry).

The CM is placed as for core decompression: its axis runs from the lateral greater trochanter
(the ``entry_*`` landmark) towards the femoral head centre, inserted so that it overlaps bone. A CT
without femur landmarks gets the CM in the bone nearest the volume centre, in a random direction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from fluoronav.anatomy.volume import Volume
from fluoronav.geometry.camera import CIOS_FUSION, Camera, DetectorSpec
from fluoronav.geometry.carm import carm_camera_from_world
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.manipulator.projection import angle_between_deg, project_cm_points, shaft_ends_cm
from fluoronav.simulation.instrument import BuiltCM

__all__ = [
    "Scene",
    "SceneSampling",
    "angle_between_deg",
    "cm_pose_along",
    "place_cm_in_bone",
    "project_cm_points",
    "projected_ab_mm",
    "projected_shaft_angle_deg",
    "projected_shaft_mm",
    "sample_scene",
]

#: HU above which a voxel counts as bone when placing a CM in an unlabelled CT
BONE_HU = 200.0


@dataclass(frozen=True)
class SceneSampling:
    """Ranges of the scene sampler (defaults: the paper's detection data set)."""

    control_point_range_deg: tuple[float, float] = (-7.9, 7.9)
    source_to_isocenter_mm: tuple[float, float] = (400.0, 500.0)
    lao_rao_deg: tuple[float, float] = (0.0, 360.0)
    cran_caud_deg: tuple[float, float] = (75.0, 105.0)
    translation_mm: float = 20.0
    #: how far the base origin A sits inside the bone from the entry point, mm
    insertion_depth_mm: tuple[float, float] = (-5.0, 15.0)
    #: tilt of the CM axis away from the entry → femoral head line, degrees
    axis_tilt_deg: float = 10.0
    detector: DetectorSpec = CIOS_FUSION
    #: keep only scenes whose landmarks A and B project at most this far apart on the detector, mm
    #: (None: every scene). Foreshortened views (the CM seen nearly along its axis: a quarter of the
    #: paper's views project A–B shorter than 33 mm) made most of the detector's errors; a training
    #: set can hold more of them.
    max_projected_ab_mm: float | None = None
    #: keep only scenes whose mounting shaft (``shaft_length_mm`` behind A along the base axis)
    #: projects at most this long on the detector, mm (None: every scene). A shaft seen nearly along
    #: its axis is a short bright stub at A that a detector can take for part of the CM (2–3 % of
    #: the paper's views project it shorter than 30 mm); a training set can hold more of them.
    max_projected_shaft_mm: float | None = None
    #: keep only scenes where the CM's chord A → B and its mounting shaft (A → the far end) meet at
    #: A at most this angle on the detector, degrees (None: every scene). The shaft goes on behind
    #: the CM (~180°) in most views; at 20–70° the two tubes form a V at A, under 35° the CM lies
    #: over its shaft, and a detector can run the CM's mask down the shaft and put A on its far end.
    max_shaft_angle_deg: float | None = None
    #: length of the mounting shaft that ``max_projected_shaft_mm`` and ``max_shaft_angle_deg``
    #: measure, mm
    shaft_length_mm: float = 50.0
    #: draws allowed to find a scene within the limits above before giving up
    max_draws: int = 10_000

    def __post_init__(self) -> None:
        for name in ("max_projected_ab_mm", "max_projected_shaft_mm"):
            limit = getattr(self, name)
            if limit is not None and not limit > 0:
                raise ValueError(f"{name} must be positive, got {limit}")
        for name in ("max_projected_shaft_mm", "max_shaft_angle_deg"):
            if getattr(self, name) is not None and not self.shaft_length_mm > 0:
                raise ValueError(f"{name} needs a shaft (shaft_length_mm > 0)")
        angle = self.max_shaft_angle_deg
        if angle is not None and not 0.0 < angle <= 180.0:
            raise ValueError(f"max_shaft_angle_deg must be in (0, 180], got {angle}")


@dataclass(frozen=True, eq=False)
class Scene:
    """One simulated acquisition.

    Attributes:
        camera: full-detector camera in world (CT) coordinates.
        world_from_cm: CM base pose (4, 4), mm.
        control_points_deg: (5,) CM control points.
        has_cm: False for negatives (no CM in the image).
        volume_name: the CT's name.
        side: which femur the CM is in ("left", "right" or "" when unlabelled).
        cm_config: the CM's geometry.
        lao_rao_deg, cran_caud_deg, source_to_isocenter_mm: the sampled C-arm angles and distance.
        isocenter_world: (3,) the C-arm isocentre, mm.
        built_cm: the instrument as built, drawn in the images and labelled instead of the model
            ``cm_config`` at ``control_points_deg`` (None: the model itself).
    """

    camera: Camera
    world_from_cm: np.ndarray
    control_points_deg: np.ndarray
    has_cm: bool = True
    volume_name: str = "volume"
    side: str = ""
    cm_config: CMConfig = field(default_factory=CMConfig)
    lao_rao_deg: float = float("nan")
    cran_caud_deg: float = float("nan")
    source_to_isocenter_mm: float = float("nan")
    isocenter_world: np.ndarray | None = None
    built_cm: BuiltCM | None = None


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _random_unit_perpendicular(rng: np.random.Generator, axis: np.ndarray) -> np.ndarray:
    v = rng.normal(size=3)
    v -= v.dot(axis) * axis
    return _unit(v)


def cm_pose_along(origin_world: np.ndarray, axis_world: np.ndarray, roll_rad: float) -> np.ndarray:
    """``world_from_cm`` with base origin A at ``origin_world`` and +z along ``axis_world``.

    ``roll_rad`` turns the bending plane about the axis.
    """
    z = _unit(np.asarray(axis_world, dtype=np.float64))
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x0 = _unit(np.cross(helper, z))
    y0 = np.cross(z, x0)
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    x = c * x0 + s * y0
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = origin_world
    return T


def place_cm_in_bone(
    volume: Volume, rng: np.random.Generator, sampling: SceneSampling
) -> tuple[np.ndarray, str]:
    """A CM base pose inside a femur (labelled phantom/CT) or in the bone nearest the volume centre."""
    sides = [
        s
        for s in ("left", "right")
        if f"entry_{s}" in volume.landmarks_world and f"femoral_head_{s}" in volume.landmarks_world
    ]
    if sides:
        side = sides[int(rng.integers(len(sides)))]
        entry = np.asarray(volume.landmarks_world[f"entry_{side}"], dtype=np.float64)
        head = np.asarray(volume.landmarks_world[f"femoral_head_{side}"], dtype=np.float64)
        axis = _unit(head - entry)
        tilt = math.radians(rng.uniform(0.0, sampling.axis_tilt_deg))
        axis = _unit(math.cos(tilt) * axis + math.sin(tilt) * _random_unit_perpendicular(rng, axis))
        depth = rng.uniform(*sampling.insertion_depth_mm)
        origin = entry + depth * axis
        return cm_pose_along(origin, axis, rng.uniform(0.0, 2.0 * math.pi)), side
    # unlabelled CT: the bone voxel nearest the volume centre
    bone = np.argwhere(volume.data > BONE_HU)  # (n, 3) as (k, j, i)
    if len(bone) == 0:
        origin = volume.center_world
    else:
        idx = bone[:, ::-1].astype(np.float64)
        world = idx @ volume.world_from_index[:3, :3].T + volume.world_from_index[:3, 3]
        origin = world[np.argmin(np.linalg.norm(world - volume.center_world, axis=1))]
    axis = _unit(rng.normal(size=3))
    return cm_pose_along(origin, axis, rng.uniform(0.0, 2.0 * math.pi)), ""


def sample_scene(
    volume: Volume,
    rng: np.random.Generator,
    *,
    sampling: SceneSampling | None = None,
    with_cm: bool = True,
    cm_config: CMConfig | None = None,
) -> Scene:
    """Sample one scene with the paper's data set distribution (see module docstring).

    With ``sampling.max_projected_ab_mm`` (``max_projected_shaft_mm``, ``max_shaft_angle_deg``) set,
    scenes are drawn until the projected A–B distance (the projected shaft, the angle between the
    two, :func:`projected_shaft_angle_deg`) is within it (rejection sampling: the paper's
    distribution restricted to foreshortened views of the CM or of its shaft, or to views where the
    CM and its shaft form a V).
    """
    sampling = sampling or SceneSampling()
    cm_config = cm_config or CMConfig()
    ab_limit, shaft_limit = sampling.max_projected_ab_mm, sampling.max_projected_shaft_mm
    angle_limit = sampling.max_shaft_angle_deg
    if ab_limit is None and shaft_limit is None and angle_limit is None:
        return _draw_scene(volume, rng, sampling, with_cm, cm_config)
    kin = CMKinematics(cm_config)
    length_mm = sampling.shaft_length_mm
    for _ in range(sampling.max_draws):
        scene = _draw_scene(volume, rng, sampling, with_cm, cm_config)
        if shaft_limit is not None and projected_shaft_mm(scene, length_mm) > shaft_limit:
            continue
        if angle_limit is not None and projected_shaft_angle_deg(scene, length_mm, kin) > angle_limit:
            continue
        if ab_limit is None or projected_ab_mm(scene, kin) <= ab_limit:
            return scene
    raise ValueError(
        f"no scene within max_projected_ab_mm={ab_limit}, max_projected_shaft_mm={shaft_limit}, "
        f"max_shaft_angle_deg={angle_limit} in {sampling.max_draws} draws"
    )


def projected_ab_mm(scene: Scene, kinematics: CMKinematics | None = None) -> float:
    """Distance of the projected landmarks A and B on the detector, mm (at the detector plane)."""
    kin = kinematics or CMKinematics(scene.cm_config)
    ab_cm = kin.landmarks_cm(torch.as_tensor(np.asarray(scene.control_points_deg, dtype=np.float64)))
    return _projected_length_mm(scene, ab_cm.numpy())


def projected_shaft_mm(scene: Scene, shaft_length_mm: float) -> float:
    """Length on the detector (mm, at the detector plane) of the mounting shaft: the segment from
    the base origin A to ``shaft_length_mm`` behind it along the base axis (−z of the CM frame)."""
    return _projected_length_mm(scene, shaft_ends_cm(shaft_length_mm))


def projected_shaft_angle_deg(
    scene: Scene, shaft_length_mm: float, kinematics: CMKinematics | None = None
) -> float:
    """Angle (degrees, 0–180) at A on the detector between the CM's chord A → B and its mounting
    shaft (A → ``shaft_length_mm`` behind it along the base axis): near 180 where the shaft goes on
    behind the CM, small where the CM lies over it (NaN where either projects to a point)."""
    kin = kinematics or CMKinematics(scene.cm_config)
    ab_cm = kin.landmarks_cm(torch.as_tensor(np.asarray(scene.control_points_deg, dtype=np.float64)))
    points_cm = np.vstack([ab_cm.numpy(), shaft_ends_cm(shaft_length_mm)[1:]])
    uv = project_cm_points(scene.camera, scene.world_from_cm, points_cm)
    return angle_between_deg(uv[1] - uv[0], uv[2] - uv[0])


def projected_length_mm(camera: Camera, world_from_cm: np.ndarray, ends_cm: np.ndarray) -> float:
    """Distance on the detector (mm, at the detector plane) between the projections of two points
    (2, 3) given in the CM's base frame, posed by ``world_from_cm`` (4, 4) and seen by ``camera``."""
    uv = project_cm_points(camera, world_from_cm, ends_cm)
    if camera.pixel_spacing_mm is None:
        raise ValueError("the camera has no pixel spacing")
    return float(np.linalg.norm(uv[1] - uv[0]) * camera.pixel_spacing_mm)


def _projected_length_mm(scene: Scene, ends_cm: np.ndarray) -> float:
    return projected_length_mm(scene.camera, scene.world_from_cm, ends_cm)


def _draw_scene(
    volume: Volume, rng: np.random.Generator, sampling: SceneSampling, with_cm: bool, cm_config: CMConfig
) -> Scene:
    world_from_cm, side = place_cm_in_bone(volume, rng, sampling)
    cp = rng.uniform(*sampling.control_point_range_deg, size=cm_config.n_control_points)
    # isocentre: the middle of the CM (so it is in the field of view), shifted like the volume
    mid_cm = np.array([0.0, 0.0, 0.5 * cm_config.tip_z_mm, 1.0])
    iso = (world_from_cm @ mid_cm)[:3] - rng.uniform(-sampling.translation_mm, sampling.translation_mm, 3)
    alpha = float(rng.uniform(*sampling.lao_rao_deg))
    beta = float(rng.uniform(*sampling.cran_caud_deg))
    sid = float(rng.uniform(*sampling.source_to_isocenter_mm))
    T = carm_camera_from_world(
        lao_rao_deg=alpha, cran_caud_deg=beta, source_to_isocenter_mm=sid, isocenter_world=iso
    )
    camera = Camera.from_detector(sampling.detector, T)
    return Scene(
        camera=camera,
        world_from_cm=world_from_cm,
        control_points_deg=cp,
        has_cm=with_cm,
        volume_name=volume.name,
        side=side,
        cm_config=cm_config,
        lao_rao_deg=alpha,
        cran_caud_deg=beta,
        source_to_isocenter_mm=sid,
        isocenter_world=iso,
    )
