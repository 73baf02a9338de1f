"""The continuum manipulator (geometry, kinematics, meshes, voxelisation) and the serial robot carrying it."""

from fluoronav.manipulator.config import CMConfig, load_cm_config
from fluoronav.manipulator.geometry import VoxelizedCM, inside_cm, inside_cm_straight, voxelize_cm
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.manipulator.mesh import cm_surface_mesh, write_stl

__all__ = [
    "CMConfig",
    "CMKinematics",
    "VoxelizedCM",
    "cm_surface_mesh",
    "inside_cm",
    "inside_cm_straight",
    "load_cm_config",
    "voxelize_cm",
    "write_stl",
]
