"""The robot's commands measured and bounded: joint motion, the CM tip's swept path, the move's size.

Every command the navigation gives (the first move, the correction) is measured before it is given:
how far each joint turns, the path the CM tip sweeps while the joints move linearly (its length and
its largest deviation from the straight segment), and how far the CM tip travels and the CM turns
between its registered pose and the target. The measurements go into the stage's diagnostics
(``navigation.json``, the report); a command beyond a bound of
:class:`~fluoronav.navigation.safety.SafetyConfig` is refused (:class:`NavigationRefused`) with a
reason that names the plan, the measured value and the bound.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from fluoronav.geometry import se3
from fluoronav.manipulator.robot import SerialRobot
from fluoronav.navigation.result import NavigationRefused
from fluoronav.navigation.safety import SafetyConfig
from fluoronav.navigation.targeting import SweptPath, joint_motion_deg, swept_tip_path

__all__ = [
    "CommandMotion",
    "check_correction",
    "check_first_move",
    "correction_allowed_mm",
    "measure_command",
]


@dataclass(frozen=True)
class CommandMotion:
    """What a command does to the robot and the CM.

    Attributes:
        joint_motion_deg: (n_joints,) how far each joint turns (degrees, wrapped).
        swept: the CM tip's path under linear joint interpolation (robot base frame).
        tip_move_mm: the CM tip's displacement, registered pose → target (femur frame).
        rotation_deg: the CM's rotation, registered pose → target (degrees, geodesic).
    """

    joint_motion_deg: np.ndarray
    swept: SweptPath
    tip_move_mm: float
    rotation_deg: float

    @property
    def max_joint_motion_deg(self) -> float:
        return float(np.max(self.joint_motion_deg))

    def diagnostics(self) -> dict[str, Any]:
        """The JSON-ready stage diagnostics (``joint_motion_deg`` is the largest joint's turn)."""
        return {
            "joint_motion_deg": self.max_joint_motion_deg,
            "joint_motion_per_joint_deg": [float(v) for v in self.joint_motion_deg],
            "swept_path_mm": self.swept.length_mm,
            "swept_straight_mm": self.swept.straight_mm,
            "swept_max_deviation_mm": self.swept.max_deviation_mm,
            "tip_move_mm": self.tip_move_mm,
            "rotation_deg": self.rotation_deg,
        }


def measure_command(
    robot: SerialRobot,
    q_from_deg: np.ndarray,
    q_to_deg: np.ndarray,
    *,
    ee_from_cm: np.ndarray,
    tip_cm_mm: np.ndarray,
    femur_from_cm_from: np.ndarray,
    femur_from_cm_to: np.ndarray,
    tip_to_cm_mm: np.ndarray | None = None,
) -> CommandMotion:
    """Measure a command (joints ``q_from_deg`` → ``q_to_deg``).

    Args:
        robot: the kinematic model the controller uses.
        q_from_deg, q_to_deg: (n_joints,) joints now and commanded.
        ee_from_cm: (4, 4) hand-eye matrix.
        tip_cm_mm: (3,) the CM tip in its base frame (its shape now).
        femur_from_cm_from, femur_from_cm_to: (4, 4) the CM registered now and its target.
        tip_to_cm_mm: (3,) the tip in the target's shape; ``tip_cm_mm`` by default.
    """
    tip_to = tip_cm_mm if tip_to_cm_mm is None else tip_to_cm_mm
    A = se3.as_transform_array(femur_from_cm_from, "femur_from_cm_from")
    B = se3.as_transform_array(femur_from_cm_to, "femur_from_cm_to")
    return CommandMotion(
        joint_motion_deg=joint_motion_deg(q_from_deg, q_to_deg),
        swept=swept_tip_path(robot, q_from_deg, q_to_deg, ee_from_cm=ee_from_cm, tip_cm_mm=tip_cm_mm),
        tip_move_mm=float(np.linalg.norm(se3.apply(B, tip_to) - se3.apply(A, tip_cm_mm))),
        rotation_deg=float(se3.rotation_angle_deg(A[:3, :3].T @ B[:3, :3])),
    )


def _refuse_joints(m: CommandMotion, safety: SafetyConfig, stage: str, what: str, plan_name: str) -> None:
    if m.max_joint_motion_deg > safety.max_joint_motion_deg:
        j = int(np.argmax(m.joint_motion_deg))
        raise NavigationRefused(
            stage,
            "joint_motion",
            f"plan '{plan_name}': the {what} would turn joint {j + 1} by {m.max_joint_motion_deg:.1f}°, "
            f"more than the bound {safety.max_joint_motion_deg:g}° (max_joint_motion_deg)",
        )


def check_first_move(m: CommandMotion, safety: SafetyConfig, *, plan_name: str, stage: str = "robot") -> None:
    """Refuse a first move beyond ``max_move_mm``, ``max_move_deg`` or ``max_joint_motion_deg``.

    Raises:
        NavigationRefused: check ``move_length``, ``move_rotation`` or ``joint_motion``.
    """
    if m.tip_move_mm > safety.max_move_mm:
        raise NavigationRefused(
            stage,
            "move_length",
            f"plan '{plan_name}': the first move would carry the CM tip {m.tip_move_mm:.1f} mm, "
            f"more than the bound {safety.max_move_mm:g} mm (max_move_mm)",
        )
    if m.rotation_deg > safety.max_move_deg:
        raise NavigationRefused(
            stage,
            "move_rotation",
            f"plan '{plan_name}': the first move would turn the CM by {m.rotation_deg:.1f}°, "
            f"more than the bound {safety.max_move_deg:g}° (max_move_deg)",
        )
    _refuse_joints(m, safety, stage, "first move", plan_name)


def correction_allowed_mm(safety: SafetyConfig, predicted_tip_error_mm: float) -> float:
    """The largest correction (mm) the verification can vouch for.

    The kinematics predict where the move put the CM tip; the verification images may disagree with
    that by up to ``max_motion_tip_mm``. So the tip can be at most ``predicted_tip_error_mm`` (the
    planned tip's distance from the prediction) + ``max_motion_tip_mm`` from the plan; a correction
    larger than that rests on images that contradict the robot.
    """
    return float(predicted_tip_error_mm) + safety.max_motion_tip_mm


def check_correction(
    m: CommandMotion,
    safety: SafetyConfig,
    *,
    plan_name: str,
    predicted_tip_error_mm: float,
    images_overrule: bool = False,
    stage: str = "correct",
) -> None:
    """Refuse a correction beyond ``max_correction_mm``, ``max_correction_deg``, what the
    verification vouches for (:func:`correction_allowed_mm`; not where ``images_overrule``: the
    images were judged unambiguous enough to be trusted over the kinematics,
    :mod:`fluoronav.navigation.safety`) or ``max_joint_motion_deg``.

    Raises:
        NavigationRefused: check ``correction_length``, ``correction_rotation``,
            ``correction_within_uncertainty`` or ``joint_motion``.
    """
    if m.tip_move_mm > safety.max_correction_mm:
        raise NavigationRefused(
            stage,
            "correction_length",
            f"plan '{plan_name}': the correction would move the CM tip {m.tip_move_mm:.1f} mm, "
            f"more than the bound {safety.max_correction_mm:g} mm (max_correction_mm)",
        )
    if m.rotation_deg > safety.max_correction_deg:
        raise NavigationRefused(
            stage,
            "correction_rotation",
            f"plan '{plan_name}': the correction would turn the CM by {m.rotation_deg:.2f}°, "
            f"more than the bound {safety.max_correction_deg:g}° (max_correction_deg)",
        )
    allowed = correction_allowed_mm(safety, predicted_tip_error_mm)
    if not images_overrule and m.tip_move_mm > allowed:
        raise NavigationRefused(
            stage,
            "correction_within_uncertainty",
            f"plan '{plan_name}': the correction of {m.tip_move_mm:.1f} mm is more than the "
            f"verification vouches for, {allowed:.1f} mm (the planned tip {predicted_tip_error_mm:.1f} mm "
            f"from the kinematic prediction + max_motion_tip_mm {safety.max_motion_tip_mm:g} mm)",
        )
    _refuse_joints(m, safety, stage, "correction", plan_name)
