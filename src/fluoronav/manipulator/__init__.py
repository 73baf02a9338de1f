"""The continuum manipulator (CM) and the serial robot carrying it (frames: docs/conventions.md).

- :mod:`~fluoronav.manipulator.config`: the CM's dimensions (:class:`CMConfig`, the paper's CM by
  default) and its mounting shaft;
- :mod:`~fluoronav.manipulator.kinematics`: control points → joint angles → link poses, landmarks
  A and B, tip and centreline (torch, batched);
- :mod:`~fluoronav.manipulator.geometry`: the notched solid (point membership, partial-volume
  voxelisation);
- :mod:`~fluoronav.manipulator.mesh`: triangle surface meshes and STL files;
- :mod:`~fluoronav.manipulator.robot`: DH serial robots (the UR-10 preset), inverse kinematics and
  the kinematic error model of a physical robot.
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.manipulator.config import CMConfig, load_cm_config, with_shaft
    from fluoronav.manipulator.geometry import VoxelizedCM, inside_cm, inside_cm_straight, voxelize_cm
    from fluoronav.manipulator.kinematics import CMKinematics
    from fluoronav.manipulator.mesh import cm_surface_mesh, mesh_volume, read_stl, write_stl
    from fluoronav.manipulator.robot import (
        UR10,
        DHRow,
        IKFailure,
        IKSolution,
        RobotErrorModel,
        SerialRobot,
        load_robot,
        random_configurations_deg,
        robot_to_dict,
        wrap_deg,
    )

__all__ = [
    "UR10",  # SerialRobot with Universal Robots' published DH table of the UR10 (CB3)
    "CMConfig",  # the CM's dimensions and notches (pydantic, frozen; the paper's CM by default)
    "CMKinematics",  # control points → joint angles → link poses, landmarks A/B, tip, centreline
    "DHRow",  # one standard DH row: a mm, α°, d mm, θ offset°
    "IKFailure",  # no joint solution reaches the pose; says why
    "IKSolution",  # one inverse-kinematics solution: joints in degrees, branch, residual errors
    "RobotErrorModel",  # seeded differences between a nominal robot model and the physical robot
    "SerialRobot",  # revolute serial robot from DH rows: forward kinematics, Jacobian, IK
    "VoxelizedCM",  # partial-volume occupancy of the bent CM with its voxel frame
    "cm_surface_mesh",  # triangle surface mesh of the bent CM in the CM frame
    "inside_cm",  # membership of points (CM frame, mm) in the bent CM
    "inside_cm_straight",  # membership of points in the straight CM solid
    "load_cm_config",  # a CMConfig from TOML or JSON (missing keys keep the paper's values)
    "load_robot",  # a robot by name ("UR10") or from a DH file (JSON)
    "mesh_volume",  # enclosed volume of a closed triangle mesh, mm³
    "random_configurations_deg",  # n joint configurations spread about a centre, degrees
    "read_stl",  # triangles and normals of a binary STL file
    "robot_to_dict",  # a robot as the DH file object load_robot reads
    "voxelize_cm",  # partial-volume voxelisation of the bent CM (supersampled)
    "with_shaft",  # the CM with its mounting shaft as a longer base tube
    "wrap_deg",  # angles wrapped to (−180°, 180°]
    "write_stl",  # write a binary STL (float32, mm) with unit face normals
]

__getattr__, __dir__ = lazy_face(__name__)
