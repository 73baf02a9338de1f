"""The truth of a simulated navigation: the patient, the robot holding the CM, the C-arm views, the plan.

:func:`build_scenario` draws the stages ``anatomy`` and ``scene`` of
:func:`~fluoronav.simulation.navigation.loop.run_simulated_navigation`: the seeded hip phantom (or a
labelled CT) and the case's CT as the world makes it (:mod:`fluoronav.simulation.world_anatomy`), a
UR-10 with joint and calibration errors holding the CM above the femoral head at a working pose
that reaches the plan gently (redrawn until it does: ``working_pose_max_joint_deg``), three C-arm
views (AP and orbits), the plan and the case's hand-eye matrix. :class:`Scenario` holds that truth
and takes the physics images of the CM wherever the robot puts it (:meth:`Scenario.simulate`), with
the cameras the case records (:meth:`Scenario.case_cameras`). Frames: ``world`` is the simulation's
world (the CT frame before the patient moved); ``cm`` the CM's base frame.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fluoronav.anatomy.volume import Volume
from fluoronav.geometry import se3
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.carm import centre_on, orbit_camera
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.navigation.planning import Plan, neck_entry_plan, planned_femur_from_cm
from fluoronav.navigation.targeting import UnreachableTarget, least_motion_target
from fluoronav.registration.stages import StageRecorder
from fluoronav.simulation.articulated import ArticulatedSimulator
from fluoronav.simulation.instrument import BuiltCM, build_instrument, built_tip_cm
from fluoronav.simulation.robot_scene import (
    HandEyeScenario,
    perturb_transform,
    sample_handeye_scenario,
    working_view_centre,
)
from fluoronav.simulation.world import IDEAL, World, case_camera, flexed_camera, patient_motion
from fluoronav.simulation.world_anatomy import world_anatomy

log = logging.getLogger(__name__)

__all__ = [
    "Scenario",
    "SimulatedNavigationConfig",
    "build_scenario",
]


@dataclass(frozen=True)
class SimulatedNavigationConfig:
    """Settings of a simulated navigation (recorded in ``results.json`` and study configs).

    Attributes:
        seed: everything random derives from it (scene, noise, optimisers).
        phantom_seed: the hip phantom's seed (default: ``seed``).
        image_size: simulated image rows = cols (the 1536² CIOS Fusion detector binned).
        orbit_deg: C-arm orbit angles of the extra views about the patient's long axis.
        handeye_error_deg, handeye_error_mm: the hand-eye matrix in the case is the truth moved by
            exactly these (the measured accuracy of the image-based calibration).
        aim_error_mm: the verification C-arm's centre misses its aim by U(−a, a) mm per axis.
        verify: take verification images after the move and command one correction.
        verify_views: how many of the verification images the case gives (1, 2 or 3):
            :func:`verification_view_indices`. Each says which first view's C-arm position it was
            taken from and the C-arm's nominal motion since (``CaseView.moved_from``).
        device: torch device of the detector, renderers and similarities.
        oracle_landmarks: the case gives the true landmarks + U(−3, 3) full-detector px and the true
            CM mask for every view instead of leaving them to the detector.
        working_pose_max_joint_deg: the person who brings the robot to its working pose before
            imaging points the CM roughly along the planned approach: a scene is redrawn (up to
            ``max_scene_draws`` times) until the plan, reached from the true poses with the least
            joint motion, turns no joint by more than this (degrees; a few below the command's
            bound ``SafetyConfig.max_joint_motion_deg``, so the registrations' errors do not push
            a gentle move over it). None: the first draw, however far from the plan.
        max_scene_draws: how many scenes that search draws at most (the last is kept).
        world: the simulated world's error sources (:mod:`fluoronav.simulation.world`): the CT
            against the patient, the C-arm's calibration and flex, the FBG reading, patient motion.
            The ideal world (default) renders the images from the case's CT with the case's cameras.
        fault: an input fault of :data:`fluoronav.simulation.navigation.faults.FAULTS` injected into the case
            (None: none). With a fault, an :class:`~fluoronav.errors.InputError` of the pipeline's
            preflight is an outcome, not an error: ``artifacts["input_error"]`` holds its ``reason``
            and ``check``, and the run stops there.
    """

    seed: int = 0
    phantom_seed: int | None = None
    image_size: int = 768
    orbit_deg: tuple[float, ...] = (20.0, -15.0)
    handeye_error_deg: float = 0.4
    handeye_error_mm: float = 0.5
    aim_error_mm: float = 5.0
    verify: bool = True
    verify_views: int = 3
    device: str = "cpu"
    oracle_landmarks: bool = False
    working_pose_max_joint_deg: float | None = 25.0
    max_scene_draws: int = 20
    fault: str | None = None
    world: World = IDEAL


@dataclass(frozen=True, eq=False)
class Scenario:
    """The truth of a simulated navigation and what the case is made of (stages ``anatomy``, ``scene``).

    Attributes:
        config: the simulation's settings.
        volume: the case's CT (what the pipeline is given).
        simulator: the physics X-rays of the patient (never the registration's renderer).
        sc: the robot scene: the true robot, hand-eye matrix, patient and femur poses.
        cp_true: (n_control_points,) the CM's true shape (degrees).
        tip_cm: (3,) the CM tip in its base frame (mm): the instrument as built where it is built.
        q_regi: (n_joints,) the joints while the first images are taken (degrees).
        W_regi: (4, 4) ``world_from_cm`` of the true robot at ``q_regi``.
        cams: the first set's nominal C-arm cameras (world frame); names: their view names.
        plan: the CM tip on the femur's entry point, its axis along the neck towards the head.
        ee_from_cm_used: (4, 4) the hand-eye matrix the case gives (the truth with its error).
        patient: the patient as rendered (finer than the CT in a realistic world).
        world_rng: the world's own random stream (the ideal world draws nothing from it).
        built: the instrument as built, None where the images show the model.
    """

    config: SimulatedNavigationConfig
    volume: Volume
    simulator: ArticulatedSimulator
    sc: HandEyeScenario
    cp_true: np.ndarray
    tip_cm: np.ndarray
    q_regi: np.ndarray
    W_regi: np.ndarray
    cams: list[Camera]
    names: list[str]
    plan: Plan
    ee_from_cm_used: np.ndarray
    patient: Volume
    world_rng: np.random.Generator
    built: BuiltCM | None = None

    def simulate(
        self,
        world_from_cm: np.ndarray,
        cameras: list[Camera],
        seed: int,
        *,
        moved_from_world: np.ndarray | None = None,
    ) -> list[Any]:
        """Physics images of the CM at ``world_from_cm`` (seeds ``seed + k``), each taken by its
        nominal camera flexed as the world says, the anatomy moved by ``moved_from_world`` and, view
        by view, by the world's motion within a set."""
        tr, w = self.sc.trial, self.config.world
        out = []
        for k, cam in enumerate(cameras):
            wp, wf = tr.world_from_patient, tr.world_from_femur
            M = self.patient_motion(w.motion.within_set_mm, w.motion.within_set_deg)
            if moved_from_world is not None:
                M = M @ moved_from_world
            if w.motion.enabled:
                wp, wf = M @ wp, M @ wf
            out.append(
                self.simulator.simulate(
                    flexed_camera(cam, w.carm, self.world_rng),
                    world_from_patient=wp,
                    world_from_femur=wf,
                    cm=(world_from_cm, self.cp_true),
                    seed=seed + k,
                    image_size=self.config.image_size,
                    cm_config=self.sc.cm_config,
                    built_cm=self.built,
                )
            )
        return out

    def patient_motion(self, translation_mm: float, rotation_deg: float) -> np.ndarray:
        """(4, 4) ``moved_from_world``: a rigid motion of the patient of exactly these sizes about
        the pelvis centre, drawn from the world's generator (the identity, nothing drawn, where
        both are 0)."""
        tr = self.sc.trial
        centre = se3.apply(tr.world_from_patient, tr.pelvis_center_ct)
        return patient_motion(translation_mm, rotation_deg, self.world_rng, center_world=centre)

    @property
    def tip_cm_true(self) -> np.ndarray | None:
        """(3,) the tip of the instrument as built (base frame), where it is not the model."""
        return None if self.built is None else self.tip_cm

    def case_cameras(self, cameras: list[Camera]) -> list[Camera] | None:
        """The cameras the case records for images by the nominal ``cameras``, at the stored size:
        the nominal geometry with the world's calibration error (a flexed image's case does not know
        its flex); None where the C-arm source is off (the images' own)."""
        carm = self.config.world.carm
        if not carm.enabled:
            return None
        n = self.config.image_size
        return [self.simulator.stored_camera(case_camera(c, carm, self.world_rng), n) for c in cameras]


def verification_view_indices(n_views: int, k: int) -> list[int]:
    """Which of the ``n_views`` verification images (AP, then the orbits) a case with ``k`` of them
    gives: all for ``k ≥ n_views``; the AP for one (the CM seen broadside); the two orbits for two
    (the widest angle between them, for the triangulation of A and B)."""
    if k < 1:
        raise ValueError(f"verify_views must be at least 1, got {k}")
    if k >= n_views:
        return list(range(n_views))
    if k == 1:
        return [0]
    return list(range(n_views - k, n_views))


def build_scenario(
    cfg: SimulatedNavigationConfig,
    ct: str,
    T: StageRecorder,
    rng: np.random.Generator,
    scene_seed: int,
    world_seed: int,
) -> Scenario:
    """Stages ``anatomy`` and ``scene``: the patient and the case's CT, the robot holding the CM,
    the C-arm views, the plan."""
    world_rng = np.random.default_rng(world_seed)  # its own stream: the ideal world draws nothing
    with T("anatomy"):
        phantom_seed = cfg.seed if cfg.phantom_seed is None else cfg.phantom_seed
        anatomy = world_anatomy(
            ct, phantom_seed, cfg.world.ct, image_size=cfg.image_size, device=cfg.device, rng=world_rng
        )
    with T("scene"):
        sc = _working_scene(anatomy.patient, cfg, np.random.default_rng(scene_seed))
        tr = sc.trial
        kin = CMKinematics(sc.cm_config)
        cp_true = np.asarray(sc.control_points_deg, np.float64)
        built = None
        if cfg.world.instrument.enabled:  # the CM in the images is not the model the registration fits
            built = build_instrument(cfg.world.instrument, sc.cm_config, world_rng)
            tip_cm = built_tip_cm(built, cp_true).numpy()
        else:
            tip_cm = kin.tip_cm(torch.as_tensor(cp_true, dtype=torch.float64)).numpy()
        q_regi = sc.q_work_deg
        W_regi = sc.execute(q_regi, rng=rng)
        iso = working_view_centre(tr)
        ap = centre_on(sc.camera, iso)
        cams = [ap] + [orbit_camera(ap, angle_deg=a, isocenter_world=iso) for a in cfg.orbit_deg]
        names = ["AP"] + [f"orbit {a:+g}" for a in cfg.orbit_deg]
        plan = neck_entry_plan(tr.entry_ct, tr.femoral_head_ct)
        ee_from_cm_used = perturb_transform(sc.ee_from_cm, rng, cfg.handeye_error_deg, cfg.handeye_error_mm)
    return Scenario(
        cfg,
        anatomy.case_ct,
        anatomy.simulator,
        sc,
        cp_true,
        tip_cm,
        q_regi,
        W_regi,
        cams,
        names,
        plan,
        ee_from_cm_used,
        anatomy.patient,
        world_rng,
        built,
    )


def _working_scene(
    volume: Volume, cfg: SimulatedNavigationConfig, rng: np.random.Generator
) -> HandEyeScenario:
    """A scene whose working pose reaches the plan gently (``cfg.working_pose_max_joint_deg``)."""
    for draw in range(max(1, cfg.max_scene_draws)):
        sc = sample_handeye_scenario(volume, rng, n_poses=0)
        if cfg.working_pose_max_joint_deg is None:
            return sc
        motion = _true_first_move_deg(sc)
        if motion <= cfg.working_pose_max_joint_deg:
            return sc
        log.debug("scene draw %d: the plan needs a %.1f° joint turn; redrawn", draw, motion)
    return sc


def _true_first_move_deg(sc: HandEyeScenario) -> float:
    """The largest joint turn of the least-motion move to the plan with true poses (inf: unreachable)."""
    tr = sc.trial
    kin = CMKinematics(sc.cm_config)
    plan = dataclasses.replace(
        neck_entry_plan(tr.entry_ct, tr.femoral_head_ct), control_points_deg=np.asarray(sc.control_points_deg)
    )
    try:
        chosen = least_motion_target(
            sc.nominal,
            sc.q_work_deg,
            lambda roll: planned_femur_from_cm(plan, kinematics=kin, roll_deg=roll),
            ee_from_cm=sc.ee_from_cm,
            carm_from_femur=tr.world_from_femur,
            carm_from_cm=sc.true_world_from_cm(sc.q_work_deg),
        )
    except UnreachableTarget:
        return float("inf")
    return float(chosen.joint_motion_deg)
