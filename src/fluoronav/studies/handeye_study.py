"""The ``hand-eye`` and ``navigation`` simulation studies (``fluoronav study hand-eye|navigation``).

Setting (both studies; world = CT frame of the phantom, LPS mm):

- Robot: a UR-10 whose physical kinematics differ from the controller's nominal model by
  :class:`~fluoronav.calibration.robot.RobotErrorModel` defaults (seeded per trial), with encoder
  noise per reading. The data the methods see are the *nominal* forward kinematics of the commanded
  joints; the truth is the true robot at the actual joints.
- Mount: true ``ee_from_cm``: the CM base origin 150–250 mm along the flange's tool axis, ±5 mm
  laterally, rotated by U(0, 10)° about a random axis (a plausible hand-made mount).
- C-arm and CM: one static AP C-arm (CIOS Fusion, isocentre near the CM) and a working CM pose as
  the paper's protocol (:func:`~fluoronav.studies.protocol.sample_trial`, "navigation": the CM
  above the femoral head, side-on to the view). The robot base is placed so that a working joint
  configuration (UR-10 "home" ± 10° per joint) holds the CM at that pose.
- Hand-eye poses: M CM poses, each the working pose moved by a rotation of U(−25, 25)° about a random
  axis and U(−10, 10) mm per axis (CM frame), reached through the nominal IK; poses whose landmarks or
  tip leave the image (100 px margin) are redrawn. One shape for all (the paper keeps the curvature
  constant during calibration): bent in one plane, control points ±(``calibration_bend_deg`` +
  U(−0.5, 0.5))° (default 2.5°: a ~70° C-bend, tip ~18 mm off the base axis), because the roll of
  the hand-eye about the CM axis is seen only through the bend (seed 6701, random U(−5, 5)° shapes:
  roll 0.35° mean, 1.01° on the least bent CM). The navigation study keeps the working shape.
- Images: :class:`~fluoronav.simulation.articulated.ArticulatedSimulator` (physics, the CM over the
  hip phantom; never the registration's renderer). Landmarks: the truth + U(−3, 3) full-detector px
  (oracle, as the authors' code) — the shipped detector is used when one is available.

Hand-eye trial: the image-based calibration
(:func:`~fluoronav.calibration.image_handeye.calibrate_hand_eye_from_images`) for each M of
``poses`` (nested: the first M images; errors vs M), initial hand-eye = truth perturbed by the
authors' 10° / 10 mm, FBG = truth + U(−0.5, 0.5)°. The tracker baseline (AX = XB, Tsai, on the
simulated shaft marker O_s) and its eq. 9 tip error run on the same poses.

Navigation trial: register the CM (single view; initial pose the truth moved by the authors'
10° / 10 mm, or the centreline initialisation) and, with
``register_bones``, pelvis and femur in the one AP image; plan = the femur entry point with the CM
tip on it and the CM axis along the femoral neck (entry → head centre); eq. 8 / IK with the nominal
model and a hand-eye of documented error (the truth perturbed by ``handeye_error_deg`` /
``handeye_error_mm``, our image-based calibration's measured accuracy); move the *true* robot; the
repositioning error is the distance of the true tip from the planned tip: ``reposition_open_loop_mm``
after the first move, ``reposition_tip_mm`` after ``corrections`` corrective moves (default 1), each
computed from new simulated images at the reached pose (:func:`_verify`: the C-arm slid to centre
the femoral head and the planned CM, ``verify_views`` views; pelvis, femur and CM registered anew,
the CM initialised at the plan) whose femur and CM poses replace the first ones in eqs. 7–8
(``reposition_registered_mm``: the first verification's registered tip against the plan, what the
surgeon would see).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from fluoronav.calibration import _se3
from fluoronav.calibration.results import HandEyeFailure
from fluoronav.calibration.robot import UR10, IKFailure, RobotErrorModel, SerialRobot, wrap_deg
from fluoronav.errors import FluoronavError, InputError
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.studies.runner import finish_row, mark_failed, new_row

__all__ = [
    "HANDEYE_METRICS",
    "NAVIGATION_METRICS",
    "HandEyeScenario",
    "HandEyeStudyConfig",
    "run_handeye_or_navigation_study",
    "run_handeye_trial",
    "run_navigation_trial",
    "sample_handeye_scenario",
    "simulate_scenario_images",
]

log = logging.getLogger(__name__)

HOME_DEG = np.array([0.0, -90.0, 90.0, -90.0, -90.0, 0.0])
CM_METRICS = ("tip_mm", "base_translation_mm", "base_rotation_deg", "notch_rotation_deg")
HANDEYE_METRICS = (
    "handeye_translation_mm",
    "handeye_rotation_deg",
    "handeye_tip_mm",
    *CM_METRICS,
    "baseline_tip_mm",
    "baseline_translation_mm",
    "baseline_rotation_deg",
    "eq9_vs_eq10_mm",
)
#: the hand-eye rotation error split into the tilt of the CM axis and the roll about it (rows, summary)
HANDEYE_DIAGNOSTICS = ("handeye_axis_deg", "handeye_roll_deg")
NAVIGATION_METRICS = (
    "reposition_tip_mm",
    "reposition_open_loop_mm",
    "reposition_registered_mm",
    "tip_mm",
    "entry_mm",
    "relative_mm",
    "base_translation_mm",
    "base_rotation_deg",
    "notch_rotation_deg",
)
#: navigation rows' further summarised figures: the robot-only error of the first move, the CM axis
#: against the plan, and the verification registration's own errors against the truth
NAVIGATION_DIAGNOSTICS = (
    "reposition_robot_mm",
    "reposition_axis_deg",
    "reposition_open_loop_axis_deg",
    "verify_entry_mm",
    "verify_tip_mm",
    "verify_relative_mm",
)


class _TrialFailure(FluoronavError):
    pass


@dataclass(frozen=True)
class HandEyeStudyConfig:
    """Settings of a hand-eye or navigation study (recorded in ``DIR/config.json``).

    Attributes:
        workflow: "hand-eye" or "navigation".
        poses: hand-eye: numbers of robot poses M evaluated per trial (nested subsets of the largest).
        image_size: simulated image rows = cols (the 1536² detector binned).
        rotation_spread_deg, translation_spread_mm: hand-eye pose sampling about the working pose.
        init_rotation_deg, init_translation_mm: initial hand-eye = truth perturbed by exactly these.
        handeye_error_deg, handeye_error_mm: navigation: hand-eye used = truth perturbed by these.
        register_bones: navigation: register pelvis and femur (else the true femur pose is used).
        navigation_init: initial CM pose of the navigation registration: "perturbed" (the truth moved
            by the authors' 10° / 10 mm, as their simulation code) or "centerline" (from the image).
        corrections: navigation: corrective moves after the first, each from a registration of a new
            image at the reached pose (eqs. 7–8 again from the reached joints); the first move's
            rotation error of the registration is multiplied by its length, a correction is short.
        verify_views, verify_orbit_deg: navigation: the images at a reached pose: the C-arm slid to
            centre the femoral head and the planned CM (estimated), an AP view and views orbited by
            ± ``verify_orbit_deg``; pelvis (per view), femur and CM are registered anew in them
            (multi-view for 2 or more), so that the correction does not reuse the first femur error.
            Three by default: with two (AP and 25°) the verification of seed-5605 trial 8 put the
            CM tip 5.1 mm off relative to the femur entry and the correction took the tip from
            1.5 to 5.5 mm from the plan; with three, 0.2 mm and 0.9 mm.
        tracker_sigma_mm: baseline tracker marker noise per axis.
        calibration_bend_deg: hand-eye: the CM's bend during calibration, degrees per control point
            (each + U(−0.5, 0.5), one sign); None: the protocol's random working shape (U(−5, 5)°).
        oracle_landmarks: use truth + U(−3, 3) px even when a detector is available.
    """

    workflow: str
    trials: int
    seed: int
    ct: str = "phantom"
    poses: tuple[int, ...] = (4, 8, 15)
    image_size: int = 768
    device: str = "cpu"
    rotation_spread_deg: float = 25.0
    translation_spread_mm: float = 10.0
    init_rotation_deg: float = 10.0
    init_translation_mm: float = 10.0
    handeye_error_deg: float = 0.4
    handeye_error_mm: float = 0.5
    register_bones: bool = True
    navigation_init: str = "perturbed"
    corrections: int = 1
    verify_views: int = 3
    verify_orbit_deg: float = 25.0
    tracker_sigma_mm: float = 0.1
    calibration_bend_deg: float | None = 2.5
    oracle_landmarks: bool = True


# ----- scenario -----------------------------------------------------------------------------------
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
    cm_config: CMConfig = dataclasses.field(default_factory=CMConfig)

    @property
    def n_poses(self) -> int:
        return int(self.q_deg.shape[0])

    def true_world_from_cm(self, q_actual_deg: np.ndarray) -> np.ndarray:
        """(..., 4, 4) true CM pose with the joints physically at ``q_actual_deg``."""
        return self.world_from_rbase @ self.true_robot.rbase_from_ee(q_actual_deg) @ self.ee_from_cm

    def move_to_plan(
        self,
        q_from_deg: np.ndarray,
        *,
        ee_from_cm: np.ndarray,
        carm_from_femur: np.ndarray,
        carm_from_cm: np.ndarray,
        femur_from_cm_target: np.ndarray,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Command the nominal robot from ``q_from_deg`` by eqs. 7–8 + IK and move the true one.

        Returns:
            (commanded joints (6,), true ``world_from_cm`` (4, 4) where the CM physically ends up).
        """
        from fluoronav.navigation.navigate import robot_target

        _, q = robot_target(
            self.nominal,
            q_from_deg,
            ee_from_cm=ee_from_cm,
            carm_from_femur=carm_from_femur,
            carm_from_cm=carm_from_cm,
            femur_from_cm_target=femur_from_cm_target,
        )
        return q, self.true_world_from_cm(self.error_model.actual_joints_deg(q, rng=rng))


def _random_rotation(rng: np.random.Generator, max_deg: float, *, fixed: bool = False) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    ang = max_deg if fixed else rng.uniform(-max_deg, max_deg)
    return Rotation.from_rotvec(np.radians(ang) * axis).as_matrix()


def _perturb(
    T: np.ndarray, rng: np.random.Generator, rotation_deg: float, translation_mm: float
) -> np.ndarray:
    """``T`` · δ with δ a rotation of exactly ``rotation_deg`` about a random axis (about T's origin)
    and a translation of exactly ``translation_mm`` in a random direction (T's frame)."""
    d = rng.normal(size=3)
    return T @ _se3.make(
        _random_rotation(rng, rotation_deg, fixed=True), translation_mm * d / np.linalg.norm(d)
    )


def _in_view(camera: Camera, world_from_cm: np.ndarray, pts_cm: np.ndarray, margin: float) -> bool:
    pts = pts_cm @ world_from_cm[:3, :3].T + world_from_cm[:3, 3]
    if np.any(camera.to_camera(pts)[:, 2] <= 0):
        return False
    uv = camera.project(pts)
    return bool(
        np.all(uv >= margin)
        and np.all(uv[:, 0] <= camera.cols - 1 - margin)
        and np.all(uv[:, 1] <= camera.rows - 1 - margin)
    )


def recentre(camera: Camera, from_world: np.ndarray, to_world: np.ndarray) -> Camera:
    """The camera translated (no rotation) so that the point it showed at ``from_world`` is now at
    ``to_world``: the C-arm slid on the floor to centre another point."""
    shift = np.eye(4)
    shift[:3, 3] = -(np.asarray(to_world, np.float64) - np.asarray(from_world, np.float64))
    return camera.with_pose(camera.camera_from_world @ shift)


def centre_on(camera: Camera, target_world: np.ndarray) -> Camera:
    """The camera translated (no rotation) so that ``target_world`` projects to the image centre at
    its present depth: the C-arm slid on the floor until the point is on its central ray."""
    uv0 = np.array([(camera.cols - 1) / 2.0, (camera.rows - 1) / 2.0])
    target = np.asarray(target_world, np.float64)
    return recentre(camera, camera.backproject(uv0, float(camera.to_camera(target)[2])), target)


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
    from fluoronav.studies.protocol import sample_trial

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
    model = RobotErrorModel(seed=int(rng.integers(2**31)))
    true_robot = model.true_robot(UR10)
    # mount: CM base ~150-250 mm along the tool axis, small lateral offset and rotation
    ee_from_cm = _se3.make(
        _random_rotation(rng, 10.0), [rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(150.0, 250.0)]
    )
    q_work = HOME_DEG + rng.uniform(-10.0, 10.0, 6)
    world_cm_work = trial.world_from_cm[0]
    world_from_rbase = world_cm_work @ np.linalg.inv(true_robot.rbase_from_ee(q_work) @ ee_from_cm)
    rbase_from_world = np.linalg.inv(world_from_rbase)
    q: list[np.ndarray] = []
    q_act: list[np.ndarray] = []
    for _ in range(max_redraws):
        if len(q) == n_poses:
            break
        d = _se3.make(
            _random_rotation(rng, rotation_spread_deg),
            rng.uniform(-translation_spread_mm, translation_spread_mm, 3),
        )
        target = rbase_from_world @ world_cm_work @ d @ np.linalg.inv(ee_from_cm)
        sol = UR10.inverse_kinematics(target, q_reference_deg=q_work)
        if isinstance(sol, IKFailure) or np.max(np.abs(wrap_deg(sol.q_deg - q_work))) > 90.0:
            continue
        qa = model.actual_joints_deg(sol.q_deg, rng=rng)
        W = world_from_rbase @ true_robot.rbase_from_ee(qa) @ ee_from_cm
        if not _in_view(camera, W, pts_cm, margin_px):
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


# ----- per-process caches -------------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def _detector_or_none(device: str) -> Any:
    """The shipped detector, or None when no model is shipped (then oracle landmarks are used)."""
    from fluoronav.detection.detector import Detector

    try:
        return Detector.load(None, device=device)
    except FluoronavError as exc:
        log.info("no detector model (%s): oracle landmarks", exc)
        return None


def _landmarks(
    images: list[Any], true_full_px: np.ndarray, rng: np.random.Generator, cfg: HandEyeStudyConfig
) -> tuple[list[np.ndarray], str]:
    """Landmarks per image (image px) and their source ("detector" or "oracle")."""
    det = None if cfg.oracle_landmarks else _detector_or_none(cfg.device)
    out = []
    for im, lm_full in zip(images, true_full_px, strict=True):
        b = (
            max(1, round(1536 / im.camera.cols))
            if im.camera.pixel_spacing_mm is None
            else max(1, round(im.camera.pixel_spacing_mm / 0.194))
        )
        oracle = (lm_full + rng.uniform(-3.0, 3.0, (2, 2)) + 0.5) / b - 0.5
        if det is None:
            out.append(oracle)
            continue
        d = det.detect(im.image, pixel_spacing_mm=im.camera.pixel_spacing_mm)
        if not d.usable:
            raise _TrialFailure(f"detector: {d.unusable_reason} in a hand-eye image")
        out.append(np.asarray(d.landmarks_px, np.float64))
    return out, "oracle" if det is None else "detector"


def _axis_and_roll_deg(ee_from_cm_est: np.ndarray, ee_from_cm_true: np.ndarray) -> dict[str, float]:
    """Split the hand-eye rotation error into the tilt of the CM axis (z) and the roll about it."""
    R = ee_from_cm_true[:3, :3].T @ ee_from_cm_est[:3, :3]  # error in the true CM frame
    tilt = math.degrees(math.acos(float(np.clip(R[2, 2], -1.0, 1.0))))
    # roll: the rotation left after aligning the estimated z axis with the true one
    z = R[:, 2]
    axis = np.cross(z, [0.0, 0.0, 1.0])
    n = float(np.linalg.norm(axis))
    align = np.eye(3) if n < 1e-12 else Rotation.from_rotvec(axis / n * math.asin(min(1.0, n))).as_matrix()
    if z[2] < 0 and n >= 1e-12:
        align = Rotation.from_rotvec(axis / n * (math.pi - math.asin(min(1.0, n)))).as_matrix()
    Rz = align @ R
    return {"handeye_axis_deg": tilt, "handeye_roll_deg": abs(math.degrees(math.atan2(Rz[1, 0], Rz[0, 0])))}


def _tip_rbase(
    rbase_from_ee: np.ndarray, ee_from_cm: np.ndarray, cp: np.ndarray, kin: CMKinematics
) -> np.ndarray:
    T = rbase_from_ee @ ee_from_cm
    tip = kin.tip_cm(torch.as_tensor(np.asarray(cp, np.float64))).numpy()
    return np.einsum("...ij,j->...i", T[..., :3, :3], tip) + T[..., :3, 3]


def _tracker_baseline(
    sc: HandEyeScenario, rng: np.random.Generator, sigma_mm: float, kin: CMKinematics
) -> dict[str, Any]:
    """AX = XB (Tsai) on the shaft marker O_s and the eq. 9 tip through the tip-segment marker O_t."""
    from fluoronav.calibration.handeye import (
        calibrate_hand_eye,
        tip_rbase_tracker_chain,
        transform_error,
    )
    from fluoronav.calibration.tracker import DEFAULT_BODY, OpticalTracker

    tracker = OpticalTracker(marker_sigma_mm=sigma_mm)
    # O_s on the shaft 60 mm behind the CM base; the tracker ~1.5 m from the robot base
    cm_from_os = _se3.make(_random_rotation(rng, 30.0), [30.0, 0.0, -60.0])
    ee_from_os = sc.ee_from_cm @ cm_from_os
    rbase_from_tracker = _se3.make(_random_rotation(rng, 180.0), [1500.0, 0.0, 500.0])
    tracker_from_rbase = np.linalg.inv(rbase_from_tracker)
    rbase_ee_true = sc.true_robot.rbase_from_ee(sc.q_actual_deg)
    t_os = tracker.track(
        tracker_from_rbase @ rbase_ee_true @ ee_from_os, DEFAULT_BODY, rng=rng
    ).tracker_from_body
    # O_t on the last link (the tip segment), its frame offset 10 mm from the link frame
    link = kin.link_transforms(torch.as_tensor(sc.control_points_deg, dtype=torch.float64))[-1].numpy()
    cm_from_ot = link @ _se3.make(np.eye(3), [15.0, 0.0, 0.0])
    tip_cm = kin.tip_cm(torch.as_tensor(sc.control_points_deg, dtype=torch.float64)).numpy()
    tip_ot = (np.linalg.inv(cm_from_ot) @ np.append(tip_cm, 1.0))[:3]
    t_ot = tracker.track(
        tracker_from_rbase @ rbase_ee_true @ sc.ee_from_cm @ cm_from_ot, DEFAULT_BODY, rng=rng
    ).tracker_from_body
    res = calibrate_hand_eye(sc.rbase_from_ee_reported, t_os, method="TSAI")
    if isinstance(res, HandEyeFailure):
        return {"baseline_reason": res.reason}
    X = res.ee_from_marker
    tip9 = tip_rbase_tracker_chain(sc.rbase_from_ee_reported, X, t_os, t_ot, tip_ot)
    tip_true = _tip_rbase(rbase_ee_true, sc.ee_from_cm, sc.control_points_deg, kin)
    rot, trans = transform_error(X @ np.linalg.inv(cm_from_os), sc.ee_from_cm)
    return {
        "baseline_tip_mm": float(np.linalg.norm(tip9 - tip_true, axis=1).mean()),
        "baseline_rotation_deg": rot,
        "baseline_translation_mm": trans,
        "_tip9": tip9,
    }


def run_handeye_trial(trial_id: int, seed: int, *, cfg: HandEyeStudyConfig) -> dict[str, Any]:
    """One hand-eye trial → one ``trials.csv`` row (metrics of the largest M, plus per-M columns)."""
    from fluoronav.calibration.handeye import transform_error
    from fluoronav.calibration.image_handeye import ImageHandEyeConfig, calibrate_hand_eye_from_images
    from fluoronav.registration.cm import CMView
    from fluoronav.studies.metrics import cm_errors
    from fluoronav.studies.pipeline import _anatomy

    t0 = time.perf_counter()
    torch.set_num_threads(1)
    rng = np.random.default_rng(seed)
    row = new_row(trial_id, seed, cfg.workflow)
    try:
        volume, simulator = _anatomy(cfg.ct, 1000 * cfg.seed, cfg.image_size, cfg.device)
        kin = CMKinematics()
        m_max = max(cfg.poses)
        sc = sample_handeye_scenario(
            volume,
            rng,
            n_poses=m_max,
            rotation_spread_deg=cfg.rotation_spread_deg,
            translation_spread_mm=cfg.translation_spread_mm,
            bend_deg=cfg.calibration_bend_deg,
        )
        images = simulate_scenario_images(
            sc, simulator, seed=int(rng.integers(2**31)), image_size=cfg.image_size
        )
        lms, source = _landmarks(images, sc.landmarks_px, rng, cfg)
        row["landmarks"] = source
        X0 = _perturb(sc.ee_from_cm, rng, cfg.init_rotation_deg, cfg.init_translation_mm)
        cp0 = sc.control_points_deg + rng.uniform(-0.5, 0.5, 5)
        views = [
            CMView(s.image, s.camera, landmarks_px=lm, name=f"pose{m}")
            for m, (s, lm) in enumerate(zip(images, lms, strict=True))
        ]
        rbase_ee_true = sc.true_robot.rbase_from_ee(sc.q_actual_deg)
        tip_true = _tip_rbase(rbase_ee_true, sc.ee_from_cm, sc.control_points_deg, kin)
        base = _tracker_baseline(sc, rng, cfg.tracker_sigma_mm, kin)
        tip9 = base.pop("_tip9", None)
        row.update(base)
        row["true_ee_from_cm"] = np.round(sc.ee_from_cm, 5).tolist()
        row["true_control_points_deg"] = np.round(sc.control_points_deg, 4).tolist()
        hcfg = ImageHandEyeConfig(device=cfg.device)
        cal_seed = int(rng.integers(2**31))
        for m in sorted(cfg.poses):
            res = calibrate_hand_eye_from_images(
                views[:m],
                sc.rbase_from_ee_reported[:m],
                initial_ee_from_cm=X0,
                initial_control_points_deg=cp0,
                config=hcfg,
                seed=cal_seed,
            )
            if isinstance(res, HandEyeFailure):
                row[f"reason_m{m}"] = res.reason
                if m == m_max:
                    raise _TrialFailure(f"hand-eye failed: {res.reason}")
                continue
            rot, trans = transform_error(res.ee_from_cm, sc.ee_from_cm)
            tip10 = _tip_rbase(sc.rbase_from_ee_reported[:m], res.ee_from_cm, res.control_points_deg, kin)
            tip_mm = float(np.linalg.norm(tip10 - tip_true[:m], axis=1).mean())
            row[f"handeye_tip_mm_m{m}"] = tip_mm
            row[f"handeye_rotation_deg_m{m}"] = rot
            row[f"handeye_translation_mm_m{m}"] = trans
            row[f"seconds_m{m}"] = res.seconds
            if m == m_max:
                row.update(
                    handeye_tip_mm=tip_mm,
                    handeye_rotation_deg=rot,
                    handeye_translation_mm=trans,
                    n_poses=m,
                    seconds_registration=res.seconds,
                    converged=res.converged,
                    mean_residual_px=float(np.nanmean(res.residuals_px)),
                )
                row.update(_axis_and_roll_deg(res.ee_from_cm, sc.ee_from_cm))
                row["est_ee_from_cm"] = np.round(res.ee_from_cm, 5).tolist()
                row["est_control_points_deg"] = np.round(res.control_points_deg, 4).tolist()
                cam = sc.camera.camera_from_world
                row.update(
                    {
                        k: v
                        for k, v in cm_errors(
                            carm_from_cm_est=cam @ res.world_from_cm[0],
                            carm_from_cm_true=cam @ sc.world_from_cm[0],
                            control_points_est_deg=res.control_points_deg,
                            control_points_true_deg=sc.control_points_deg,
                        ).items()
                        if k in CM_METRICS
                    }
                )
                if tip9 is not None:
                    row["eq9_vs_eq10_mm"] = float(np.linalg.norm(tip9[:m] - tip10, axis=1).mean())
    except Exception as exc:  # a failed trial is recorded with its reason, never dropped
        mark_failed(row, exc, trial_id)
    return finish_row(row, t0)


def _register_single(
    image: Any,
    lm: np.ndarray,
    cp0: np.ndarray,
    world_from_cm0: np.ndarray | None,
    cfg: HandEyeStudyConfig,
    seed: int,
) -> Any:
    """CM registration in one view; initial pose from the centreline (None) or the given pose."""
    from fluoronav.detection.centerline import extract_centerline
    from fluoronav.registration.centerline_init import centerline_initialize
    from fluoronav.registration.cm import CMRegistrationConfig, CMView, register_cm

    if world_from_cm0 is None:
        cl = extract_centerline(image.mask.astype(bool), lm[0], lm[1])
        init = centerline_initialize(image.camera, lm, cl, cp0, seed=seed, image=image.image)
        world_from_cm0 = init.world_from_cm(image.camera)
    return register_cm(
        [CMView(image.image, image.camera, landmarks_px=lm, name="view0")],
        initial_control_points_deg=cp0,
        initial_world_from_cm=world_from_cm0,
        config=CMRegistrationConfig(device=cfg.device),
        seed=seed + 1,
    )


@dataclass(frozen=True)
class _Verification:
    """Registrations at a reached pose, in the verification's C-arm frame (its view 0)."""

    carm_from_femur: np.ndarray
    carm_from_cm: np.ndarray
    #: the CM shape this registration found (its base pose and shape together place the tip)
    control_points_deg: np.ndarray
    #: registered tip vs the planned tip through the registered femur: what the surgeon sees
    registered_error_mm: float
    #: the verification's own errors against the truth (C-arm frame of its view 0): femur entry
    #: point, CM tip, and the CM tip relative to the entry point (what a correction acts on)
    entry_error_mm: float
    tip_error_mm: float
    relative_error_mm: float
    seconds: float


def _verify(
    sc: HandEyeScenario,
    simulator: Any,
    volume: Any,
    *,
    world_from_cm_now: np.ndarray,
    plan: Any,
    femur_from_cm_target: np.ndarray,
    world_from_femur_est: np.ndarray,
    control_points_deg: np.ndarray,
    binning: int,
    cfg: HandEyeStudyConfig,
    rng: np.random.Generator,
    kin: CMKinematics,
) -> _Verification | None:
    """Image the CM where the robot took it and register femur and CM anew (``verify_views``).

    The C-arm is slid (no rotation) to centre the midpoint of the femoral head and the planned CM as
    the first registration placed them (± 5 mm: a person positions it), and orbited for the other
    views; the new C-arm pose is unknown to the software, so the pelvis is registered again per view
    (the view geometry for several views), then the femur and the CM (initial CM pose: the plan on
    the new femur). None when the CM is not in the AP view (20 px margin)."""
    from fluoronav.detection.instrument import instrument_mask_from_landmarks
    from fluoronav.geometry.carm import orbit_camera
    from fluoronav.registration.bone import (
        register_femur,
        register_pelvis_per_view,
        views_from_images,
        views_in_ct_frame,
    )
    from fluoronav.registration.cm import CMRegistrationConfig, CMView, register_cm

    t0 = time.perf_counter()
    tr = sc.trial
    # between the femoral head and the planned CM: the CM, the neck and the acetabulum in view (the
    # pelvis registration fails when only the trochanter region is imaged)
    centre_femur = verification_view_centre(femur_from_cm_target, tr.femoral_head_ct)
    centre = (world_from_femur_est @ np.append(centre_femur, 1.0))[:3] + rng.uniform(-5.0, 5.0, 3)
    ap = centre_on(sc.camera, centre)
    cpt = torch.as_tensor(sc.control_points_deg, dtype=torch.float64)
    pts = np.concatenate([kin.landmarks_cm(cpt).numpy(), kin.tip_cm(cpt).numpy()[None]])
    if not _in_view(ap, world_from_cm_now, pts, 20.0):
        return None
    cams = [ap]
    for k in range(1, cfg.verify_views):
        sign = 1.0 if k % 2 else -1.0
        cams.append(
            orbit_camera(ap, angle_deg=sign * cfg.verify_orbit_deg * ((k + 1) // 2), isocenter_world=centre)
        )
    noise_seed = int(rng.integers(2**31))
    images = [
        simulate_scenario_images(
            sc,
            simulator,
            seed=noise_seed + k,
            image_size=cfg.image_size,
            world_from_cm=world_from_cm_now,
            camera=c,
        )[0]
        for k, c in enumerate(cams)
    ]
    ab_world = pts[:2] @ world_from_cm_now[:3, :3].T + world_from_cm_now[:3, 3]
    lms = [im.camera.project(ab_world) + rng.uniform(-3.0, 3.0, (2, 2)) / binning for im in images]
    # the CM and its shaft are left out of the bone similarity (segmentation + oracle landmarks)
    views = views_from_images(
        images,
        [
            instrument_mask_from_landmarks(im.mask, lm, image=im.image)
            for im, lm in zip(images, lms, strict=True)
        ],
    )
    pelvis = register_pelvis_per_view(
        views, volume, initial_world_from_patient=tr.initial_world_from_patient, seed=int(rng.integers(2**31))
    )
    # the CT frame of the pelvis-estimated views (the multi-view study's frame; with one view the
    # same relative poses as the true camera with the pelvis estimate)
    views_ct = views_in_ct_frame(views, pelvis)
    reg_cams = [v.camera for v in views_ct]
    femur = register_femur(
        views_ct, volume, side=tr.side, world_from_patient=np.eye(4), seed=int(rng.integers(2**31))
    )
    reg = register_cm(
        [
            CMView(im.image, c, landmarks_px=lm, name=f"verify{k}")
            for k, (im, c, lm) in enumerate(zip(images, reg_cams, lms, strict=True))
        ],
        initial_control_points_deg=control_points_deg,
        initial_world_from_cm=femur.world_from_bone @ femur_from_cm_target,
        config=CMRegistrationConfig(device=cfg.device),
        seed=int(rng.integers(2**31)),
    )
    planned_tip = (femur.world_from_bone @ np.append(plan.tip_target_world_mm, 1.0))[:3]
    carm = reg_cams[0].camera_from_world
    carm_true = images[0].camera.camera_from_world
    entry_est = (carm @ femur.world_from_bone @ np.append(tr.entry_ct, 1.0))[:3]
    entry_true = (carm_true @ np.append(tr.entry_world, 1.0))[:3]
    tip_est = (carm @ np.append(reg.tip_world[0], 1.0))[:3]
    tip_true = (carm_true @ world_from_cm_now @ np.append(pts[-1], 1.0))[:3]
    return _Verification(
        carm_from_femur=carm @ femur.world_from_bone,
        carm_from_cm=carm @ reg.world_from_cm[0],
        control_points_deg=reg.control_points_deg,
        registered_error_mm=float(np.linalg.norm(reg.tip_world[0] - planned_tip)),
        entry_error_mm=float(np.linalg.norm(entry_est - entry_true)),
        tip_error_mm=float(np.linalg.norm(tip_est - tip_true)),
        relative_error_mm=float(np.linalg.norm((tip_est - entry_est) - (tip_true - entry_true))),
        seconds=time.perf_counter() - t0,
    )


def run_navigation_trial(trial_id: int, seed: int, *, cfg: HandEyeStudyConfig) -> dict[str, Any]:
    """One navigation trial → one ``trials.csv`` row (module docstring)."""
    from fluoronav.navigation.navigate import femur_from_cm_registered, tip_correction_target
    from fluoronav.navigation.planning import neck_entry_plan, planned_femur_from_cm
    from fluoronav.studies.metrics import axis_error_deg, cm_errors, point_error_mm, relative_error_mm
    from fluoronav.studies.pipeline import _anatomy

    t0 = time.perf_counter()
    torch.set_num_threads(1)
    rng = np.random.default_rng(seed)
    row = new_row(trial_id, seed, cfg.workflow)
    try:
        volume, simulator = _anatomy(cfg.ct, 1000 * cfg.seed, cfg.image_size, cfg.device)
        kin = CMKinematics()
        sc = sample_handeye_scenario(volume, rng, n_poses=0)
        tr = sc.trial
        # the CM, the neck and the acetabulum in view; the verification slides the C-arm (_verify)
        sc = dataclasses.replace(sc, camera=centre_on(sc.camera, working_view_centre(tr)))
        cam = sc.camera.camera_from_world
        q_regi = sc.q_work_deg
        W_regi = sc.true_world_from_cm(sc.error_model.actual_joints_deg(q_regi, rng=rng))
        img = simulate_scenario_images(
            sc, simulator, seed=int(rng.integers(2**31)), image_size=cfg.image_size, world_from_cm=W_regi
        )[0]
        cpt = torch.as_tensor(sc.control_points_deg, dtype=torch.float64)
        lm_true = img.camera.project(kin.landmarks_cm(cpt).numpy() @ W_regi[:3, :3].T + W_regi[:3, 3])
        b = max(1, round(img.camera.pixel_spacing_mm / 0.194)) if img.camera.pixel_spacing_mm else 1
        lm = lm_true + rng.uniform(-3.0, 3.0, (2, 2)) / b  # oracle: U(−3, 3) full-detector px
        cp0 = tr.initial_control_points_deg
        init = None if cfg.navigation_init == "centerline" else _perturb(W_regi, rng, 10.0, 10.0)
        reg = _register_single(img, lm, cp0, init, cfg, int(rng.integers(2**31)))
        row["seconds_registration"] = reg.seconds
        row.update(
            {
                k: v
                for k, v in cm_errors(
                    carm_from_cm_est=cam @ reg.world_from_cm[0],
                    carm_from_cm_true=cam @ W_regi,
                    control_points_est_deg=reg.control_points_deg,
                    control_points_true_deg=sc.control_points_deg,
                ).items()
                if k in CM_METRICS
            }
        )
        # femur: registered (pelvis then femur in the one view) or the truth
        if cfg.register_bones:
            from fluoronav.detection.instrument import instrument_mask_from_landmarks
            from fluoronav.registration.bone import register_femur, register_pelvis, views_from_images

            tb = time.perf_counter()
            bv = views_from_images([img], [instrument_mask_from_landmarks(img.mask, lm, image=img.image)])
            pelvis = register_pelvis(
                bv,
                volume,
                initial_world_from_patient=tr.initial_world_from_patient,
                seed=int(rng.integers(2**31)),
            )
            femur = register_femur(
                bv,
                volume,
                side=tr.side,
                world_from_patient=pelvis.world_from_bone,
                seed=int(rng.integers(2**31)),
            )
            world_from_femur_est = femur.world_from_bone
            row["seconds_bones"] = time.perf_counter() - tb
        else:
            world_from_femur_est = tr.world_from_femur
        entry_est = (world_from_femur_est @ np.append(tr.entry_ct, 1.0))[:3]
        tip_reg = reg.tip_world[0]
        tip_true_regi = (W_regi @ np.append(kin.tip_cm(cpt).numpy(), 1.0))[:3]
        if cfg.register_bones:  # with the true femur pose these would only repeat the CM errors
            row["entry_mm"] = point_error_mm(entry_est, tr.entry_world)
            row["relative_mm"] = relative_error_mm(entry_est, tip_reg, tr.entry_world, tip_true_regi)
        # plan (femur = CT frame): tip on the entry point, axis along the neck towards the head
        plan = neck_entry_plan(tr.entry_ct, tr.femoral_head_ct, reg.control_points_deg)
        femur_from_cm_target = planned_femur_from_cm(plan, kinematics=kin)
        X_used = _perturb(sc.ee_from_cm, rng, cfg.handeye_error_deg, cfg.handeye_error_mm)
        q_target, W_after = sc.move_to_plan(
            q_regi,
            ee_from_cm=X_used,
            carm_from_femur=cam @ world_from_femur_est,
            carm_from_cm=cam @ reg.world_from_cm[0],
            femur_from_cm_target=femur_from_cm_target,
            rng=rng,
        )
        tip_after = (W_after @ np.append(kin.tip_cm(cpt).numpy(), 1.0))[:3]
        planned_true = (tr.world_from_femur @ np.append(plan.tip_target_world_mm, 1.0))[:3]
        row["reposition_open_loop_mm"] = point_error_mm(tip_after, planned_true)
        row["reposition_tip_mm"] = row["reposition_open_loop_mm"]
        # the CM base axis against the planned direction (the drilling direction)
        axis_true = (tr.world_from_femur @ femur_from_cm_target)[:3, 2]
        row["reposition_open_loop_axis_deg"] = axis_error_deg(W_after[:3, 2], axis_true)
        row["reposition_axis_deg"] = row["reposition_open_loop_axis_deg"]
        row["joint_motion_deg"] = float(np.max(np.abs(wrap_deg(q_target - q_regi))))
        # error budget without image errors: true registrations, the same hand-eye and robot errors
        plan_true = dataclasses.replace(plan, control_points_deg=sc.control_points_deg)
        _, W_ideal = sc.move_to_plan(
            q_regi,
            ee_from_cm=X_used,
            carm_from_femur=cam @ tr.world_from_femur,
            carm_from_cm=cam @ W_regi,
            femur_from_cm_target=planned_femur_from_cm(plan_true, kinematics=kin),
            rng=rng,
        )
        row["reposition_robot_mm"] = point_error_mm(
            (W_ideal @ np.append(kin.tip_cm(cpt).numpy(), 1.0))[:3], planned_true
        )
        # new images at the reached pose (C-arm re-centred): what they say, and corrective moves
        q_now, W_now = q_target, W_after
        seconds_verify = 0.0
        # one verification per correction (each moves again); one for the record when open loop
        for k in range(max(1, cfg.corrections)):
            ver = _verify(
                sc,
                simulator,
                volume,
                world_from_cm_now=W_now,
                plan=plan,
                femur_from_cm_target=femur_from_cm_target,
                world_from_femur_est=world_from_femur_est,
                control_points_deg=reg.control_points_deg,
                binning=b,
                cfg=cfg,
                rng=rng,
                kin=kin,
            )
            if ver is None:
                row["reposition_reason"] = "reached pose outside the re-centred image"
                break
            seconds_verify += ver.seconds
            if k == 0:
                row["reposition_registered_mm"] = ver.registered_error_mm
                row["verify_entry_mm"] = ver.entry_error_mm
                row["verify_tip_mm"] = ver.tip_error_mm
                row["verify_relative_mm"] = ver.relative_error_mm
            if cfg.corrections == 0:
                break
            # slide the verified CM so that its registered tip meets the plan (tip_correction_target:
            # the verification's tip is reliable, its base orientation trades against its shape)
            tip_ver = kin.tip_cm(torch.as_tensor(ver.control_points_deg, dtype=torch.float64)).numpy()
            target_k = tip_correction_target(
                femur_from_cm_registered(ver.carm_from_femur, ver.carm_from_cm),
                tip_ver,
                plan.tip_target_world_mm,
            )
            q_now, W_now = sc.move_to_plan(
                q_now,
                ee_from_cm=X_used,
                carm_from_femur=ver.carm_from_femur,
                carm_from_cm=ver.carm_from_cm,
                femur_from_cm_target=target_k,
                rng=rng,
            )
            tip_now = (W_now @ np.append(kin.tip_cm(cpt).numpy(), 1.0))[:3]
            row["reposition_tip_mm"] = point_error_mm(tip_now, planned_true)
            row["reposition_axis_deg"] = axis_error_deg(W_now[:3, 2], axis_true)
        row["seconds_verification"] = seconds_verify
    except Exception as exc:  # a failed trial is recorded with its reason, never dropped
        mark_failed(row, exc, trial_id)
    return finish_row(row, t0)


# ----- study --------------------------------------------------------------------------------------
def _columns(cfg: HandEyeStudyConfig) -> list[str]:
    head = ["trial", "seed", "workflow", "status", "reason"]
    tail = ["seconds", "seconds_registration", "seconds_bones"]
    if cfg.workflow == "navigation":
        return [
            *head,
            *NAVIGATION_METRICS,
            *NAVIGATION_DIAGNOSTICS,
            "joint_motion_deg",
            "reposition_reason",
            *tail,
            "seconds_verification",
        ]
    per_m = [
        f"{k}_m{m}"
        for m in sorted(cfg.poses)
        for k in ("handeye_tip_mm", "handeye_rotation_deg", "handeye_translation_mm", "seconds")
    ]
    return [
        *head,
        *HANDEYE_METRICS,
        *HANDEYE_DIAGNOSTICS,
        "n_poses",
        "converged",
        "mean_residual_px",
        "landmarks",
        "baseline_reason",
        *per_m,
        *[f"reason_m{m}" for m in sorted(cfg.poses)],
        *tail,
        "true_ee_from_cm",
        "est_ee_from_cm",
        "true_control_points_deg",
        "est_control_points_deg",
    ]


def _figures(rows: list[dict[str, Any]], out: Path, cfg: HandEyeStudyConfig) -> list[Path]:
    """The generic histograms plus: hand-eye error vs M; navigation repositioning histogram."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fluoronav.studies.figures import _col, study_figures

    written = study_figures(rows, out, workflow=cfg.workflow)
    ok = [r for r in rows if str(r.get("status")) == "ok"]
    if cfg.workflow == "hand-eye":
        ms = sorted(cfg.poses)
        fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
        for ax, (key, label) in zip(
            axes,
            (
                ("handeye_tip_mm", "tip error (mm)"),
                ("handeye_rotation_deg", "rotation error (°)"),
                ("handeye_translation_mm", "translation error (mm)"),
            ),
            strict=True,
        ):
            data = [_col(ok, f"{key}_m{m}") for m in ms]
            keep = [i for i, d in enumerate(data) if len(d)]
            if keep:
                ax.boxplot([data[i] for i in keep], showfliers=True)
                ax.plot(
                    range(1, len(keep) + 1),
                    [float(np.mean(data[i])) for i in keep],
                    "o-",
                    color="crimson",
                    label="mean",
                )
                ax.set_xticks(range(1, len(keep) + 1), [str(ms[i]) for i in keep])
            ax.set_xlabel("number of robot poses M")
            ax.set_ylabel(f"hand-eye {label}")
        if "baseline_tip_mm" in (ok[0] if ok else {}):
            axes[0].axhline(
                float(np.mean(_col(ok, "baseline_tip_mm"))),
                color="grey",
                linestyle="--",
                label="tracker AX=XB, eq. 9",
            )
        axes[0].legend(fontsize=8)
        fig.suptitle(f"image-based hand-eye: error vs number of poses (n = {len(ok)} trials)")
        fig.tight_layout()
        p = out / "handeye_error_vs_poses.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        written.append(p)
    else:
        v = _col(ok, "reposition_tip_mm")
        if len(v):
            fig, ax = plt.subplots(figsize=(5, 3.6))
            ax.hist(v, bins=min(30, max(5, len(v) // 2)), color="steelblue", edgecolor="white")
            ax.axvline(float(np.mean(v)), color="crimson", linestyle="--", label=f"mean {np.mean(v):.2f} mm")
            ax.set_xlabel("repositioning tip error (mm)")
            ax.set_ylabel("trials")
            ax.legend(fontsize=8)
            fig.tight_layout()
            p = out / "reposition_error_histogram.png"
            fig.savefig(p, dpi=100)
            plt.close(fig)
            written.append(p)
    return written


def run_study(
    cfg: HandEyeStudyConfig, out: Path, *, scheduler: str | None = None, workers: int | None = None
) -> dict[str, Any]:
    """Run (or resume) a hand-eye or navigation study into ``out``: trials.csv, summary.json,
    config.json, figures/."""
    from fluoronav import __version__
    from fluoronav.studies.runner import CsvLog, run_tasks
    from fluoronav.studies.summary import summarize, write_summary

    if cfg.workflow not in ("hand-eye", "navigation"):
        raise InputError("WORKFLOW", f"unknown workflow {cfg.workflow!r}; use hand-eye or navigation")
    if any(m < 1 for m in cfg.poses):
        raise InputError("--poses", "numbers of poses must be positive")
    if cfg.verify_views < 1:
        raise InputError("--verify-views", "at least one verification view is needed")
    out.mkdir(parents=True, exist_ok=True)
    cfg_path = out / "config.json"
    cfg_dict = {**dataclasses.asdict(cfg), "version": __version__}
    cfg_dict["poses"] = list(cfg.poses)
    if cfg_path.exists():
        old = json.loads(cfg_path.read_text(encoding="utf-8"))
        keep = [k for k in cfg_dict if k not in ("trials", "device", "version")]
        if any(old.get(k) != cfg_dict.get(k) for k in keep):
            raise InputError(cfg_path, "this directory holds a study with other settings; use another --out")
    if cfg.ct != "phantom":
        from fluoronav.anatomy.io import resolve_ct

        resolve_ct(cfg.ct)
    detector = _detector_or_none(cfg.device)
    cfg_dict["detector_precision"] = None if detector is None else detector.precision
    cfg_path.write_text(json.dumps(cfg_dict, indent=2), encoding="utf-8")
    csv_log = CsvLog(out / "trials.csv", _columns(cfg))
    fn = run_handeye_trial if cfg.workflow == "hand-eye" else run_navigation_trial
    run_tasks(
        functools.partial(fn, cfg=cfg),
        cfg.trials,
        cfg.seed,
        csv_log,
        scheduler=scheduler,
        workers=workers,
        description=f"study {cfg.workflow}",
    )
    rows = sorted(csv_log.read(), key=lambda r: int(r["trial"]))
    names = list(HANDEYE_METRICS if cfg.workflow == "hand-eye" else NAVIGATION_METRICS)
    if cfg.workflow == "navigation":
        names += list(NAVIGATION_DIAGNOSTICS)
    if cfg.workflow == "hand-eye":
        names += list(HANDEYE_DIAGNOSTICS)
        names += [
            f"{k}_m{m}"
            for m in sorted(cfg.poses)
            for k in ("handeye_tip_mm", "handeye_rotation_deg", "handeye_translation_mm")
        ]
    summary = summarize(
        cfg.workflow,
        rows,
        names,
        trials=cfg.trials,
        device=cfg.device,
        extra={
            "seed": cfg.seed,
            "ct": cfg.ct,
            "poses": list(cfg.poses),
            "landmarks": "oracle" if cfg.oracle_landmarks else "detector or oracle",
            "image_size": cfg.image_size,
        },
    )
    write_summary(out / "summary.json", summary)
    _figures(rows, out / "figures", cfg)
    return summary


def run_handeye_or_navigation_study(
    workflow: str,
    *,
    trials: int,
    seed: int,
    out: Path,
    ct: str = "phantom",
    scheduler: str | None = None,
    workers: int | None = None,
    device: str = "cpu",
    poses: Sequence[int] = (4, 8, 15),
    image_size: int = 768,
    register_bones: bool = True,
    navigation_init: str = "perturbed",
    corrections: int = 1,
    verify_views: int = 3,
    calibration_bend_deg: float | None = 2.5,
) -> dict[str, Any]:
    """Entry point of ``fluoronav study hand-eye|navigation`` → the summary dict (CONTRACTS)."""
    cfg = HandEyeStudyConfig(
        workflow=workflow,
        trials=trials,
        seed=seed,
        ct=ct,
        poses=tuple(int(m) for m in poses),
        image_size=image_size,
        device=device,
        register_bones=register_bones,
        navigation_init=navigation_init,
        corrections=corrections,
        verify_views=verify_views,
        calibration_bend_deg=calibration_bend_deg,
    )
    return run_study(cfg, Path(out), scheduler=scheduler, workers=workers)
