"""The CM's points on a C-arm image, and the angle between two vectors.

Why here: the simulator (ground truth) and the detector's training (heatmap targets) both project
points given in the CM's base frame; neither may import the other.
"""

from __future__ import annotations

import math

import numpy as np

from fluoronav.geometry.camera import Camera

__all__ = ["angle_between_deg", "project_cm_points", "shaft_ends_cm"]


def angle_between_deg(u: np.ndarray, v: np.ndarray) -> float:
    """Angle (degrees, 0–180) between two vectors (2-D or 3-D); NaN where either has no length."""
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    den = float(np.linalg.norm(u) * np.linalg.norm(v))
    if not den > 0.0:
        return math.nan
    return math.degrees(math.acos(float(np.clip(u @ v / den, -1.0, 1.0))))


def shaft_ends_cm(shaft_length_mm: float) -> np.ndarray:
    """The mounting shaft's ends (2, 3) in the CM's base frame: A and ``shaft_length_mm`` behind it."""
    return np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -float(shaft_length_mm)]])


def project_cm_points(camera: Camera, world_from_cm: np.ndarray, points_cm: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) (u, v) of points (N, 3) given in the CM's base frame, posed by
    ``world_from_cm`` (4, 4) and seen by ``camera``."""
    w = np.asarray(world_from_cm, dtype=np.float64)
    return camera.project(np.asarray(points_cm, dtype=np.float64) @ w[:3, :3].T + w[:3, 3])
