"""The reached CM tip from images and robot kinematics, weighted by what each sees (:func:`fuse_tip`).

A C-arm view measures the tip across its ray well (about ``inplane_sigma_mm``) and along it
poorly (``depth_sigma_mm``): its information is ``P/σ_in² + r rᵀ/σ_depth²`` with ``r`` the unit
ray to the tip and ``P = I − r rᵀ``. The views' information adds up; the kinematic prediction adds
``I/σ_kin²`` (its stated uncertainty, isotropic). The fused tip is the information-weighted mean
of the registered tip and the predicted one, and the registered CM is translated onto it (its
rotation and shape are the images'). With two or more views at an angle the images decide in
every direction and the fused tip moves little; with one, the depth comes from the kinematics.

Frames: the world frame of the cameras (the CT frame, LPS, mm).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from fluoronav.geometry.camera import Camera
from fluoronav.registration.cm import CMRegistrationResult

__all__ = ["TipFusionConfig", "fuse_tip"]


@dataclass(frozen=True)
class TipFusionConfig:
    """How well one view registers the CM's tip (1 σ, mm, at the CM).

    Attributes:
        inplane_sigma_mm: across the view's ray (the multi-view CM registration's tip error,
            docs/validation.md; one view is no worse across its ray).
        depth_sigma_mm: along the ray (the single-view registration's tip error, mostly depth, is
            a few millimetres, docs/validation.md).
    """

    inplane_sigma_mm: float = 0.3
    depth_sigma_mm: float = 3.0


def fuse_tip(
    cm: CMRegistrationResult,
    cameras: Sequence[Camera],
    predicted_tip_world_mm: np.ndarray,
    kinematic_sigma_mm: float,
    config: TipFusionConfig,
) -> tuple[CMRegistrationResult, dict[str, Any]]:
    """The registered CM translated onto the information-weighted mean of its tip and the
    predicted one (module docstring).

    Args:
        cm: the CM registered in ``cameras``' views (one pose).
        cameras: the views whose images the registration used (world frame).
        predicted_tip_world_mm: (3,) where the kinematics put the tip.
        kinematic_sigma_mm: the prediction's σ (mm, per axis).
        config: the views' σ.

    Returns:
        The translated registration (its ``world_from_cm``, ``camera_from_cm``, ``tip_world``,
        ``landmarks_world`` and ``landmarks_px``; the ROI renderings are the images' own) and
        diagnostics: ``mahalanobis`` (the two tips' difference over their combined covariance:
        whether they are consistent at all), ``fusion_shift_mm`` (how far the tip moved),
        ``fused_tip_sigma_mm`` (the fused tip's largest σ) and ``image_depth_sigma_mm`` (the
        images' largest σ).
    """
    tip = np.asarray(cm.tip_world[0], np.float64)
    eye = np.eye(3)
    info_img = np.zeros((3, 3))
    for cam in cameras:
        r = tip - cam.world_from_camera[:3, 3]
        r /= np.linalg.norm(r)
        rr = np.outer(r, r)
        info_img += (eye - rr) / config.inplane_sigma_mm**2 + rr / config.depth_sigma_mm**2
    info_kin = eye / kinematic_sigma_mm**2
    cov = np.linalg.inv(info_img + info_kin)
    fused = cov @ (info_img @ tip + info_kin @ np.asarray(predicted_tip_world_mm, np.float64))
    shift = fused - tip
    W = np.array(cm.world_from_cm, np.float64)
    W[:, :3, 3] += shift
    out = replace(
        cm,
        world_from_cm=W,
        camera_from_cm=np.stack([c.camera_from_world @ W[0] for c in cameras]),
        tip_world=np.asarray(cm.tip_world) + shift,
        landmarks_world=np.asarray(cm.landmarks_world) + shift,
        landmarks_px=np.stack([c.project(np.asarray(cm.landmarks_world[0]) + shift) for c in cameras]),
    )
    d = tip - np.asarray(predicted_tip_world_mm, np.float64)
    diag = {
        "mahalanobis": float(
            np.sqrt(d @ np.linalg.solve(np.linalg.inv(info_img) + np.linalg.inv(info_kin), d))
        ),
        "fusion_shift_mm": float(np.linalg.norm(shift)),
        "fused_tip_sigma_mm": float(np.sqrt(np.linalg.eigvalsh(cov).max())),
        "image_depth_sigma_mm": float(np.sqrt(np.linalg.eigvalsh(np.linalg.inv(info_img)).max())),
    }
    return out, diag
