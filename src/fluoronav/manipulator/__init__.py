"""The continuum manipulator: parametric geometry, kinematics, meshes and voxelisation."""

from fluoronav.manipulator.config import CMConfig, load_cm_config
from fluoronav.manipulator.kinematics import CMKinematics

__all__ = ["CMConfig", "CMKinematics", "load_cm_config"]
