"""The settings of a view-set registration, its stages' seeds, and what an earlier registration of
the same anatomy gives a later one (:class:`ViewSetPrior`: the verification after a move).

Frames: ``ct`` (LPS, mm); ``femur`` is the CT frame moved with the femur (``ct_from_femur``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluoronav.registration.bone import PELVIS_PRESET, PELVIS_REFINE_PRESET, BoneRegistrationConfig
from fluoronav.registration.bone.checks import BoneCheckConfig
from fluoronav.registration.bone.presets import FEMUR_LOCAL_PRESET
from fluoronav.registration.cm import CMRegistrationConfig
from fluoronav.registration.cm.checks import MAX_MOTION_TIP_MM, CMCheckConfig
from fluoronav.registration.levels import LevelConfig
from fluoronav.registration.view_set.fusion import TipFusionConfig
from fluoronav.settings import setting

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
        local: the views' cameras (``camera_from_ct``) are already within about a millimetre and
            a degree (views of a C-arm moved by a known motion from registered views): each view's
            pelvis is registered with ``pelvis_local`` alone (the earlier femur's footprint left
            out), and after a move the femur with ``femur_local`` from the earlier femur.
        pelvis_local, femur_local: the bones' levels in that case.
        fusion_max_gap_mm: after a move with a prediction of stated uncertainty
            (:attr:`ViewSetPrior.prediction_sigma_mm`) the CM is first registered from the
            prediction with the local levels (``fusion_cm_levels``), the views' checks judging it,
            and from the images' own starts where it fails them. With a single view, whose checks
            cannot see depth, only where its landmarks lie within this of the predicted ones
            (mm at the CM).
        fusion_max_mahalanobis: the registered tip and the predicted one are then fused
            (:func:`~fluoronav.registration.view_set.fusion.fuse_tip`) where their difference is
            within this many σ of their combined uncertainty; otherwise the images and the
            kinematics disagree, and what that means is the caller's to judge (the CM stage's
            ``motion_tip_mm``, of the fused CM where fused; the images' own in
            ``image_motion_tip_mm``).
        fusion_cm_levels: the levels of the registration from the prediction; None:
            :func:`~fluoronav.registration.cm.config.local_cm_levels` for the number of views.
        tip_fusion: how well one view registers the tip, across and along its ray.
        min_unmoved_ncc: views taken from an earlier registration's C-arm positions keep its
            bones only where each image agrees with the earlier one this well
            (:func:`~fluoronav.registration.view_set.unmoved.unmoved_ncc`; between the same scene
            and a patient moved by half a millimetre: docs/validation.md, "Unmoved C-arm positions").
    """

    device: str = setting("cpu", "torch device of every renderer and similarity")
    pelvis: BoneRegistrationConfig = setting(PELVIS_PRESET, "the per-view pelvis registration's levels")
    femur: BoneRegistrationConfig | None = setting(
        None, "the femur registration's levels; none: the preset for the number of views"
    )
    pelvis_refine: BoneRegistrationConfig | None = setting(
        PELVIS_REFINE_PRESET,
        "after a move, each view's second pelvis registration, femur left out; none: none",
    )
    femur_margin_mm: float = setting(
        3.0, "how far around the femur's footprint that registration leaves out", unit="mm", ge=0
    )
    cm: CMRegistrationConfig = setting(
        doc="the CM registration's settings", default_factory=CMRegistrationConfig
    )
    max_cm_starts: int = setting(2, "roll minima of the centreline initialisation the CM starts from", ge=1)
    cm_checks: CMCheckConfig | None = setting(
        doc="thresholds of the CM's per-view checks; none: unchecked", default_factory=CMCheckConfig
    )
    bone_checks: BoneCheckConfig | None = setting(
        doc="thresholds of the bones' per-view checks; none: unchecked", default_factory=BoneCheckConfig
    )
    local: bool = setting(False, "the views' cameras are already within about a millimetre and a degree")
    pelvis_local: BoneRegistrationConfig = setting(
        PELVIS_REFINE_PRESET, "the pelvis's levels from such cameras"
    )
    femur_local: BoneRegistrationConfig = setting(
        FEMUR_LOCAL_PRESET, "the femur's levels from the earlier femur after a move"
    )
    fusion_max_gap_mm: float = setting(
        3.0,
        "one view registers the CM from the prediction where its landmarks are this close",
        unit="mm",
        ge=0,
    )
    fusion_max_mahalanobis: float = setting(
        3.0, "the registered and predicted tips are fused where within this", unit="sigma", ge=0
    )
    fusion_cm_levels: tuple[LevelConfig, ...] | None = setting(
        None, "the CM's levels from the prediction; none: the local levels for the number of views"
    )
    tip_fusion: TipFusionConfig = setting(
        doc="how well one view registers the tip, across and along its ray", default_factory=TipFusionConfig
    )
    min_unmoved_ncc: float = setting(
        0.995, "an unmoved C-arm's view keeps the earlier bones where its image agrees this well", ge=-1, le=1
    )


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
        prediction_sigma_mm: the prediction's stated uncertainty at the CM (mm per axis, per
            point: the robot's, the hand-eye matrix's and the earlier registration's errors), or
            None. With it, where the images agree with the prediction
            (:attr:`ViewSetSettings.fusion_max_gap_mm`), the CM is registered from the
            prediction with the local levels, and its tip fused with the predicted one, each
            weighted by its uncertainty (:func:`~fluoronav.registration.view_set.fusion.fuse_tip`):
            the depth one view cannot see comes from the kinematics, the images correct the rest.
    """

    ct_from_femur: np.ndarray
    femur_from_cm_start: np.ndarray
    femur_from_cm_predicted: np.ndarray | None = None
    max_motion_tip_mm: float = MAX_MOTION_TIP_MM
    prediction_sigma_mm: float | None = None
