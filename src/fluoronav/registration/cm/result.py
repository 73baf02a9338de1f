"""The outcome of a CM registration (:class:`CMRegistrationResult`) and its errors against the truth."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fluoronav.geometry.camera import Camera
from fluoronav.geometry.rotations import angle_between_rotations_deg
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.registration.trace import RegistrationTrace

__all__ = ["CMRegistrationResult", "cm_pose_errors"]


@dataclass(frozen=True, eq=False)
class CMRegistrationResult:
    """Outcome of :func:`~fluoronav.registration.cm.register_cm`.

    Attributes:
        workflow: "single-view", "multi-view" or "multi-cm".
        world_from_cm: (M, 4, 4) registered CM base pose per CM pose (M = 1 except multiple-CM).
        camera_from_cm: (K, 4, 4) registered CM pose in each view's camera.
        control_points_deg: (5,); joint_angles_deg: (27,).
        tip_world: (M, 3) distal end point; landmarks_world: (M, 2, 3) A and B.
        landmarks_px: (K, 2, 2) landmark projections in each view's image pixels.
        cost, converged, success, reason: final level's outcome (see ``RegistrationResult``).
        trace: per-level and per-iteration records; seconds: wall time of the registration.
        params: (11,) optimiser vector; view_names: (K,) labels.
        roi_images, roi_drrs: (K, h, w) fixed ROI images and final CM DRRs (without background) at
            the last level, for overlays; roi_cameras: their cameras.
        world_from_ref: (4, 4) multiple-CM reference frame (None otherwise).
        responses: per view, the measured response applied at the last level (``gain``, ``veil``,
            ``blur_mm``, ``rms``, ``level``), or None where none was measured (linear DRR).
    """

    workflow: str
    world_from_cm: np.ndarray
    camera_from_cm: np.ndarray
    control_points_deg: np.ndarray
    joint_angles_deg: np.ndarray
    tip_world: np.ndarray
    landmarks_world: np.ndarray
    landmarks_px: np.ndarray
    cost: float
    converged: bool
    success: bool
    reason: str
    trace: RegistrationTrace
    seconds: float
    params: np.ndarray
    view_names: list[str]
    roi_images: np.ndarray
    roi_drrs: np.ndarray
    roi_cameras: list[Camera]
    world_from_ref: np.ndarray | None = None
    responses: list[dict[str, float] | None] | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no images, no trace)."""
        d: dict[str, Any] = {
            "workflow": self.workflow,
            "world_from_cm": self.world_from_cm.tolist(),
            "camera_from_cm": {
                n: T.tolist() for n, T in zip(self.view_names, self.camera_from_cm, strict=True)
            },
            "control_points_deg": self.control_points_deg.tolist(),
            "joint_angles_deg": self.joint_angles_deg.tolist(),
            "tip_world_mm": self.tip_world.tolist(),
            "landmarks_world_mm": self.landmarks_world.tolist(),
            "landmarks_px": {n: p.tolist() for n, p in zip(self.view_names, self.landmarks_px, strict=True)},
            "cost": self.cost if math.isfinite(self.cost) else None,
            "converged": self.converged,
            "success": self.success,
            "reason": self.reason,
            "seconds": self.seconds,
            "n_evaluations": self.trace.n_evals,
            "params": self.params.tolist(),
        }
        if self.world_from_ref is not None:
            d["world_from_ref"] = self.world_from_ref.tolist()
        if self.responses is not None:
            d["responses"] = dict(zip(self.view_names, self.responses, strict=True))
        return d


def cm_pose_errors(
    world_from_cm: np.ndarray,
    control_points_deg: np.ndarray,
    world_from_cm_true: np.ndarray,
    control_points_true_deg: np.ndarray,
    *,
    cm_config: CMConfig | None = None,
) -> dict[str, float]:
    """Errors of a registered CM against the truth (one pose).

    Returns:
        ``tip_error_mm`` (distance of the distal end points), ``base_translation_error_mm`` and
        ``base_rotation_error_deg`` of ``δ = T_gt⁻¹ · T_reg`` (expressed in the true CM base frame),
        ``notch_rotation_error_deg`` (mean |Δ joint angle| over the notches) and
        ``control_point_error_deg`` (mean |Δ control point|).
    """
    kin = CMKinematics(cm_config or CMConfig())
    T, Tg = np.asarray(world_from_cm, np.float64), np.asarray(world_from_cm_true, np.float64)
    cp, cpg = (
        torch.as_tensor(np.asarray(c, np.float64)) for c in (control_points_deg, control_points_true_deg)
    )
    tip = T[:3, :3] @ kin.tip_cm(cp).numpy() + T[:3, 3]
    tip_g = Tg[:3, :3] @ kin.tip_cm(cpg).numpy() + Tg[:3, 3]
    delta = np.linalg.inv(Tg) @ T
    return {
        "tip_error_mm": float(np.linalg.norm(tip - tip_g)),
        "base_translation_error_mm": float(np.linalg.norm(delta[:3, 3])),
        "base_rotation_error_deg": float(
            angle_between_rotations_deg(torch.as_tensor(T[:3, :3]), torch.as_tensor(Tg[:3, :3]))
        ),
        "notch_rotation_error_deg": float(
            (kin.joint_angles_deg(cp) - kin.joint_angles_deg(cpg)).abs().mean().item()
        ),
        "control_point_error_deg": float((cp - cpg).abs().mean().item()),
    }
