"""The bone registrations of one protocol trial against its truth: pelvis, then femur, outside a
study's trial (:mod:`fluoronav.studies.pipeline` re-exports it)."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from fluoronav.anatomy.volume import Volume
from fluoronav.registration.bone import register_femur, register_pelvis, views_from_images

__all__ = ["bone_registration_errors"]


def bone_registration_errors(trial: Any, images: list[Any], volume: Volume, *, seed: int) -> dict[str, float]:
    """Register the pelvis (from the trial's initial pose) then the femur, jointly over the images;
    errors w.r.t. the ground truth (mm, degrees) and run times (s, rough).

    Keys: ``pelvis_mm`` (at the pelvis centre), ``pelvis_deg``, ``pelvis_depth_mm`` (along the first
    view's axis), ``femur_deg``, ``entry_mm`` (‖entry_est − entry_true‖, frame independent),
    ``pelvis_s``, ``femur_s``.
    """
    views = views_from_images(images)
    pelvis = register_pelvis(
        views, volume, initial_world_from_patient=trial.initial_world_from_patient, seed=seed
    )
    femur = register_femur(
        views, volume, side=trial.side, world_from_patient=pelvis.world_from_bone, seed=seed + 1
    )

    def rot_deg(A: np.ndarray, B: np.ndarray) -> float:
        return float(np.degrees(np.linalg.norm(Rotation.from_matrix(A[:3, :3] @ B[:3, :3].T).as_rotvec())))

    c = (pelvis.world_from_bone @ np.append(trial.pelvis_center_ct, 1.0))[:3] - trial.pelvis_center_world
    entry = (femur.world_from_bone @ np.append(trial.entry_ct, 1.0))[:3]
    return {
        "pelvis_mm": float(np.linalg.norm(c)),
        "pelvis_deg": rot_deg(pelvis.world_from_bone, trial.world_from_patient),
        "pelvis_depth_mm": float(abs((trial.cameras[0].camera_from_world[:3, :3] @ c)[2])),
        "femur_deg": rot_deg(femur.world_from_bone, trial.world_from_femur),
        "entry_mm": float(np.linalg.norm(entry - trial.entry_world)),
        "pelvis_s": pelvis.seconds,
        "femur_s": femur.seconds,
    }
