"""Fixtures shared by the articulated simulator's tests."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.geometry.carm import carm_camera
from fluoronav.simulation.physics import XrayPhysics
from fluoronav.simulation.scene import cm_pose_along
from fluoronav.simulation.xray import SimulationConfig

#: the articulated tests' stored image size (px)
ARTICULATED_SIZE = 128


@pytest.fixture(scope="module")
def setup() -> tuple[Any, ...]:
    """A 2 mm phantom, noise-free physics at 128², a C-arm at the femoral head and a CM 5 mm into
    the femur along the entry's axis: (volume, config, camera, world_from_cm, control points)."""
    vol = hip_phantom(seed=0, spacing_mm=2.0)
    physics = XrayPhysics(energy_bin_keV=3.0, photons_per_pixel=None)
    cfg = SimulationConfig(physics=physics, image_size=ARTICULATED_SIZE)
    head = vol.landmarks_world["femoral_head_left"]
    entry = vol.landmarks_world["entry_left"]
    axis = (head - entry) / np.linalg.norm(head - entry)
    world_from_cm = cm_pose_along(entry + 5.0 * axis, axis, 0.3)
    cp = np.array([3.0, 2.0, 1.0, 0.0, -1.0])
    camera = carm_camera(isocenter_world=head, source_to_isocenter_mm=450.0)
    return vol, cfg, camera, world_from_cm, cp
