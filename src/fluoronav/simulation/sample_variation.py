"""A training sample's domain randomisation, drawn from its own random stream and recorded.

Before the physics (:class:`~fluoronav.simulation.xray.ImageVariation`, decided once the sample's
labels are known): the spectrum, dose, blur and scatter, collimator blades and a wedge that keep the
CM's landmarks in the field (:mod:`fluoronav.simulation.randomisation`), and distractor metal near the
CM (:mod:`fluoronav.simulation.distractors`). After it: the detector's response, a partial field of
view and the image's orientation, the mask, landmarks and camera moved with the image. With every
source off nothing is drawn and the sample is the scene's image itself.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fluoronav.geometry.camera import Camera
from fluoronav.simulation.distractors import DISTRACTORS_OFF, DistractorConfig, distractor_densities
from fluoronav.simulation.physics import XrayPhysics
from fluoronav.simulation.randomisation import (
    RANDOMISATION_OFF,
    RandomisationConfig,
    beam_filter_densities,
    output_camera,
    randomise_image,
    randomised_physics,
)
from fluoronav.simulation.xray import ImageVariation, SimulatedImage, VaryImage

__all__ = ["SampleVariation", "vary_after", "vary_before"]


@dataclass(frozen=True)
class SampleVariation:
    """What a data set randomises per sample (all off by default: the scene's image itself).

    Attributes:
        randomisation: physics, beam filters, detector response, field of view, orientation.
        distractors: the kinds and sizes of distractor metal.
        p_distractors: the share of samples that get distractor metal (drawn per sample).
    """

    randomisation: RandomisationConfig = RANDOMISATION_OFF
    distractors: DistractorConfig = DISTRACTORS_OFF
    p_distractors: float = 0.5

    def __post_init__(self) -> None:
        if not 0.0 <= self.p_distractors <= 1.0:
            raise ValueError(f"p_distractors must be in [0, 1], got {self.p_distractors}")

    @property
    def enabled(self) -> bool:
        """Whether any source can draw at all."""
        return self != SampleVariation(p_distractors=self.p_distractors)


def _cm_points_world(world_from_cm: np.ndarray, tip_z_mm: float) -> np.ndarray:
    """(2, 3) the CM's base and the point ``tip_z_mm`` along its straight axis, world mm."""
    base = np.asarray(world_from_cm, np.float64)
    return np.stack([base[:3, 3], base[:3, 3] + tip_z_mm * base[:3, 2]])


def vary_before(
    variation: SampleVariation,
    physics: XrayPhysics,
    rng: np.random.Generator,
    record: dict[str, Any],
    *,
    world_from_cm: np.ndarray,
    tip_z_mm: float,
    device: str | torch.device = "cpu",
) -> VaryImage:
    """The simulator's ``vary`` hook: draws the sample's physics (from ``physics``, the detector
    pixels'), beam filters (the landmarks kept in the field) and distractor metal (near the CM's
    pose ``world_from_cm``, a negative's too), writing their records into ``record``."""

    def vary(camera: Camera, landmarks_px: np.ndarray | None) -> ImageVariation:
        cfg = variation.randomisation
        drawn_physics, physics_record = randomised_physics(physics, cfg, rng)
        densities, filter_record = beam_filter_densities(
            camera.rows, camera.cols, cfg, rng, keep_points_px=landmarks_px, device=device
        )
        metal: list[dict[str, Any]] = []
        if variation.distractors != DISTRACTORS_OFF and rng.random() < variation.p_distractors:
            cm_points = _cm_points_world(world_from_cm, tip_z_mm)
            metal_densities, metal = distractor_densities(
                camera, cm_points[0], variation.distractors, rng, device, near_world_mm=cm_points
            )
            for m, density in metal_densities.items():
                densities[m] = densities[m] + density if m in densities else density
        record.update(physics=physics_record, beam_filters=filter_record, distractors=metal)
        return ImageVariation(physics=drawn_physics if physics_record else None, densities=densities)

    return vary


def vary_after(
    image: SimulatedImage, variation: SampleVariation, rng: np.random.Generator, record: dict[str, Any]
) -> tuple[SimulatedImage, Camera | None]:
    """The sample after its detector response, field of view and orientation are drawn: (the image
    with its mask and landmarks moved, its camera; None for a transposed image, which no camera
    gives: ``record["image"]["pixel_affine"]`` maps the stored pixels to the output's)."""
    img, mask, lm, image_record = randomise_image(
        image.image, image.mask, image.landmarks_px, variation.randomisation, rng
    )
    record["image"] = image_record
    camera = None if image_record.get("transpose") else output_camera(image.camera, image_record)
    moved = dataclasses.replace(
        image, image=img, mask=mask, landmarks_px=lm, camera=camera if camera is not None else image.camera
    )
    return moved, camera
