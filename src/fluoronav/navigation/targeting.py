"""Targeting: registered poses → CM pose relative to the femur (eq. 7) → robot target (eq. 8).

Frames: ``carm`` (C-arm camera), ``femur``, ``cm`` (CM base frame), ``ee`` (robot end effector),
``rbase`` (robot base). The femur and the robot base do not move relative to each other between
registration and navigation.

Eq. 7 (our naming): ``femur_from_cm_regi = inv(carm_from_femur_regi) · carm_from_cm_regi``.

Eq. 8 (our naming), from ``rbase_from_femur = rbase_from_ee_regi · ee_from_cm · cm_from_femur_regi``
being the same before and after the move, and ``rbase_from_ee_tar · ee_from_cm · cm_from_femur_tar``
= ``rbase_from_femur``::

    rbase_from_ee_tar = rbase_from_ee_regi · ee_from_cm · inv(femur_from_cm_regi)
                        · femur_from_cm_tar · inv(ee_from_cm)

The paper prints these with T_A^B; they chain as printed when T_A^B is read as ``a_from_b`` (then
T_Femur^CM = femur_from_cm, T_ee^Rbase = ee_from_rbase, T_CM^ee = cm_from_ee) and eq. 8 above is
exactly the inverse of the paper's eq. 8 (see docs/robot-and-calibration.md and the tests).
"""

from __future__ import annotations

import logging

import numpy as np

from fluoronav.errors import FluoronavError
from fluoronav.geometry import se3
from fluoronav.manipulator.robot import IKFailure, SerialRobot

__all__ = [
    "UnreachableTarget",
    "femur_from_cm_registered",
    "predicted_femur_from_cm",
    "rbase_from_ee_target",
    "robot_target",
    "tip_correction_target",
]

logger = logging.getLogger(__name__)


class UnreachableTarget(FluoronavError):
    """The robot cannot reach the pose that puts the CM at the planned pose."""


def femur_from_cm_registered(carm_from_femur: np.ndarray, carm_from_cm: np.ndarray) -> np.ndarray:
    """Eq. 7: registered CM pose relative to the femur.

    Args:
        carm_from_femur: (..., 4, 4) femur registration.
        carm_from_cm: (..., 4, 4) CM registration.

    Returns:
        (..., 4, 4) ``femur_from_cm = inv(carm_from_femur) · carm_from_cm``.
    """
    F = se3.as_transform_array(carm_from_femur, "carm_from_femur")
    C = se3.as_transform_array(carm_from_cm, "carm_from_cm")
    return se3.inv(F) @ C


def predicted_femur_from_cm(
    robot: SerialRobot,
    joints_deg: np.ndarray,
    joints_after_deg: np.ndarray,
    *,
    ee_from_cm: np.ndarray,
    femur_from_cm: np.ndarray,
) -> np.ndarray:
    """Where the robot's kinematics put the CM after a move, in the femur frame: ``femur_from_cm``
    (registered at ``joints_deg``, eq. 7) moved by the robot's motion to ``joints_after_deg``.

    Args:
        robot: the kinematic model the controller uses.
        joints_deg, joints_after_deg: (n_joints,) the joint readings before and after the move.
        ee_from_cm: (4, 4) hand-eye matrix.
        femur_from_cm: (4, 4) the CM registered before the move, relative to the femur.

    Returns:
        (4, 4) the predicted ``femur_from_cm`` (the femur and the robot base do not move relative to
        each other).
    """
    rbase_from_cm_1 = robot.rbase_from_ee(joints_deg) @ ee_from_cm
    rbase_from_cm_2 = robot.rbase_from_ee(np.asarray(joints_after_deg, np.float64)) @ ee_from_cm
    return np.asarray(femur_from_cm @ np.linalg.inv(rbase_from_cm_1) @ rbase_from_cm_2)


def tip_correction_target(
    femur_from_cm_regi: np.ndarray, tip_cm_mm: np.ndarray, tip_target_femur_mm: np.ndarray
) -> np.ndarray:
    """Target of a corrective move that only translates: the registered CM slid so that its tip
    lands on the planned tip, its orientation kept.

    For a registration at a reached pose whose tip is reliable but whose base orientation is not:
    base pose and shape place the tip together, and a few degrees of base rotation can trade
    against the control points with the tip nearly unchanged. Rotating the CM to the plan's
    orientation would turn such an error into the CM's axis (docs/validation.md, demo seeds); a
    translation corrects the tip and leaves the axis where the first move put it.

    Args:
        femur_from_cm_regi: (4, 4) registered CM pose relative to the femur (eq. 7).
        tip_cm_mm: (3,) the registered CM's tip in its base frame (its registered shape).
        tip_target_femur_mm: (3,) planned tip in the femur frame.

    Returns:
        (4, 4) ``femur_from_cm_target`` for :func:`robot_target`.
    """
    T = se3.as_transform_array(femur_from_cm_regi, "femur_from_cm_regi").copy()
    tip = T[:3, :3] @ np.asarray(tip_cm_mm, dtype=np.float64) + T[:3, 3]
    T[:3, 3] += np.asarray(tip_target_femur_mm, dtype=np.float64) - tip
    return T


def rbase_from_ee_target(
    rbase_from_ee_regi: np.ndarray,
    ee_from_cm: np.ndarray,
    femur_from_cm_regi: np.ndarray,
    femur_from_cm_target: np.ndarray,
) -> np.ndarray:
    """Eq. 8: end-effector pose that moves the CM to ``femur_from_cm_target``.

    Args:
        rbase_from_ee_regi: (..., 4, 4) robot forward kinematics during registration.
        ee_from_cm: (4, 4) hand-eye matrix.
        femur_from_cm_regi: (..., 4, 4) eq. 7 result.
        femur_from_cm_target: (..., 4, 4) planned CM pose relative to the femur.

    Returns:
        (..., 4, 4) ``rbase_from_ee`` target.
    """
    X = se3.as_transform_array(ee_from_cm, "ee_from_cm")
    return (
        se3.as_transform_array(rbase_from_ee_regi, "rbase_from_ee_regi")
        @ X
        @ se3.inv(se3.as_transform_array(femur_from_cm_regi, "femur_from_cm_regi"))
        @ se3.as_transform_array(femur_from_cm_target, "femur_from_cm_target")
        @ se3.inv(X)
    )


def robot_target(
    robot: SerialRobot,
    q_regi_deg: np.ndarray,
    *,
    ee_from_cm: np.ndarray,
    carm_from_femur: np.ndarray,
    carm_from_cm: np.ndarray,
    femur_from_cm_target: np.ndarray,
    tol_mm: float = 1e-6,
    tol_deg: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray]:
    """Joint target that puts the CM at the planned pose (eqs. 7, 8, then IK near ``q_regi_deg``).

    Args:
        robot: the kinematic model the controller uses.
        q_regi_deg: (6,) joint values recorded during registration.
        ee_from_cm: (4, 4) hand-eye matrix.
        carm_from_femur, carm_from_cm: (4, 4) registration results.
        femur_from_cm_target: (4, 4) planned pose (e.g. :func:`planned_femur_from_cm`).
        tol_mm, tol_deg: IK acceptance tolerance.

    Returns:
        (rbase_from_ee_target (4, 4), q_target_deg (6,)).

    Raises:
        UnreachableTarget: no joint configuration reaches the target pose.
    """
    q_regi = np.asarray(q_regi_deg, dtype=np.float64)
    femur_from_cm_regi = femur_from_cm_registered(carm_from_femur, carm_from_cm)
    target = rbase_from_ee_target(
        robot.rbase_from_ee(q_regi), ee_from_cm, femur_from_cm_regi, femur_from_cm_target
    )
    sol = robot.inverse_kinematics(target, q_reference_deg=q_regi, tol_mm=tol_mm, tol_deg=tol_deg)
    if isinstance(sol, IKFailure):
        raise UnreachableTarget(f"{robot.name}: {sol.reason}")
    logger.debug("robot target %s (branch %s)", np.round(sol.q_deg, 4), sol.branch)
    return target, sol.q_deg
