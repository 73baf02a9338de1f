"""The patient and the case's CT of a simulated world (:mod:`fluoronav.simulation.world`).

In the ideal world the X-ray images are rendered from the very CT the case gives the registration.
With a :class:`~fluoronav.simulation.world.CTWorld` that is on, the images are rendered from the
*patient*, and the case gets a clinical CT of it (:func:`~fluoronav.simulation.clinical_ct.clinical_ct`):

- ``"phantom"``: the patient is the procedural hip phantom sampled at ``patient_spacing_mm`` (finer than a
  clinical CT), the CT its average on the clinical grid with noise, HU scale error and labels off by a voxel;
- a CT file: the patient is that CT (it cannot be sampled finer), the case's CT its degraded copy.

Frames: both volumes share the world frame (LPS, mm): the CT frame of the patient before it moved.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.simulation.articulated import ArticulatedSimulator, anatomy_and_simulator
from fluoronav.simulation.clinical_ct import clinical_ct
from fluoronav.simulation.world import CTWorld
from fluoronav.simulation.xray import SimulationConfig

__all__ = ["QUANTISE_FINER_THAN_MM", "WorldAnatomy", "world_anatomy"]

#: a phantom patient finer than this (the studies' phantom's spacing) is rendered from uint16 volumes
QUANTISE_FINER_THAN_MM = 1.0


@dataclass(frozen=True, eq=False)
class WorldAnatomy:
    """What a simulated case is made of.

    Attributes:
        patient: the anatomy the images are rendered from (the truth's landmarks and labels).
        case_ct: the CT the case gives the registration (``patient`` itself in the ideal world).
        simulator: the physics simulator of ``patient`` (its femur moves).
    """

    patient: Volume
    case_ct: Volume
    simulator: ArticulatedSimulator


@functools.lru_cache(maxsize=1)
def _fine_patient(
    phantom_seed: int, spacing_mm: float, image_size: int, device: str
) -> tuple[Volume, ArticulatedSimulator]:
    # one per process: a 0.5 mm phantom and its simulator take a few GB, its densities held as
    # uint16 on the CPU (within 1e-5 of the image's range) so that a trial stays under 4 GB; a
    # patient at the studies' phantom's spacing or coarser is that phantom, imaged as the ideal world
    patient = hip_phantom(seed=phantom_seed, spacing_mm=spacing_mm)
    sim = ArticulatedSimulator(
        patient,
        femur_side="left",
        config=SimulationConfig(image_size=image_size),
        device=device,
        quantise=spacing_mm < QUANTISE_FINER_THAN_MM,
    )
    return patient, sim


def world_anatomy(
    ct: str,
    phantom_seed: int,
    world_ct: CTWorld,
    *,
    image_size: int,
    device: str,
    rng: np.random.Generator,
) -> WorldAnatomy:
    """The patient, its simulator and the case's CT (module docstring).

    Args:
        ct: ``"phantom"`` or a labelled CT path.
        phantom_seed: the phantom's seed.
        world_ct: the CT's error source; off: the case's CT is the patient.
        image_size: the simulator's stored image size.
        device: torch device of the simulator.
        rng: the CT's noise, scale and label errors (nothing is drawn where the source is off).
    """
    fine = world_ct.patient_spacing_mm
    if fine is not None and str(ct).strip().lower() == "phantom":
        patient, sim = _fine_patient(int(phantom_seed), float(fine), int(image_size), str(device))
    else:
        patient, sim = anatomy_and_simulator(ct, phantom_seed, image_size, device)
    case_ct = clinical_ct(patient, world_ct, rng) if world_ct.enabled else patient
    return WorldAnatomy(patient=patient, case_ct=case_ct, simulator=sim)
