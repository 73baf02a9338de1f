"""Error metrics of the paper's simulation study (§III-B), in one place.

All positions are compared in the C-arm frame of the (first) view; distances do not depend on that
choice. Names follow the study tables: ``tip_mm``, ``entry_mm``, ``relative_mm``,
``base_translation_mm``, ``base_rotation_deg``, ``notch_rotation_deg`` (+ ``depth_mm``,
``theta_deg`` for the centreline initialisation).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics

__all__ = ["axis_error_deg", "base_error", "cm_errors", "point_error_mm", "relative_error_mm"]


def _rotation_angle_deg(R: np.ndarray) -> float:
    c = (np.trace(R) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))


def _rotvec_deg(R: np.ndarray) -> np.ndarray:
    return np.degrees(Rotation.from_matrix(R).as_rotvec())


def base_error(carm_from_cm_est: np.ndarray, carm_from_cm_true: np.ndarray) -> dict[str, float]:
    """CM base pose error in the CM base frame, as the paper: δT = T_regi · T_gt⁻¹ with T = cm_from_carm.

    δT = cm_from_carm_est · carm_from_cm_true maps the true CM frame into the estimated one; its
    translation is the base origin error expressed in the CM frame and its rotation the base rotation
    error. Per-axis components are returned too (x, y, z of the CM base frame).
    """
    delta = np.linalg.inv(carm_from_cm_est) @ carm_from_cm_true
    t = delta[:3, 3]
    rv = _rotvec_deg(delta[:3, :3])
    return {
        "base_translation_mm": float(np.linalg.norm(t)),
        "base_rotation_deg": _rotation_angle_deg(delta[:3, :3]),
        "base_tx_mm": float(t[0]),
        "base_ty_mm": float(t[1]),
        "base_tz_mm": float(t[2]),
        "base_rx_deg": float(rv[0]),
        "base_ry_deg": float(rv[1]),
        "base_rz_deg": float(rv[2]),
    }


def axis_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two directions (3,) in degrees (e.g. a CM axis against the planned one)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    c = float(a @ b) / (float(np.linalg.norm(a)) * float(np.linalg.norm(b)))
    return math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))


def point_error_mm(p_est: np.ndarray, p_true: np.ndarray) -> float:
    """Euclidean distance in mm."""
    return float(np.linalg.norm(np.asarray(p_est, float) - np.asarray(p_true, float)))


def relative_error_mm(
    entry_est: np.ndarray, tip_est: np.ndarray, entry_true: np.ndarray, tip_true: np.ndarray
) -> float:
    """Eq. 11: ||(entry_gt − tip_gt) − (entry_est − tip_est)||."""
    return float(np.linalg.norm((np.asarray(entry_true) - tip_true) - (np.asarray(entry_est) - tip_est)))


def cm_errors(
    *,
    carm_from_cm_est: np.ndarray,
    carm_from_cm_true: np.ndarray,
    control_points_est_deg: np.ndarray,
    control_points_true_deg: np.ndarray,
    config: CMConfig | None = None,
) -> dict[str, float]:
    """Tip, base and notch errors of one CM registration (C-arm frame of the view given).

    Also returns ``base_depth_mm``: the error of the base origin along the camera's optical axis
    (the ambiguous direction of a single view; the paper's Fig. 13 correlates it with the tip error).
    """
    kin = CMKinematics(config or CMConfig())
    cps = torch.as_tensor(np.stack([control_points_est_deg, control_points_true_deg]), dtype=torch.float64)
    tips = kin.tip_cm(cps).numpy()
    joints = kin.joint_angles_deg(cps).numpy()
    tip_est = (carm_from_cm_est @ np.append(tips[0], 1.0))[:3]
    tip_true = (carm_from_cm_true @ np.append(tips[1], 1.0))[:3]
    out = base_error(carm_from_cm_est, carm_from_cm_true)
    out["tip_mm"] = point_error_mm(tip_est, tip_true)
    out["notch_rotation_deg"] = float(np.mean(np.abs(joints[0] - joints[1])))
    out["base_depth_mm"] = float(abs(carm_from_cm_est[2, 3] - carm_from_cm_true[2, 3]))
    return out
