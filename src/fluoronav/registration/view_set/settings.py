"""The settings of a view-set registration, its stages' seeds, and what an earlier registration of
the same anatomy gives a later one (:class:`ViewSetPrior`: the verification after a move).

Frames: ``ct`` (LPS, mm); ``femur`` is the CT frame moved with the femur (``ct_from_femur``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fluoronav.registration.bone import PELVIS_PRESET, PELVIS_REFINE_PRESET, BoneRegistrationConfig
from fluoronav.registration.bone.checks import BoneCheckConfig
from fluoronav.registration.cm import CMRegistrationConfig
from fluoronav.registration.cm.checks import MAX_MOTION_TIP_MM, CMCheckConfig

__all__ = [
    "ViewSetPrior",
    "ViewSetSeeds",
    "ViewSetSettings",
]


@dataclass(frozen=True)
class ViewSetSettings:
    """Settings of a view-set registration.

    Attributes:
        device: torch device of every renderer and similarity; it replaces the ``device`` of the
            sub-configs below.
        pelvis: the per-view pelvis registration's levels.
        femur: the femur registration's levels; None: the preset for the number of views
            (:func:`~fluoronav.registration.bone.presets.femur_config`).
        pelvis_refine: after a move (:attr:`ViewSetPrior.ct_from_femur`), each view's second pelvis
            registration, from the first, with the femur's footprint left out of the similarity;
            None: none.
        femur_margin_mm: how far around the femur's footprint that second registration leaves out,
            in mm at the femur (the femur's and the camera's errors, and a leg that moved a little).
        cm: the CM registration's settings (its ``cm_config`` is replaced by the CM's).
        max_cm_starts: roll minima of the centreline initialisation the CM registration starts from.
        cm_checks: thresholds of the CM registration's per-view checks
            (:mod:`~fluoronav.registration.cm.checks`); None: the CM is registered unchecked, from
            the first starts only.
        bone_checks: thresholds of the pelvis's and the femur's per-view checks
            (:mod:`~fluoronav.registration.bone.checks`); None: the bones are not checked.
    """

    device: str = "cpu"
    pelvis: BoneRegistrationConfig = PELVIS_PRESET
    femur: BoneRegistrationConfig | None = None
    pelvis_refine: BoneRegistrationConfig | None = PELVIS_REFINE_PRESET
    femur_margin_mm: float = 3.0
    cm: CMRegistrationConfig = field(default_factory=CMRegistrationConfig)
    max_cm_starts: int = 2
    cm_checks: CMCheckConfig | None = field(default_factory=CMCheckConfig)
    bone_checks: BoneCheckConfig | None = field(default_factory=BoneCheckConfig)


@dataclass(frozen=True)
class ViewSetSeeds:
    """The optimisers' seeds of the stages (each CMA-ES run takes its own)."""

    pelvis: int
    femur: int
    pelvis_refine: int
    cm: int

    @classmethod
    def from_seed(cls, seed: int) -> ViewSetSeeds:
        """Each stage's seed from one."""
        return cls(pelvis=seed + 2, femur=seed + 3, pelvis_refine=seed + 4, cm=seed + 5)


@dataclass(frozen=True, eq=False)
class ViewSetPrior:
    """What an earlier registration of the same anatomy gives a later one: the verification after
    the robot moved the CM.

    Attributes:
        ct_from_femur: (4, 4) the earlier femur: the femur starts there, and each view's pelvis is
            registered a second time with the femur's footprint left out
            (:attr:`ViewSetSettings.pelvis_refine`).
        femur_from_cm_start: (4, 4) the CM's start in the frame of the femur registered anew (the
            plan's pose, where the robot was sent).
        femur_from_cm_predicted: (4, 4) where another account (the robot's kinematics) puts the CM
            in the femur frame, or None: one start among the images' own, and the pose the
            registration is compared with afterwards (the CM stage's ``motion_tip_mm``,
            ``motion_rotation_deg``). It is not a gate: the CM is found where the images show it,
            and what a disagreement means is for the caller to judge.
        max_motion_tip_mm: the tolerance of that comparison the caller applies.
    """

    ct_from_femur: np.ndarray
    femur_from_cm_start: np.ndarray
    femur_from_cm_predicted: np.ndarray | None = None
    max_motion_tip_mm: float = MAX_MOTION_TIP_MM
