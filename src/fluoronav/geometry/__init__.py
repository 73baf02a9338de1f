"""Frames, rigid transforms, rotations and the C-arm camera model.

- :mod:`~fluoronav.geometry.camera`: the pinhole C-arm camera (OpenCV convention), camera files,
  the CIOS Fusion detector, triangulation;
- :mod:`~fluoronav.geometry.carm`: C-arm poses from clinical angles (LAO/RAO, CRAN/CAUD), orbits;
- :mod:`~fluoronav.geometry.dicom`: cameras from the geometry tags of X-ray DICOM files;
- :mod:`~fluoronav.geometry.transforms`, :mod:`~fluoronav.geometry.rotations`: batched 4×4
  transforms and rotation parameterisations in torch;
- :mod:`~fluoronav.geometry.se3`: float64 numpy transforms (robot, calibration, navigation).

The frame conventions used everywhere in fluoronav are in docs/conventions.md.
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.geometry import se3
    from fluoronav.geometry.camera import (
        CIOS_FUSION,
        Camera,
        DetectorSpec,
        project_points,
        stack_cameras,
        triangulate_points,
        triangulate_points_robust,
    )
    from fluoronav.geometry.carm import carm_camera, carm_camera_from_world, centre_on, orbit_camera, recentre
    from fluoronav.geometry.dicom import camera_from_dicom, camera_from_dicom_tags
    from fluoronav.geometry.rotations import (
        angle_between_rotations_deg,
        axis_angle_to_matrix,
        euler_to_matrix,
        matrix_to_quat,
        matrix_to_rotvec,
        quat_to_matrix,
        random_rotation_about_random_axis,
        rotvec_to_matrix,
        rotx,
        roty,
        rotz,
    )
    from fluoronav.geometry.transforms import (
        apply_transform,
        compose,
        invert_transform,
        make_transform,
        params_from_transform,
        rotation_about_point,
        transform_from_params,
    )

__all__ = [
    "CIOS_FUSION",  # DetectorSpec of the Siemens CIOS Fusion: 1536², 0.194 mm pixels, SDD 1020 mm
    "Camera",  # pinhole C-arm camera (OpenCV convention): world ↔ pixels, crops, binning, files
    "DetectorSpec",  # a flat-panel detector: rows, cols, pixel pitch mm, source-to-detector mm
    "angle_between_rotations_deg",  # geodesic angle between rotation matrices (torch, degrees)
    "apply_transform",  # apply 4×4 transforms to points (torch, batched)
    "axis_angle_to_matrix",  # rotation matrices from unit axes and angles in radians (torch)
    "camera_from_dicom",  # the camera of an X-ray DICOM file from its geometry tags
    "camera_from_dicom_tags",  # the same from DICOM tag values ("0018|1110" keys)
    "carm_camera",  # camera from C-arm angles (LAO/RAO, CRAN/CAUD) and source-to-isocentre mm
    "carm_camera_from_world",  # the pose part of carm_camera alone (4×4 camera_from_world)
    "centre_on",  # the camera slid (not rotated) so that a world point images at the centre
    "compose",  # compose 4×4 transforms right to left (torch)
    "euler_to_matrix",  # rotation matrices from Euler angles in degrees (torch)
    "invert_transform",  # inverse of rigid 4×4 transforms (torch)
    "make_transform",  # 4×4 transforms from rotations (…, 3, 3) and translations mm (torch)
    "matrix_to_quat",  # rotation matrices → quaternions (x, y, z, w) (torch)
    "matrix_to_rotvec",  # rotation matrices → rotation vectors in radians (torch)
    "orbit_camera",  # a view rotated about an axis through the isocentre (multi-view acquisitions)
    "params_from_transform",  # 4×4 → (…, 6) rotation vector rad + translation mm (torch)
    "project_points",  # pinhole projection of world points with K and camera_from_world (torch)
    "quat_to_matrix",  # quaternions (x, y, z, w) → rotation matrices (torch)
    "random_rotation_about_random_axis",  # n rotations, random axes, angles U(−max, max)° (torch)
    "recentre",  # the camera slid (not rotated) so that one world point shows where another did
    "rotation_about_point",  # 4×4 rotation about a centre point mm (torch)
    "rotvec_to_matrix",  # rotation vectors in radians → rotation matrices (torch)
    "rotx",  # rotation matrices about x by angles in radians (torch)
    "roty",  # rotation matrices about y by angles in radians (torch)
    "rotz",  # rotation matrices about z by angles in radians (torch)
    "se3",  # float64 numpy helpers for 4×4 rigid transforms (make, inv, apply, mean_rotation, ...)
    "stack_cameras",  # cameras → batched K (V, 3, 3) and camera_from_world (V, 4, 4) tensors
    "transform_from_params",  # (…, 6) rotation vector rad + translation mm → 4×4 (torch)
    "triangulate_points",  # linear (DLT) triangulation of points seen in several cameras
    "triangulate_points_robust",  # the same, dropping views whose pixel disagrees with the others
]

__getattr__, __dir__ = lazy_face(__name__)
