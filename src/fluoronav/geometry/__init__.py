"""Frames, rigid transforms, rotations and the C-arm camera model.

See docs/conventions.md for the frame conventions used everywhere in fluoronav.
"""

from fluoronav.geometry.camera import (
    CIOS_FUSION,
    Camera,
    DetectorSpec,
    project_points,
    stack_cameras,
    triangulate_points,
    triangulate_points_robust,
)
from fluoronav.geometry.carm import carm_camera, carm_camera_from_world, orbit_camera

__all__ = [
    "CIOS_FUSION",
    "Camera",
    "DetectorSpec",
    "carm_camera",
    "carm_camera_from_world",
    "orbit_camera",
    "project_points",
    "stack_cameras",
    "triangulate_points",
    "triangulate_points_robust",
]
