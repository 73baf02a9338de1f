"""Which one is wrong where the verification's detections and the robot's kinematics disagree.

The CM is registered once more, from the kinematic prediction, on the images alone: no detected
landmark centres its region, pulls it or checks it (:func:`register_at_prediction`). Its outline is
then judged in each view (edge NCC, :mod:`fluoronav.registration.cm.checks`) and the detections
measured against it (:func:`images_side_with`): where it stays at the prediction, fits the images
and a view's detected landmarks lie elsewhere, the detection is wrong (another structure found);
where it does not fit them, the images show no CM at the prediction and the kinematics (the hand-eye
matrix, the joint readings) are. One view cannot tell a detection off along its ray from a CM that
is. Frames: the verification's cameras' world (CT, LPS, mm); the prediction is the femur's.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.navigation.checks.safety import SafetyConfig
from fluoronav.registration.cm import CMRegistrationResult, CMView, register_cm
from fluoronav.registration.cm.checks import CMCheckConfig, PredictedCMPose, motion_agreement
from fluoronav.registration.cm.config import local_cm_levels
from fluoronav.registration.cm.diagnostics import cm_view_diagnostics
from fluoronav.registration.view_set import FluoroView, ViewSetSettings

log = logging.getLogger(__name__)

__all__ = ["ImagesAtPrediction", "Side", "images_side_with", "register_at_prediction"]

#: what the images say: the detection is wrong, the CM is not at the kinematic prediction, or
#: neither (the CM at the prediction fits and every detection agrees with it)
Side = Literal["detection", "kinematics", "neither"]


@dataclass(frozen=True, eq=False)
class ImagesAtPrediction:
    """The CM registered from the kinematic prediction on the images alone, judged view by view.

    Attributes:
        cm: the registration (CT frame), over the views in the order given.
        edge_ncc: per view (the case's name) its gradient NCC on the registered CM's outline.
        detection_offset_mm: per view how far its detected landmarks lie from the registered CM's
            (the larger of A and B, mm at the detector); None without a detection.
        motion_tip_mm, motion_rotation_deg: the registered CM against the prediction (femur frame).
    """

    cm: CMRegistrationResult
    edge_ncc: dict[str, float]
    detection_offset_mm: dict[str, float | None]
    motion_tip_mm: float
    motion_rotation_deg: float

    def fitting(self, checks: CMCheckConfig) -> list[str]:
        """The views whose outline passes the edge check (``checks.min_edge_ncc``)."""
        return [n for n, ncc in self.edge_ncc.items() if ncc >= checks.min_edge_ncc]

    def detections_off(self, checks: CMCheckConfig) -> dict[str, float]:
        """The fitting views whose detected landmarks lie further than
        ``checks.max_landmark_residual_mm`` from the registered CM's, name → mm."""
        fit = self.fitting(checks)
        return {
            n: float(d)
            for n, d in self.detection_offset_mm.items()
            if n in fit and d is not None and d > checks.max_landmark_residual_mm
        }

    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready record (the ``verify_cm`` stage's ``at_prediction``)."""
        return {
            "views": {
                n: {"edge_ncc": self.edge_ncc[n], "detection_offset_mm": self.detection_offset_mm[n]}
                for n in self.edge_ncc
            },
            "motion_tip_mm": self.motion_tip_mm,
            "motion_rotation_deg": self.motion_rotation_deg,
        }


def register_at_prediction(
    views: Sequence[FluoroView],
    cameras: Sequence[Camera],
    predicted: PredictedCMPose,
    *,
    control_points_deg: np.ndarray,
    cm_config: CMConfig,
    settings: ViewSetSettings,
    seed: int,
) -> ImagesAtPrediction:
    """The CM registered from ``predicted`` with the verification's local levels on the images of
    ``views`` (their cameras ``cameras``, CT frame), without their detections (module docstring).

    Args:
        views: the verification's views (their detections are measured, not used).
        cameras: each view's camera placed by the verification's bones.
        predicted: the kinematic prediction (femur frame) and the registered femur.
        control_points_deg: (n_control_points,) the shape's start (the first registration's).
        cm_config: the CM's geometry.
        settings: the verification's view-set settings (``cm``, ``device``, ``fusion_cm_levels``).
        seed: the registration's seed.
    """
    levels = settings.fusion_cm_levels or local_cm_levels(len(views))
    config = settings.cm.with_(device=settings.device, cm_config=cm_config, levels=levels)
    names = [v.name for v in views]
    cm_views = [
        CMView(np.asarray(v.image, np.float32), c, name=f"{v.name} (at the prediction)")
        for v, c in zip(views, cameras, strict=True)
    ]
    cm = register_cm(
        cm_views,
        initial_control_points_deg=np.asarray(control_points_deg, np.float64),
        initial_world_from_cm=predicted.world_from_cm,
        config=config,
        seed=seed,
    )
    detected = [None if v.detection is None else v.detection.landmarks_px for v in views]
    diags = cm_view_diagnostics(cm, detected, [c.pixel_spacing_mm for c in cameras])
    motion = motion_agreement(predicted, cm, cm_config)
    return ImagesAtPrediction(
        cm=cm,
        edge_ncc={n: float(d.edge_ncc) for n, d in zip(names, diags, strict=True)},
        detection_offset_mm={n: d.landmark_residual_mm for n, d in zip(names, diags, strict=True)},
        motion_tip_mm=float(motion["motion_tip_mm"]),
        motion_rotation_deg=float(motion["motion_rotation_deg"]),
    )


def images_side_with(at: ImagesAtPrediction, checks: CMCheckConfig, safety: SafetyConfig) -> Side:
    """What the CM registered at the prediction says (:data:`Side`).

    ``"detection"``: it stayed within ``safety.max_motion_tip_mm`` of the prediction, its outline
    fits at least ``safety.detection_check_min_views`` views (``checks.min_edge_ncc``) and a fitting
    view's detected landmarks lie elsewhere (:meth:`ImagesAtPrediction.detections_off`);
    ``"kinematics"``: it left the prediction or fits too few views (no CM there);
    ``"neither"``: it fits at the prediction and every detection agrees with it.
    """
    fit = at.fitting(checks)
    if at.motion_tip_mm > safety.max_motion_tip_mm or len(fit) < safety.detection_check_min_views:
        return "kinematics"
    return "detection" if at.detections_off(checks) else "neither"
