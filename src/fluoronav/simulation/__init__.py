"""Physics-based X-ray simulation: the images every study and test registers against.

The simulator is not the registration's renderer: it models the spectrum, the materials, scatter,
the detector and quantum noise (docs/simulation.md), so that no test commits an inverse crime.

- :mod:`~fluoronav.simulation.xray`: :class:`XraySimulator`, one C-arm image of a CT and a CM;
- :mod:`~fluoronav.simulation.articulated`: pelvis and a moving femur, the navigation's images;
- ``physics``, ``materials``, ``spectrum``, ``noise``: the physics;
- ``scene``, ``protocol``, ``robot_scene``, ``cm_case``: ground truths sampled as the paper's studies, the
  hand-eye study and the CM registration cases sample them;
- :mod:`~fluoronav.simulation.dataset`: the detector's training data sets.
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.simulation.articulated import ArticulatedSimulator, anatomy_and_simulator, split_femur
    from fluoronav.simulation.cm_case import SimulatedCMCase, simulate_cm_case
    from fluoronav.simulation.dataset import DatasetSpec, simulate_dataset
    from fluoronav.simulation.dataset_check import check_dataset
    from fluoronav.simulation.materials import decompose_hu, hu_to_density, linear_attenuation_per_mm
    from fluoronav.simulation.physics import XrayPhysics
    from fluoronav.simulation.protocol import ProtocolConfig, Trial, sample_trial, simulate_trial_images
    from fluoronav.simulation.robot_scene import HandEyeScenario, sample_handeye_scenario
    from fluoronav.simulation.scene import Scene, SceneSampling, sample_scene
    from fluoronav.simulation.spectrum import Spectrum, load_spectrum
    from fluoronav.simulation.xray import SimulatedImage, SimulationConfig, XraySimulator

__all__ = [
    "ArticulatedSimulator",  # images of a patient whose femur moves relative to the pelvis
    "DatasetSpec",  # what a simulated training data set holds (sizes, sampling, physics)
    "HandEyeScenario",  # the robot, C-arm and CM ground truth of one hand-eye trial
    "ProtocolConfig",  # the paper's study protocol: ranges of poses, bends and C-arm angles
    "Scene",  # one sampled ground truth: CM pose and shape, camera, anatomy pose
    "SceneSampling",  # the ranges a scene is drawn from
    "SimulatedCMCase",  # a CM registration case: images, cameras, start and truth (arrays only)
    "SimulatedImage",  # one simulated X-ray: log image, intensities and what made it
    "SimulationConfig",  # the X-ray physics and image size of one simulator
    "Spectrum",  # a tube spectrum: photons per keV bin after filtration
    "Trial",  # one study trial's ground truth (pelvis, femur, CM, cameras)
    "XrayPhysics",  # polychromatic attenuation, scatter, detector response and noise
    "XraySimulator",  # renders a CT and a CM into a physics-simulated C-arm image
    "anatomy_and_simulator",  # the phantom (or a CT) and its articulated simulator, ready to image
    "check_dataset",  # validates a simulated data set's manifest and files
    "decompose_hu",  # CT numbers → per-material densities (adipose, soft tissue, bone)
    "hu_to_density",  # CT numbers → mass density, g/cm³
    "linear_attenuation_per_mm",  # a material's μ at given energies, 1/mm
    "load_spectrum",  # a tube spectrum by kVp and filtration from the shipped table
    "sample_handeye_scenario",  # draws a hand-eye trial's ground truth
    "sample_scene",  # draws one scene for a training sample
    "sample_trial",  # draws one study trial as the paper's protocol does
    "simulate_cm_case",  # simulates a CM registration case (single-view, multi-view, multi-CM)
    "simulate_dataset",  # writes a physics-simulated data set (resumable, Dask-parallel)
    "simulate_trial_images",  # the physics-simulated images of a study trial
    "split_femur",  # the femur's voxels and bounding box, cut from the patient volume
]

__getattr__, __dir__ = lazy_face(__name__)
