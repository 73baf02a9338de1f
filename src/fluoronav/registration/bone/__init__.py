"""Intensity-based 2D/3D registration of the pelvis and the femur (single and multi-view).

Pelvis (the fiducial relating the C-arm views; Gao et al. 2022, II-C): 6 DoF
(:class:`RigidAboutPoint`: about the pelvis centre, axes of the first view's camera) of the
label-masked pelvis DRR against the whole image with patch gradient NCC. Femur: 3 DoF rotation
about the femoral head (:class:`RotationAboutPoint`) after the pelvis, against the static pelvis
DRR plus the femur DRR. A bone's DRR volume is its attenuation in excess of soft tissue; each level
renders the whole population and all views in one call (``levels``); the levels are data
(``presets``); a view's ``mask`` leaves the CM and its shaft out (``views``); each view's result is
checked (``checks``). :func:`register_pelvis_per_view` gives each view's ``camera_from_patient``
(``relative_view_poses``: ``camera_k_from_camera_0``). Why these measures: docs/registration.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.registration.bone.checks import (
        BoneCheckConfig,
        BoneVerdict,
        BoneViewDiagnostics,
        bone_view_diagnostics,
        judge_bone_view,
        judge_pelvis_views,
        mirrored_view,
        pelvis_mirror_diagnosis,
        register_femur_checked,
    )
    from fluoronav.registration.bone.levels import (
        TISSUE_HU,
        bone_excess_mu,
    )
    from fluoronav.registration.bone.presets import (
        FEMUR_AUTHORS_PRESET,
        FEMUR_MULTI_VIEW_PRESET,
        FEMUR_ONE_VIEW_PRESET,
        FEMUR_TILT_START_DEG,
        FEMUR_TILT_STARTS,
        PELVIS_AUTHORS_PRESET,
        PELVIS_CMAES_PRESET,
        PELVIS_LINEARIZED_PRESET,
        PELVIS_PRESET,
        PELVIS_REFINE_PRESET,
        BoneLevel,
        BoneRegistrationConfig,
        femur_config,
        pelvis_config,
    )
    from fluoronav.registration.bone.register import (
        BoneRegistrationResult,
        bone_footprints,
        register_femur,
        register_pelvis,
        register_pelvis_per_view,
        relative_view_poses,
        views_in_ct_frame,
    )
    from fluoronav.registration.bone.views import (
        BoneView,
        static_view_composite,
        views_from_images,
    )

__all__ = [
    "FEMUR_AUTHORS_PRESET",
    "FEMUR_MULTI_VIEW_PRESET",
    "FEMUR_ONE_VIEW_PRESET",
    "FEMUR_TILT_STARTS",
    "FEMUR_TILT_START_DEG",
    "PELVIS_AUTHORS_PRESET",
    "PELVIS_CMAES_PRESET",
    "PELVIS_LINEARIZED_PRESET",
    "PELVIS_PRESET",
    "PELVIS_REFINE_PRESET",
    "TISSUE_HU",
    "BoneCheckConfig",
    "BoneLevel",
    "BoneRegistrationConfig",
    "BoneRegistrationResult",
    "BoneVerdict",
    "BoneView",
    "BoneViewDiagnostics",
    "bone_excess_mu",
    "bone_footprints",
    "bone_view_diagnostics",
    "femur_config",
    "judge_bone_view",
    "judge_pelvis_views",
    "mirrored_view",
    "pelvis_config",
    "pelvis_mirror_diagnosis",
    "register_femur",
    "register_femur_checked",
    "register_pelvis",
    "register_pelvis_per_view",
    "relative_view_poses",
    "static_view_composite",
    "views_from_images",
    "views_in_ct_frame",
]

__getattr__, __dir__ = lazy_face(__name__)
