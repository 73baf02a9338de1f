"""A robot holding the CM over the hip phantom: the simulated scene of the navigation and hand-eye studies.

World = the CT frame of the phantom before the patient moved (LPS, mm). The robot is a UR-10 whose physical
kinematics differ from the controller's nominal model by :class:`~fluoronav.manipulator.robot.RobotErrorModel`
defaults (seeded per scene), with encoder noise per reading: the controller sees the *nominal* forward
kinematics of the commanded joints, the truth is the true robot at the actual joints
(:meth:`HandEyeScenario.execute`). The mount ``ee_from_cm`` is a plausible hand-made one; the C-arm and the
working CM pose follow the paper's protocol (:func:`~fluoronav.simulation.protocol.sample_trial`,
"navigation"), the robot base placed so that a working joint configuration holds the CM there. Hand-eye poses
move the working pose (CM frame), reached through the nominal IK and kept in the image. Images:
:class:`~fluoronav.simulation.articulated.ArticulatedSimulator`; magnitudes: docs/robot-and-calibration.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from fluoronav.geometry import se3
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.manipulator.robot import UR10, IKFailure, RobotErrorModel, SerialRobot, wrap_deg
from fluoronav.simulation.protocol import sample_trial

__all__ = [
    "HOME_DEG",
    "HandEyeScenario",
    "cm_centre",
    "in_view",
    "perturb_transform",
    "random_rotation",
    "sample_handeye_scenario",
    "simulate_scenario_images",
    "verification_view_centre",
    "working_view_centre",
]

HOME_DEG = np.array([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])


@dataclass(frozen=True, eq=False)
class HandEyeScenario:
    """Truth of one hand-eye / navigation trial (world = CT frame).

    Attributes:
        camera: full-detector C-arm camera (static).
        nominal, true_robot: controller model and physical robot; error_model: their difference.
        world_from_rbase: (4, 4) robot base; ee_from_cm: (4, 4) true hand-eye matrix.
        q_work_deg: (6,) working configuration; q_deg: (M, 6) commanded hand-eye configurations.
        q_actual_deg: (M, 6) where the joints physically were.
        rbase_from_ee_reported: (M, 4, 4) nominal FK of ``q_deg`` (the calibration's data).
        world_from_cm: (M, 4, 4) true CM poses; control_points_deg: (5,) true shape.
        landmarks_px: (M, 2, 2) true landmarks, full-detector px; trial: the protocol sample.
    """

    camera: Camera
    nominal: SerialRobot
    true_robot: SerialRobot
    error_model: RobotErrorModel
    world_from_rbase: np.ndarray
    ee_from_cm: np.ndarray
    q_work_deg: np.ndarray
    q_deg: np.ndarray
    q_actual_deg: np.ndarray
    rbase_from_ee_reported: np.ndarray
    world_from_cm: np.ndarray
    control_points_deg: np.ndarray
    landmarks_px: np.ndarray
    trial: Any
    cm_config: CMConfig = field(default_factory=CMConfig)

    @property
    def n_poses(self) -> int:
        return int(self.q_deg.shape[0])

    def true_world_from_cm(self, q_actual_deg: np.ndarray) -> np.ndarray:
        """(..., 4, 4) true CM pose with the joints physically at ``q_actual_deg``."""
        return self.world_from_rbase @ self.true_robot.rbase_from_ee(q_actual_deg) @ self.ee_from_cm

    def execute(self, q_deg: np.ndarray, *, rng: np.random.Generator) -> np.ndarray:
        """Move the true robot to the commanded joints ``q_deg`` (encoder noise on where they end
        up) → (4, 4) true ``world_from_cm`` where the CM physically is."""
        return self.true_world_from_cm(self.error_model.actual_joints_deg(q_deg, rng=rng))


def random_rotation(rng: np.random.Generator, max_deg: float, *, fixed: bool = False) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    ang = max_deg if fixed else rng.uniform(-max_deg, max_deg)
    return Rotation.from_rotvec(np.radians(ang) * axis).as_matrix()


def perturb_transform(
    T: np.ndarray, rng: np.random.Generator, rotation_deg: float, translation_mm: float
) -> np.ndarray:
    """``T`` · δ with δ a rotation of exactly ``rotation_deg`` about a random axis (about T's origin)
    and a translation of exactly ``translation_mm`` in a random direction (T's frame)."""
    d = rng.normal(size=3)
    return T @ se3.make(
        random_rotation(rng, rotation_deg, fixed=True), translation_mm * d / np.linalg.norm(d)
    )


def in_view(camera: Camera, world_from_cm: np.ndarray, pts_cm: np.ndarray, margin: float) -> bool:
    pts = pts_cm @ world_from_cm[:3, :3].T + world_from_cm[:3, 3]
    if np.any(camera.to_camera(pts)[:, 2] <= 0):
        return False
    uv = camera.project(pts)
    return bool(
        np.all(uv >= margin)
        and np.all(uv[:, 0] <= camera.cols - 1 - margin)
        and np.all(uv[:, 1] <= camera.rows - 1 - margin)
    )


def cm_centre(frame_from_cm: np.ndarray) -> np.ndarray:
    """(3,) the point 15 mm along the CM's axis from A (about the middle of its notched part) in the
    frame of the pose ``frame_from_cm`` (4, 4): what a person centres the C-arm on."""
    return (np.asarray(frame_from_cm, np.float64) @ np.array([0.0, 0.0, 15.0, 1.0]))[:3]


def verification_view_centre(femur_from_cm_target: np.ndarray, femoral_head_femur: np.ndarray) -> np.ndarray:
    """(3,) femur-frame point a verification C-arm centres: midway between the femoral head and the
    planned CM, so that the CM where the robot took it, the neck and the acetabulum are in view."""
    return 0.5 * (cm_centre(femur_from_cm_target) + np.asarray(femoral_head_femur, np.float64))


def working_view_centre(trial: Any) -> np.ndarray:
    """(3,) world point the C-arm centres for the first registration: midway between the femoral
    head and the working CM's centre (15 mm along its axis from A), so that the CM, the neck and the
    acetabulum are in view (the pelvis registration fails when only the trochanter region is
    imaged). The CM at the plan is imaged afterwards from a C-arm slid towards it."""
    return 0.5 * (np.asarray(trial.femoral_head_world, np.float64) + cm_centre(trial.world_from_cm[0]))


def _place_robot(
    rng: np.random.Generator, world_from_cm_work: np.ndarray
) -> tuple[RobotErrorModel, SerialRobot, np.ndarray, np.ndarray, np.ndarray]:
    """The robot's error model and true robot, the mount ``ee_from_cm``, the working joints (deg) and
    the base ``world_from_rbase`` that holds the CM at ``world_from_cm_work`` with them."""
    model = RobotErrorModel(seed=int(rng.integers(2**31)))
    true_robot = model.true_robot(UR10)
    # mount: CM base ~150-250 mm along the tool axis, small lateral offset and rotation
    ee_from_cm = se3.make(
        random_rotation(rng, 10.0), [rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(150.0, 250.0)]
    )
    q_work = HOME_DEG + rng.uniform(-10.0, 10.0, 6)
    world_from_rbase = world_from_cm_work @ np.linalg.inv(true_robot.rbase_from_ee(q_work) @ ee_from_cm)
    return model, true_robot, ee_from_cm, q_work, world_from_rbase


def sample_handeye_scenario(
    volume: Any,
    rng: np.random.Generator,
    *,
    n_poses: int,
    rotation_spread_deg: float = 25.0,
    translation_spread_mm: float = 10.0,
    margin_px: float = 100.0,
    cm_config: CMConfig | None = None,
    max_redraws: int = 400,
    bend_deg: float | None = None,
) -> HandEyeScenario:
    """Sample robot, mount, C-arm, working pose and ``n_poses`` hand-eye poses (module docstring).

    ``bend_deg``: the CM shape of the hand-eye poses: every control point ±(``bend_deg`` +
    U(−0.5, 0.5))° with one random sign (a planar C-bend); None keeps the trial's working shape.

    Raises:
        ValueError: when not enough reachable in-view poses are found in ``max_redraws`` draws.
    """
    cm_config = cm_config or CMConfig()
    kin = CMKinematics(cm_config)
    trial = sample_trial("navigation", volume, rng, cm_config=cm_config)
    cp = trial.control_points_deg
    if bend_deg is not None:
        sign = 1.0 if rng.random() < 0.5 else -1.0
        cp = sign * (bend_deg + rng.uniform(-0.5, 0.5, cm_config.n_control_points))
    cpt = torch.as_tensor(cp, dtype=torch.float64)
    pts_cm = np.concatenate([kin.landmarks_cm(cpt).numpy(), kin.tip_cm(cpt).numpy()[None]])
    camera = trial.cameras[0]
    world_cm_work = trial.world_from_cm[0]
    model, true_robot, ee_from_cm, q_work, world_from_rbase = _place_robot(rng, world_cm_work)
    rbase_from_world = np.linalg.inv(world_from_rbase)
    q: list[np.ndarray] = []
    q_act: list[np.ndarray] = []
    for _ in range(max_redraws):
        if len(q) == n_poses:
            break
        d = se3.make(
            random_rotation(rng, rotation_spread_deg),
            rng.uniform(-translation_spread_mm, translation_spread_mm, 3),
        )
        target = rbase_from_world @ world_cm_work @ d @ np.linalg.inv(ee_from_cm)
        sol = UR10.inverse_kinematics(target, q_reference_deg=q_work)
        if isinstance(sol, IKFailure) or np.max(np.abs(wrap_deg(sol.q_deg - q_work))) > 90.0:
            continue
        qa = model.actual_joints_deg(sol.q_deg, rng=rng)
        W = world_from_rbase @ true_robot.rbase_from_ee(qa) @ ee_from_cm
        if not in_view(camera, W, pts_cm, margin_px):
            continue
        q.append(sol.q_deg)
        q_act.append(qa)
    if len(q) < n_poses:
        raise ValueError(f"only {len(q)} of {n_poses} reachable in-view robot poses in {max_redraws} draws")
    qd, qa = np.asarray(q).reshape(-1, 6), np.asarray(q_act).reshape(-1, 6)
    W = world_from_rbase @ true_robot.rbase_from_ee(qa) @ ee_from_cm if len(q) else np.zeros((0, 4, 4))
    lm = np.asarray([camera.project(pts_cm[:2] @ T[:3, :3].T + T[:3, 3]) for T in W]).reshape(-1, 2, 2)
    return HandEyeScenario(
        camera=camera,
        nominal=UR10,
        true_robot=true_robot,
        error_model=model,
        world_from_rbase=world_from_rbase,
        ee_from_cm=ee_from_cm,
        q_work_deg=q_work,
        q_deg=qd,
        q_actual_deg=qa,
        rbase_from_ee_reported=UR10.rbase_from_ee(qd) if len(q) else np.zeros((0, 4, 4)),
        world_from_cm=W,
        control_points_deg=cp,
        landmarks_px=lm,
        trial=trial,
        cm_config=cm_config,
    )


def simulate_scenario_images(
    scenario: HandEyeScenario,
    simulator: Any,
    *,
    seed: int,
    image_size: int,
    world_from_cm: np.ndarray | None = None,
    camera: Camera | None = None,
) -> list[Any]:
    """Physics images of the CM at ``world_from_cm`` (default: the scenario's M poses) over the
    phantom at the trial's anatomy pose, seen by ``camera`` (default the scenario's); image m uses
    noise seed ``seed + m``."""
    tr = scenario.trial
    poses = scenario.world_from_cm if world_from_cm is None else np.asarray(world_from_cm).reshape(-1, 4, 4)
    return [
        simulator.simulate(
            scenario.camera if camera is None else camera,
            world_from_patient=tr.world_from_patient,
            world_from_femur=tr.world_from_femur,
            cm=(T, scenario.control_points_deg),
            seed=seed + m,
            image_size=image_size,
            cm_config=scenario.cm_config,
        )
        for m, T in enumerate(poses)
    ]
