"""C-arm poses from clinical angles (docs/conventions.md, "C-arm angles").

World frame: patient LPS (+x left, +y posterior, +z superior), as ITK reads a CT; patient supine.
The source sits on a sphere of radius ``source_to_isocenter_mm`` about the isocentre, at direction

    s(α, β) = (sin β · sin α,  sin β · cos α,  cos β)         (unit vector, isocentre → source)

with α = LAO/RAO angle (about the patient's long axis, 0 = source posterior) and β = CRAN/CAUD polar
angle from the superior axis (90° = perpendicular to the long axis): α = 0°, β = 90° is AP with the
source under the table. The camera +z points from the source to the isocentre (−s); +y (image rows) is the
patient's inferior direction projected on the image plane, the head at the top; +x = y × z.
"""

from __future__ import annotations

import math

import numpy as np

from fluoronav.geometry.camera import CIOS_FUSION, Camera, DetectorSpec

__all__ = ["carm_camera", "carm_camera_from_world", "centre_on", "orbit_camera", "recentre"]


def carm_camera_from_world(
    *,
    lao_rao_deg: float,
    cran_caud_deg: float,
    source_to_isocenter_mm: float,
    isocenter_world: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> np.ndarray:
    """Rigid ``camera_from_world`` (4, 4) for a C-arm at the given angles (see module docstring)."""
    a, b = math.radians(lao_rao_deg), math.radians(cran_caud_deg)
    s = np.array([math.sin(b) * math.sin(a), math.sin(b) * math.cos(a), math.cos(b)])
    iso = np.asarray(isocenter_world, dtype=np.float64)
    source = iso + source_to_isocenter_mm * s
    z = -s
    down = np.array([0.0, 0.0, -1.0])  # patient inferior
    y = down - np.dot(down, z) * z
    if np.linalg.norm(y) < 1e-6:  # looking along the long axis: fall back to posterior as "down"
        y = np.array([0.0, 1.0, 0.0]) - z[1] * z
    y /= np.linalg.norm(y)
    x = np.cross(y, z)
    R_world_from_cam = np.stack([x, y, z], axis=1)
    T = np.eye(4)
    T[:3, :3] = R_world_from_cam.T
    T[:3, 3] = -R_world_from_cam.T @ source
    return T


def carm_camera(
    *,
    lao_rao_deg: float = 0.0,
    cran_caud_deg: float = 90.0,
    source_to_isocenter_mm: float = 450.0,
    isocenter_world: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
    detector: DetectorSpec = CIOS_FUSION,
) -> Camera:
    """A :class:`Camera` for a C-arm at clinical angles, with the CIOS Fusion detector by default."""
    T = carm_camera_from_world(
        lao_rao_deg=lao_rao_deg,
        cran_caud_deg=cran_caud_deg,
        source_to_isocenter_mm=source_to_isocenter_mm,
        isocenter_world=isocenter_world,
    )
    return Camera.from_detector(detector, T)


def orbit_camera(
    camera: Camera,
    *,
    angle_deg: float,
    isocenter_world: np.ndarray,
    axis_world: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 1.0),
) -> Camera:
    """Rotate a camera about an axis through the isocentre (default: the patient's long axis).

    Used for multi-view acquisitions ("views rotated about the C-arm orbit").
    """
    axis = np.asarray(axis_world, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    th = math.radians(angle_deg)
    Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + math.sin(th) * Kx + (1 - math.cos(th)) * Kx @ Kx
    iso = np.asarray(isocenter_world, dtype=np.float64)
    world_from_world2 = np.eye(4)  # moves the camera: new pose = rotate old pose about iso
    world_from_world2[:3, :3] = R
    world_from_world2[:3, 3] = iso - R @ iso
    cam_from_world = camera.camera_from_world @ np.linalg.inv(world_from_world2)
    return camera.with_pose(cam_from_world)


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
