"""How well the robot's kinematics say where a move took the CM (:class:`KinematicUncertainty`).

The prediction is the first registration of the CM (relative to the femur) carried by the robot's
relative motion, ``femur_from_cm_2 = femur_from_cm_1 · cm_1_from_cm_2`` with
``cm_1_from_cm_2 = (ee_from_cm)⁻¹ · ee_1_from_ee_2 · ee_from_cm``. Its error
(:func:`prediction_sigma_mm`), to first order with independent terms: the first registration's
error, carried along; the robot's positioning error over the move; a hand-eye rotation error δ
turning the motion's translation ``t`` (``|t| · δ``); a hand-eye translation error ``e`` moving the
CM by ``(R − I) e`` for a motion rotation ``R`` of angle θ (``2 sin(θ/2) |e|``).

Frames: ``femur`` (the CT frame moved with the femur), ``rbase``, ``ee``, ``cm``; mm and degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fluoronav.geometry import se3
from fluoronav.manipulator.robot import SerialRobot
from fluoronav.navigation.targeting import predicted_femur_from_cm

__all__ = ["KinematicUncertainty", "prediction_sigma_mm"]


@dataclass(frozen=True)
class KinematicUncertainty:
    """Stated uncertainties (1 σ, per axis) of what the kinematic prediction is made of.

    Attributes:
        registration_mm: the first registration's CM relative to the femur (the navigation
            study's ``cm_relative_mm``, docs/validation.md).
        robot_mm: the robot's positioning error over a move of ~100 mm (a UR10's repeatability is
            ±0.1 mm; its nominal kinematic model errs by a few tenths of a millimetre over such a
            move).
        handeye_deg, handeye_mm: the hand-eye calibration's rotation and translation error (the
            image-based calibration's measured accuracy, docs/validation.md).
    """

    registration_mm: float = 0.5
    robot_mm: float = 0.3
    handeye_deg: float = 0.4
    handeye_mm: float = 0.5


def prediction_sigma_mm(
    robot: SerialRobot,
    joints_deg: np.ndarray,
    joints_after_deg: np.ndarray,
    *,
    ee_from_cm: np.ndarray,
    uncertainty: KinematicUncertainty,
) -> float:
    """σ (mm, per axis) of the CM's predicted position after the robot moved from ``joints_deg`` to
    ``joints_after_deg`` (module docstring): the root sum of squares of the four terms."""
    # the CM's own motion: the prediction of a CM registered at the identity
    cm1_from_cm2 = predicted_femur_from_cm(
        robot,
        np.asarray(joints_deg, np.float64),
        joints_after_deg,
        ee_from_cm=ee_from_cm,
        femur_from_cm=np.eye(4),
    )
    t = float(np.linalg.norm(cm1_from_cm2[:3, 3]))
    theta = math.radians(float(se3.rotation_angle_deg(cm1_from_cm2[:3, :3])))
    u = uncertainty
    terms = (
        u.registration_mm,
        u.robot_mm,
        t * math.radians(u.handeye_deg),
        2.0 * math.sin(theta / 2.0) * u.handeye_mm,
    )
    return float(math.sqrt(sum(x * x for x in terms)))
