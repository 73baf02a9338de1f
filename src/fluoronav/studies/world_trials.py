"""A registration-study trial in a simulated world (``fluoronav study WORKFLOW --world``).

The registration studies (:mod:`fluoronav.studies.pipeline`) take each source of the simulated world
(:mod:`fluoronav.simulation.world`) as the simulated navigation does: the images rendered from the *patient*
and the case's CT given to the registration (``world.ct``); each image taken with its C-arm position's camera
flexed and the registration given the nominal camera with a calibration error (``world.carm``; intrinsics
only, so errors stay in the imaging C-arm's frame); the FBG reading as the initial control points and prior
(``world.fbg``); the CM as built in the images, its tip the truth (``world.instrument``); the patient moved
between the images of one set (``world.motion.within_set_*``; none between sets). The world draws from its own
generator (:func:`world_rng`, from the trial's seed) in the navigation's order, the protocol from the trial's,
so the ideal world, which draws nothing, gives the same trials as a study without a world.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from fluoronav.anatomy.volume import Volume
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.simulation.articulated import ArticulatedSimulator
from fluoronav.simulation.instrument import (
    BuiltCM,
    build_instrument,
    built_landmarks_cm,
    built_tip_cm,
)
from fluoronav.simulation.protocol import Trial, sample_trial
from fluoronav.simulation.world import (
    World,
    case_camera,
    case_fbg_reading,
    flexed_camera,
    patient_motion,
)
from fluoronav.simulation.world_anatomy import world_anatomy
from fluoronav.simulation.xray import SimulatedImage

__all__ = ["WorldTrial", "simulate_world_trial", "world_rng"]

#: the world stream's key beside the trial's seed ("WRLD"): independent of the trial's own stream
_WORLD_STREAM = 0x57524C44


def world_rng(trial_seed: int) -> np.random.Generator:
    """The world's generator of a trial: its own stream, so the trial's draws stay where they were."""
    return np.random.default_rng([_WORLD_STREAM, abs(int(trial_seed))])


@dataclass(frozen=True, eq=False)
class WorldTrial:
    """A trial's truth and images in a world, and what the registration is given.

    Attributes:
        patient: the anatomy the images are rendered from (the truth's landmarks and labels).
        case_ct: the CT the registration is given (``patient`` itself where the CT source is off).
        trial: the protocol's truth (world = the CT frame, mm, degrees); its
            ``initial_control_points_deg`` are the FBG reading where that source is on.
        images: the simulated images, each with the camera it was taken with (flexed, stored size).
        cameras: per image the camera the registration is given (stored size): the images' own
            where the C-arm source is off, else the nominal one with the case's calibration error.
        oracle_landmarks_px: (N, 2, 2) the trial's oracle landmarks (full-detector pixels, truth +
            U(−3, 3) px) moved to where the images show A and B (the instrument as built, the flex).
        tip_cm_true: (3,) the tip of the instrument as built in its base frame (mm), None where the
            images show the model.
    """

    patient: Volume
    case_ct: Volume
    trial: Trial
    images: list[SimulatedImage]
    cameras: tuple[Camera, ...]
    oracle_landmarks_px: np.ndarray
    tip_cm_true: np.ndarray | None


def _positions(cameras: Sequence[Camera]) -> list[int]:
    """Per camera the index of the first equal one (one C-arm position, e.g. multiple-CM's images)."""
    out: list[int] = []
    for i, c in enumerate(cameras):
        same = (
            j
            for j in range(i)
            if np.array_equal(c.K, cameras[j].K)
            and np.array_equal(c.camera_from_world, cameras[j].camera_from_world)
        )
        out.append(next(same, i))
    return out


def _oracle_landmarks_px(
    trial: Trial, imaging: Sequence[Camera], built: BuiltCM | None, world: World
) -> np.ndarray:
    """The trial's oracle landmarks (full-detector px) shifted to where the images show A and B."""
    if built is None and world.carm.flex_detector_shift_mm <= 0:
        return trial.oracle_landmarks_px  # the images show the model through the nominal cameras
    cp = trial.control_points_deg
    if built is not None:
        lm_cm = built_landmarks_cm(built, cp).numpy()
    else:
        lm_cm = CMKinematics(trial.cm_config).landmarks_cm(torch.as_tensor(cp, dtype=torch.float64)).numpy()
    shown = np.stack(
        [
            cam.project(lm_cm @ T[:3, :3].T + T[:3, 3])
            for cam, T in zip(imaging, trial.world_from_cm, strict=True)
        ]
    )
    # the protocol's noise kept: it was drawn about the nominal projection
    return np.asarray(trial.oracle_landmarks_px + (shown - trial.landmarks_px))


def _simulate_images(
    trial: Trial,
    simulator: ArticulatedSimulator,
    positions: list[int],
    world: World,
    built: BuiltCM | None,
    *,
    seed: int,
    image_size: int,
    world_rng: np.random.Generator,
) -> tuple[list[SimulatedImage], dict[int, Camera]]:
    """The trial's images (image ``i`` with noise seed ``seed + i``) in ``world`` → the images and
    per C-arm position (``positions``, :func:`_positions`) its flexed camera; per image the world draws
    the patient's motion within the set, then a new position's flex."""
    motion = world.motion
    # one image is its own set: the patient at that image is the trial's truth
    moving = trial.n_images > 1 and (motion.within_set_mm > 0 or motion.within_set_deg > 0)
    flexed: dict[int, Camera] = {}
    images: list[SimulatedImage] = []
    for i, (cam, T) in enumerate(zip(trial.cameras, trial.world_from_cm, strict=True)):
        wp, wf = trial.world_from_patient, trial.world_from_femur
        if moving:
            M = patient_motion(
                motion.within_set_mm, motion.within_set_deg, world_rng, center_world=trial.pelvis_center_world
            )
            wp, wf = M @ wp, M @ wf
        if positions[i] not in flexed:
            flexed[positions[i]] = flexed_camera(cam, world.carm, world_rng)
        images.append(
            simulator.simulate(
                flexed[positions[i]],
                world_from_patient=wp,
                world_from_femur=wf,
                cm=(T, trial.control_points_deg),
                seed=seed + i,
                image_size=image_size,
                cm_config=trial.cm_config,
                built_cm=built,
            )
        )
    return images, flexed


def simulate_world_trial(
    workflow: str,
    ct: str,
    phantom_seed: int,
    world: World,
    *,
    image_size: int,
    device: str,
    rng: np.random.Generator,
    world_rng: np.random.Generator,
) -> WorldTrial:
    """Sample a trial of the protocol's ``workflow`` and simulate its images in ``world`` (module
    docstring).

    Args:
        workflow: a protocol workflow (:data:`~fluoronav.simulation.protocol.WORKFLOWS`).
        ct: ``"phantom"`` or a labelled CT path.
        phantom_seed: the phantom's seed.
        world: the error sources.
        image_size: stored image rows = cols (the 1536² detector binned).
        device: torch device of the simulator.
        rng: the trial's generator: the protocol's draws and the images' noise seed, as before worlds.
        world_rng: the world's generator (:func:`world_rng`); the ideal world draws nothing from it.
    """
    anatomy = world_anatomy(ct, phantom_seed, world.ct, image_size=image_size, device=device, rng=world_rng)
    trial = sample_trial(workflow, anatomy.patient, rng)
    simulator = anatomy.simulator
    if simulator.femur_side != trial.side:
        raise ValueError(f"the simulator moves the {simulator.femur_side} femur, the trial the {trial.side}")
    built = None
    if world.instrument.enabled:  # the CM in the images is not the model the registration fits
        built = build_instrument(world.instrument, trial.cm_config, world_rng)
    seed = int(rng.integers(2**31))
    positions = _positions(trial.cameras)
    images, flexed = _simulate_images(
        trial, simulator, positions, world, built, seed=seed, image_size=image_size, world_rng=world_rng
    )
    cameras = tuple(im.camera for im in images)
    if world.carm.enabled:  # the case's calibration of each nominal position, not the flexed truth
        case = {
            p: simulator.stored_camera(case_camera(trial.cameras[p], world.carm, world_rng), image_size)
            for p in dict.fromkeys(positions)
        }
        cameras = tuple(case[p] for p in positions)
    if world.fbg.enabled or built is not None:
        reading = case_fbg_reading(
            trial.initial_control_points_deg, trial.control_points_deg, world.fbg, world_rng, built=built
        )
        trial = dataclasses.replace(trial, initial_control_points_deg=reading)
    return WorldTrial(
        patient=anatomy.patient,
        case_ct=anatomy.case_ct,
        trial=trial,
        images=images,
        cameras=cameras,
        oracle_landmarks_px=_oracle_landmarks_px(trial, [flexed[p] for p in positions], built, world),
        tip_cm_true=None if built is None else built_tip_cm(built, trial.control_points_deg).numpy(),
    )
