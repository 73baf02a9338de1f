"""The paper's simulation protocol (Gao et al., IEEE TBME 69(1), 2022, §III-B, and the authors' code).

One :class:`Trial` holds the ground truth of one simulated experiment and the initialisation noise
of the authors' code, all drawn from the one ``rng`` in a fixed order: the pelvis (the whole
patient), the femur about its head, the control points, the C-arm (≈ AP; multi-view adds two
orbits), the CM "above the femoral head" (redrawn until it projects inside every view), the
multiple-CM poses, then the initialisation noise. The distributions: docs/simulation.md ("The
studies' protocol"). Workflows: ``centerline``, ``single-view`` and ``navigation`` have one image;
``multi-view`` three (one CM pose, three cameras); ``multi-cm`` and ``hand-eye`` four (one camera,
four CM poses).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from fluoronav.anatomy.volume import Volume
from fluoronav.geometry.camera import CIOS_FUSION, Camera, DetectorSpec
from fluoronav.geometry.carm import carm_camera, orbit_camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.simulation.articulated import ArticulatedSimulator
from fluoronav.simulation.scene import cm_pose_along
from fluoronav.simulation.xray import SimulatedImage

__all__ = [
    "WORKFLOWS",
    "ProtocolConfig",
    "Trial",
    "perturb_about",
    "sample_trial",
    "simulate_trial_images",
]

WORKFLOWS = ("centerline", "single-view", "multi-view", "multi-cm", "hand-eye", "navigation")
#: workflows with several CM poses in one view
_MULTI_CM = ("multi-cm", "hand-eye")
_ANTERIOR = np.array([0.0, -1.0, 0.0])  # LPS: +y is posterior


@dataclass(frozen=True)
class ProtocolConfig:
    """Ranges of the protocol (defaults: the paper and the authors' code; see the module docstring).

    Attributes:
        pelvis_translation_mm, pelvis_rotation_deg: 1. pelvis motion, U(0, t) mm and U(−r, r)°.
        femur_rotation_deg: 2. femur rotation about the head, U(−r, r)°.
        control_point_range_deg: 3. control points U(range).
        source_to_isocenter_mm: 4. C-arm source-to-isocentre U(range).
        angle_jitter_deg: 4. LAO/RAO U(±j)° and CRAN/CAUD ``cran_caud_deg`` + U(±j)°.
        cran_caud_deg: 4. nominal CRAN/CAUD of the AP view.
        isocenter_jitter_mm: 4. isocentre = femoral head + U(±j) mm per axis.
        view_offsets_deg: 4. multi-view: the further views' orbit angles N(mean, σ)°, (mean, σ) each.
        cm_anterior_mm, cm_setback_mm: 5. nominal CM base origin relative to the femoral head.
        cm_translation_mm, cm_rotation_deg: 5. CM base perturbation.
        multi_cm_poses, multi_cm_translation_mm, multi_cm_rotation_deg: 6. multiple-CM / hand-eye poses.
        init_ct_rotation_deg, init_ct_translation_mm: 7. initial CT pose error (exact sizes).
        init_cm_rotation_deg, init_cm_translation_mm: 7. initial CM base error (exact sizes).
        fbg_noise_deg: 7. FBG control points = truth + U(±x)°.
        landmark_noise_px: 7. oracle landmarks = truth + U(±x) full-detector pixels.
        margin_px: 5. landmarks and tip at least this far inside every detector edge.
        max_redraws: 5. CM poses drawn at most this often to get one in view.
        detector: the C-arm detector.
    """

    pelvis_translation_mm: float = 10.0
    pelvis_rotation_deg: float = 10.0
    femur_rotation_deg: float = 15.0
    control_point_range_deg: tuple[float, float] = (-5.0, 5.0)
    source_to_isocenter_mm: tuple[float, float] = (400.0, 500.0)
    angle_jitter_deg: float = 5.0
    cran_caud_deg: float = 90.0
    isocenter_jitter_mm: float = 15.0
    view_offsets_deg: tuple[tuple[float, float], ...] = ((20.0, 3.0), (-15.0, 3.0))
    cm_anterior_mm: tuple[float, float] = (20.0, 40.0)
    cm_setback_mm: tuple[float, float] = (15.0, 35.0)
    cm_translation_mm: float = 30.0
    cm_rotation_deg: float = 30.0
    multi_cm_poses: int = 4
    multi_cm_translation_mm: float = 10.0
    multi_cm_rotation_deg: float = 30.0
    init_ct_rotation_deg: float = 3.0
    init_ct_translation_mm: float = 10.0
    init_cm_rotation_deg: float = 10.0
    init_cm_translation_mm: float = 10.0
    fbg_noise_deg: float = 0.5
    landmark_noise_px: float = 3.0
    margin_px: float = 100.0
    max_redraws: int = 200
    detector: DetectorSpec = CIOS_FUSION

    def n_images(self, workflow: str) -> int:
        """Images of a trial of ``workflow``: the AP view and the orbited views (multi-view), one per
        CM pose (multiple-CM, hand-eye), else one."""
        if workflow == "multi-view":
            return 1 + len(self.view_offsets_deg)
        if workflow in _MULTI_CM:
            return self.multi_cm_poses
        return 1


@dataclass(frozen=True, eq=False)
class Trial:
    """Ground truth and initialisation of one simulated experiment (world = CT frame, mm, degrees).

    Attributes:
        workflow: one of :data:`WORKFLOWS`.
        side: femur side ("left" / "right").
        cameras: per image, the full-detector camera (multi-cm: the same camera repeated).
        world_from_patient: (4, 4) pelvis (whole patient) motion.
        world_from_femur: (4, 4) total femur motion.
        world_from_cm: (N, 4, 4) CM base pose per image (multi-view: the same pose repeated).
        control_points_deg: (5,) true control points.
        landmarks_px: (N, 2, 2) true projected landmarks A, B per image (full-detector pixels).
        entry_world: (3,) femur entry point after the motion.
        femoral_head_world: (3,) femoral head centre after the motion.
        pelvis_center_world: (3,) pelvis centre after the motion.
        initial_world_from_patient: (4, 4) perturbed initial CT pose.
        initial_world_from_cm: (N, 4, 4) perturbed initial CM bases.
        initial_control_points_deg: (5,) FBG readings (truth + noise).
        oracle_landmarks_px: (N, 2, 2) noisy 2D landmarks.
        pelvis_center_ct, femoral_head_ct, entry_ct: (3,) the landmarks in the unmoved CT.
    """

    workflow: str
    side: str
    cameras: tuple[Camera, ...]
    world_from_patient: np.ndarray
    world_from_femur: np.ndarray
    world_from_cm: np.ndarray
    control_points_deg: np.ndarray
    landmarks_px: np.ndarray
    entry_world: np.ndarray
    femoral_head_world: np.ndarray
    pelvis_center_world: np.ndarray
    initial_world_from_patient: np.ndarray
    initial_world_from_cm: np.ndarray
    initial_control_points_deg: np.ndarray
    oracle_landmarks_px: np.ndarray
    pelvis_center_ct: np.ndarray
    femoral_head_ct: np.ndarray
    entry_ct: np.ndarray
    cm_config: CMConfig = field(default_factory=CMConfig)

    @property
    def n_images(self) -> int:
        return len(self.cameras)


# ----- sampling helpers ---------------------------------------------------------------------------
def _unit_vector(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _rotation(rng: np.random.Generator, max_angle_deg: float, *, fixed: bool = False) -> np.ndarray:
    """(3, 3) rotation about a random unit axis by U(−max, max)° (exactly ``max`` when ``fixed``)."""
    angle = max_angle_deg if fixed else rng.uniform(-max_angle_deg, max_angle_deg)
    return Rotation.from_rotvec(math.radians(angle) * _unit_vector(rng)).as_matrix()


def _about(R: np.ndarray, center: np.ndarray, t: np.ndarray | None = None) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = center - R @ center + (0.0 if t is None else t)
    return T


def perturb_about(
    T: np.ndarray,
    center_world: np.ndarray,
    rng: np.random.Generator,
    *,
    rotation_deg: float,
    translation_mm: float,
) -> np.ndarray:
    """``T`` moved by a rotation of exactly ``rotation_deg`` about a random axis through
    ``center_world`` and a translation of exactly ``translation_mm`` in a random direction (world)."""
    D = _about(
        _rotation(rng, rotation_deg, fixed=True),
        np.asarray(center_world, np.float64),
        translation_mm * _unit_vector(rng),
    )
    return D @ T


def _landmark(volume: Volume, name: str) -> np.ndarray:
    if name not in volume.landmarks_world:
        raise ValueError(f"the CT has no landmark {name!r} (has {sorted(volume.landmarks_world)})")
    return np.asarray(volume.landmarks_world[name], dtype=np.float64)


def _cm_points_cm(kin: CMKinematics, cp: np.ndarray) -> np.ndarray:
    """(3, 3) A, B and the tip in CM coordinates."""
    cpt = torch.as_tensor(cp, dtype=torch.float64)
    lm = kin.landmarks_cm(cpt).numpy()
    return np.concatenate([lm, kin.tip_cm(cpt).numpy()[None]], axis=0)


def _in_view(cameras: list[Camera], world_from_cm: np.ndarray, pts_cm: np.ndarray, margin: float) -> bool:
    for cam in cameras:
        for T in world_from_cm:
            pts = pts_cm @ T[:3, :3].T + T[:3, 3]
            if np.any(cam.to_camera(pts)[:, 2] <= 0):
                return False
            uv = cam.project(pts)
            if (
                np.any(uv < margin)
                or np.any(uv[:, 0] > cam.cols - 1 - margin)
                or np.any(uv[:, 1] > cam.rows - 1 - margin)
            ):
                return False
    return True


def _small_motion(rng: np.random.Generator, rotation_deg: float, translation_mm: float) -> np.ndarray:
    """[R | t] in the moved frame: rotation U(−r, r)° about a random axis, t U(−t, t) per axis."""
    D = np.eye(4)
    D[:3, :3] = _rotation(rng, rotation_deg)
    D[:3, 3] = rng.uniform(-translation_mm, translation_mm, 3)
    return D


# ----- the protocol -------------------------------------------------------------------------------
def _anatomy(
    rng: np.random.Generator, cfg: ProtocolConfig, pelvis_ct: np.ndarray, head_ct: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Steps 1-2: ``(world_from_patient, world_from_femur)``."""
    t = rng.uniform(0.0, cfg.pelvis_translation_mm) * _unit_vector(rng)
    world_from_patient = _about(_rotation(rng, cfg.pelvis_rotation_deg), pelvis_ct, t)
    world_from_femur = world_from_patient @ _about(_rotation(rng, cfg.femur_rotation_deg), head_ct)
    return world_from_patient, world_from_femur


def _carm_views(
    workflow: str, rng: np.random.Generator, cfg: ProtocolConfig, head_w: np.ndarray
) -> list[Camera]:
    """Step 4: the AP view about the femoral head, and for multi-view the orbited views."""
    iso = head_w + rng.uniform(-cfg.isocenter_jitter_mm, cfg.isocenter_jitter_mm, 3)
    j = cfg.angle_jitter_deg
    ap = carm_camera(
        lao_rao_deg=rng.uniform(-j, j),
        cran_caud_deg=cfg.cran_caud_deg + rng.uniform(-j, j),
        source_to_isocenter_mm=rng.uniform(*cfg.source_to_isocenter_mm),
        isocenter_world=iso,
        detector=cfg.detector,
    )
    views = [ap]
    if workflow == "multi-view":
        views += [
            orbit_camera(ap, angle_deg=rng.normal(m, s), isocenter_world=iso) for m, s in cfg.view_offsets_deg
        ]
    return views


def _cm_poses(
    rng: np.random.Generator,
    cfg: ProtocolConfig,
    world_from_patient: np.ndarray,
    head_w: np.ndarray,
    entry_w: np.ndarray,
    views: list[Camera],
    pts_cm: np.ndarray,
    n: int,
    *,
    multi_cm: bool,
) -> np.ndarray:
    """Steps 5-6: the (n, 4, 4) CM poses, redrawn until in view. Nominal axis: the femoral neck
    direction (entry → head) in the patient's coronal plane, so that the AP view sees the CM
    side-on."""
    anterior = world_from_patient[:3, :3] @ _ANTERIOR
    neck = head_w - entry_w
    neck -= neck.dot(anterior) * anterior
    neck /= np.linalg.norm(neck)
    for _ in range(cfg.max_redraws):
        origin = head_w + rng.uniform(*cfg.cm_anterior_mm) * anterior - rng.uniform(*cfg.cm_setback_mm) * neck
        base = cm_pose_along(origin, neck, rng.uniform(0.0, 2.0 * math.pi))
        base = base @ _small_motion(rng, cfg.cm_rotation_deg, cfg.cm_translation_mm)
        if multi_cm:
            poses = np.stack(
                [
                    base @ _small_motion(rng, cfg.multi_cm_rotation_deg, cfg.multi_cm_translation_mm)
                    for _ in range(cfg.multi_cm_poses)
                ]
            )
        else:
            poses = np.repeat(base[None], n, axis=0)
        if _in_view(views, poses, pts_cm, cfg.margin_px):
            return poses
    raise ValueError(f"no CM pose in view after {cfg.max_redraws} draws; check the protocol ranges")


def _initial_cm_poses(rng: np.random.Generator, cfg: ProtocolConfig, poses: np.ndarray) -> np.ndarray:
    """Step 7 for the CM: each base pose perturbed about its origin A."""
    return np.stack(
        [
            perturb_about(
                T,
                T[:3, 3],
                rng,
                rotation_deg=cfg.init_cm_rotation_deg,
                translation_mm=cfg.init_cm_translation_mm,
            )
            for T in poses
        ]
    )


def sample_trial(
    workflow: str,
    volume: Volume,
    rng: np.random.Generator,
    *,
    side: str = "left",
    config: ProtocolConfig | None = None,
    cm_config: CMConfig | None = None,
) -> Trial:
    """Sample one trial of ``workflow`` (see the module docstring); deterministic for ``rng``'s state.

    Raises:
        ValueError: unknown workflow, missing landmarks, or no CM pose in view after
            ``config.max_redraws`` draws.
    """
    if workflow not in WORKFLOWS:
        raise ValueError(f"unknown workflow {workflow!r}; use one of {', '.join(WORKFLOWS)}")
    cfg = config or ProtocolConfig()
    cm_config = cm_config or CMConfig()
    kin = CMKinematics(cm_config)
    head_ct = _landmark(volume, f"femoral_head_{side}")
    entry_ct = _landmark(volume, f"entry_{side}")
    pelvis_ct = (
        _landmark(volume, "pelvis_center")
        if "pelvis_center" in volume.landmarks_world
        else volume.center_world
    )
    # the draws in the module docstring's order: the anatomy, the shape, the C-arm, the CM, the noise
    world_from_patient, world_from_femur = _anatomy(rng, cfg, pelvis_ct, head_ct)
    head_w = (world_from_femur @ np.append(head_ct, 1.0))[:3]
    entry_w = (world_from_femur @ np.append(entry_ct, 1.0))[:3]
    pelvis_w = (world_from_patient @ np.append(pelvis_ct, 1.0))[:3]
    cp = rng.uniform(*cfg.control_point_range_deg, size=cm_config.n_control_points)
    pts_cm = _cm_points_cm(kin, cp)
    views = _carm_views(workflow, rng, cfg, head_w)
    n = cfg.n_images(workflow)
    poses = _cm_poses(
        rng, cfg, world_from_patient, head_w, entry_w, views, pts_cm, n, multi_cm=workflow in _MULTI_CM
    )
    cameras = tuple(views) if len(views) == n else tuple([views[0]] * n)
    landmarks = np.stack(
        [cam.project(pts_cm[:2] @ T[:3, :3].T + T[:3, 3]) for cam, T in zip(cameras, poses, strict=True)]
    )
    init_patient = perturb_about(
        world_from_patient,
        pelvis_w,
        rng,
        rotation_deg=cfg.init_ct_rotation_deg,
        translation_mm=cfg.init_ct_translation_mm,
    )
    init_cm = _initial_cm_poses(rng, cfg, poses)
    init_cp = cp + rng.uniform(-cfg.fbg_noise_deg, cfg.fbg_noise_deg, size=cp.shape)
    oracle = landmarks + rng.uniform(-cfg.landmark_noise_px, cfg.landmark_noise_px, size=landmarks.shape)
    return Trial(
        workflow=workflow,
        side=side,
        cameras=cameras,
        world_from_patient=world_from_patient,
        world_from_femur=world_from_femur,
        world_from_cm=poses,
        control_points_deg=cp,
        landmarks_px=landmarks,
        entry_world=entry_w,
        femoral_head_world=head_w,
        pelvis_center_world=pelvis_w,
        initial_world_from_patient=init_patient,
        initial_world_from_cm=init_cm,
        initial_control_points_deg=init_cp,
        oracle_landmarks_px=oracle,
        pelvis_center_ct=pelvis_ct,
        femoral_head_ct=head_ct,
        entry_ct=entry_ct,
        cm_config=cm_config,
    )


def simulate_trial_images(
    trial: Trial, simulator: ArticulatedSimulator, *, seed: int, image_size: int = 768
) -> list[SimulatedImage]:
    """The trial's X-ray images (image ``i`` uses noise seed ``seed + i``), at ``image_size``²."""
    if simulator.femur_side != trial.side:
        raise ValueError(f"the simulator moves the {simulator.femur_side} femur, the trial the {trial.side}")
    return [
        simulator.simulate(
            cam,
            world_from_patient=trial.world_from_patient,
            world_from_femur=trial.world_from_femur,
            cm=(T, trial.control_points_deg),
            seed=seed + i,
            image_size=image_size,
            cm_config=trial.cm_config,
        )
        for i, (cam, T) in enumerate(zip(trial.cameras, trial.world_from_cm, strict=True))
    ]
