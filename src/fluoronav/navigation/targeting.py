"""Targeting: registered poses → CM pose relative to the femur (eq. 7) → robot target (eq. 8).

Frames: ``carm`` (C-arm camera), ``femur``, ``cm`` (CM base frame), ``ee`` (robot end effector),
``rbase`` (robot base); the femur and the robot base do not move relative to each other between
registration and navigation. In our naming (docs/robot-and-calibration.md, "Navigation")::

    femur_from_cm_regi = inv(carm_from_femur_regi) · carm_from_cm_regi                   (eq. 7)
    rbase_from_ee_tar = rbase_from_ee_regi · ee_from_cm · inv(femur_from_cm_regi)
                        · femur_from_cm_tar · inv(ee_from_cm)                            (eq. 8)

The paper prints T_A^B, which chain read as ``a_from_b``; eq. 8 above is then the inverse of its eq. 8.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fluoronav.errors import FluoronavError
from fluoronav.geometry import se3
from fluoronav.manipulator.robot import IKFailure, SerialRobot, wrap_deg

__all__ = [
    "LeastMotionTarget",
    "RollSearchConfig",
    "SweptPath",
    "UnreachableTarget",
    "femur_from_cm_registered",
    "joint_motion_deg",
    "least_motion_target",
    "predicted_femur_from_cm",
    "rbase_from_ee_target",
    "robot_target",
    "swept_tip_path",
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


def joint_motion_deg(q_from_deg: np.ndarray, q_to_deg: np.ndarray) -> np.ndarray:
    """(n_joints,) how far each joint turns, |wrapped q_to − q_from| in degrees."""
    return np.abs(wrap_deg(np.asarray(q_to_deg, np.float64) - np.asarray(q_from_deg, np.float64)))


@dataclass(frozen=True)
class RollSearchConfig:
    """How :func:`least_motion_target` searches the roll of a free-roll plan.

    Attributes:
        scan_step_deg: spacing of the coarse scan over the full turn; fine enough that the basin of
            the least motion is not stepped over (the joint motion changes by about the roll's step).
        refine_xatol_deg: tolerance of the bounded 1-D refinement around the scan's best roll.
        refine_maxiter: iteration cap of that refinement.
    """

    scan_step_deg: float = 5.0
    refine_xatol_deg: float = 0.01
    refine_maxiter: int = 60


@dataclass(frozen=True)
class LeastMotionTarget:
    """The reachable roll whose command moves the joints least.

    Attributes:
        roll_deg: the chosen roll (degrees, in [−180, 180)).
        femur_from_cm_target: (4, 4) the plan's pose at that roll.
        rbase_from_ee_target: (4, 4) the end-effector target (eq. 8).
        joints_target_deg: (n_joints,) the IK solution nearest the current joints.
        joint_motion_deg: largest joint turn of that command (degrees).
        n_reachable: rolls of the coarse scan the robot reaches.
    """

    roll_deg: float
    femur_from_cm_target: np.ndarray
    rbase_from_ee_target: np.ndarray
    joints_target_deg: np.ndarray
    joint_motion_deg: float
    n_reachable: int


def least_motion_target(
    robot: SerialRobot,
    q_regi_deg: np.ndarray,
    target_at_roll: Callable[[float], np.ndarray],
    *,
    ee_from_cm: np.ndarray,
    carm_from_femur: np.ndarray,
    carm_from_cm: np.ndarray,
    config: RollSearchConfig | None = None,
    tol_mm: float = 1e-6,
    tol_deg: float = 1e-6,
) -> LeastMotionTarget:
    """The roll of a free-roll plan whose robot command turns the joints least.

    The cost of a roll is the joint motion of :func:`robot_target`'s solution there (the IK branch
    nearest ``q_regi_deg``): the largest wrapped |Δq| over the joints, ties broken by their sum. A
    coarse scan over the full turn finds the basin, a bounded Brent search refines it; rolls the
    robot cannot reach are skipped. Deterministic.

    Args:
        robot, q_regi_deg, ee_from_cm, carm_from_femur, carm_from_cm, tol_mm, tol_deg: as
            :func:`robot_target`.
        target_at_roll: roll (degrees) → (4, 4) ``femur_from_cm_target`` (e.g.
            :func:`~fluoronav.navigation.planning.planned_femur_from_cm` with ``roll_deg``).
        config: the search (default :class:`RollSearchConfig`).

    Raises:
        UnreachableTarget: no roll of the scan is reachable.
    """
    cfg = config or RollSearchConfig()
    q0 = np.asarray(q_regi_deg, dtype=np.float64)
    cache: dict[float, tuple[tuple[float, float], np.ndarray, np.ndarray, np.ndarray] | None] = {}

    def solve(roll: float) -> tuple[tuple[float, float], np.ndarray, np.ndarray, np.ndarray] | None:
        roll = float(wrap_deg(roll))
        roll = -180.0 if roll == 180.0 else roll
        if roll not in cache:
            F = target_at_roll(roll)
            try:
                T, q = robot_target(
                    robot,
                    q0,
                    ee_from_cm=ee_from_cm,
                    carm_from_femur=carm_from_femur,
                    carm_from_cm=carm_from_cm,
                    femur_from_cm_target=F,
                    tol_mm=tol_mm,
                    tol_deg=tol_deg,
                )
            except UnreachableTarget:
                cache[roll] = None
            else:
                dq = joint_motion_deg(q0, q)
                cache[roll] = ((float(np.max(dq)), float(np.sum(dq))), F, T, q)
        return cache[roll]

    rolls = np.arange(-180.0, 180.0, cfg.scan_step_deg)
    scored = [(sol[0], float(r)) for r in rolls if (sol := solve(float(r))) is not None]
    if not scored:
        raise UnreachableTarget(f"{robot.name}: no roll about the insertion axis is reachable")
    best_roll = min(scored)[1]

    def cost(roll: float) -> float:
        sol = solve(roll)
        return 1e6 if sol is None else sol[0][0]  # unreachable: worse than any motion

    roll, sol = best_roll, solve(best_roll)
    refined_roll = _refine_roll(cost, best_roll, cfg)
    refined = solve(refined_roll)
    assert sol is not None
    if refined is not None and refined[0] < sol[0]:  # the refinement keeps only what it improves
        roll, sol = refined_roll, refined
    (motion, _), F, T, q = sol
    logger.debug("least-motion roll %.3f deg: joint motion %.3f deg", roll, motion)
    return LeastMotionTarget(float(wrap_deg(roll)), F, T, q, motion, len(scored))


def _refine_roll(cost: Callable[[float], float], best_roll: float, cfg: RollSearchConfig) -> float:
    """The bounded Brent search about the scan's best roll (degrees) → the refined roll (degrees)."""
    from scipy.optimize import minimize_scalar  # here: a slow import, not needed at start-up

    opt = minimize_scalar(
        cost,
        bounds=(best_roll - cfg.scan_step_deg, best_roll + cfg.scan_step_deg),
        method="bounded",
        options={"xatol": cfg.refine_xatol_deg, "maxiter": cfg.refine_maxiter},
    )
    return float(opt.x)


@dataclass(frozen=True)
class SweptPath:
    """The CM tip's path while the joints move linearly from one reading to the commanded one.

    Attributes:
        length_mm: length of the path (polyline over the samples).
        straight_mm: length of the straight segment from start to end.
        max_deviation_mm: largest distance of the path from that segment.
        tip_rbase_mm: (n, 3) the sampled tip positions in the robot base frame.
    """

    length_mm: float
    straight_mm: float
    max_deviation_mm: float
    tip_rbase_mm: np.ndarray


def swept_tip_path(
    robot: SerialRobot,
    q_from_deg: np.ndarray,
    q_to_deg: np.ndarray,
    *,
    ee_from_cm: np.ndarray,
    tip_cm_mm: np.ndarray,
    n_samples: int = 101,
) -> SweptPath:
    """Where the CM tip sweeps under linear joint interpolation (a joint move), robot base frame.

    Args:
        robot: the kinematic model.
        q_from_deg, q_to_deg: (n_joints,) start and commanded joints (the values the controller
            interpolates between, not wrapped).
        ee_from_cm: (4, 4) hand-eye matrix.
        tip_cm_mm: (3,) the CM tip in its base frame.
        n_samples: samples along the move, ends included.

    Notes:
        A joint move that is short in joint space can still swing the tip far from the straight line
        near a patient; the deviation says how far.
    """
    q0, q1 = np.asarray(q_from_deg, np.float64), np.asarray(q_to_deg, np.float64)
    tip_h = np.append(np.asarray(tip_cm_mm, np.float64), 1.0)
    X = se3.as_transform_array(ee_from_cm, "ee_from_cm")
    ts = np.linspace(0.0, 1.0, n_samples)
    pts = np.stack([(robot.rbase_from_ee(q0 + t * (q1 - q0)) @ X @ tip_h)[:3] for t in ts])
    length = float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)))
    seg = pts[-1] - pts[0]
    straight = float(np.linalg.norm(seg))
    rel = pts - pts[0]
    if straight > 1e-12:
        u = np.clip(rel @ seg / straight**2, 0.0, 1.0)
        dev = np.linalg.norm(rel - u[:, None] * seg, axis=1)
    else:
        dev = np.linalg.norm(rel, axis=1)
    return SweptPath(length, straight, float(np.max(dev)), pts)
