"""CM 2D/3D registration workflows: single-view, multi-view and multiple-CM (Gao et al. 2022, II-C).

All three are one problem: K views, each of the CM at one of M base poses, with known cameras in one
world frame, and 6 + 5 unknowns (a rigid perturbation of the CM base pose, or of the multiple-CM
reference frame, and the five control points). Single-view: K = M = 1; multi-view: K views of one
pose; multiple-CM: one C-arm pose, M = K images at robot poses of known relative pose
(``base_from_cm``; :class:`~fluoronav.registration.parameterization.MultiCMReference`). The ROIs,
the cost and the levels: docs/registration.md. The parts (all names importable from here):
``config``, ``views`` (:class:`CMView`), ``problem`` (:func:`register_cm`), ``result``,
``multistart``, ``roll_scan``, ``overlays``, ``background`` (the anatomy behind the CM) and
``checks`` (:func:`register_cm_checked`: view by view and against a predicted pose).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.registration.cm.checks import (
        CMCheckConfig,
        PredictedCMPose,
        ViewVerdict,
        judge_cm_views,
        judge_motion,
        motion_agreement,
        register_cm_checked,
    )
    from fluoronav.registration.cm.config import (
        CM_COARSE_LEVEL,
        CM_FINE_LEVEL,
        DEFAULT_CM_MU_PER_MM,
        CMRegistrationConfig,
        default_cm_levels,
        fbg_shape_prior,
    )
    from fluoronav.registration.cm.multistart import register_cm_multistart
    from fluoronav.registration.cm.overlays import edge_mask, save_overlays, to_uint8
    from fluoronav.registration.cm.problem import CMProblem, Workflow, register_cm
    from fluoronav.registration.cm.result import CMRegistrationResult, cm_pose_errors
    from fluoronav.registration.cm.roll_scan import RollScanResult, roll_scan, roll_scan_initialization
    from fluoronav.registration.cm.views import BackgroundFn, CMView, ViewROI, view_roi

# the former private names of the overlay helpers, still imported by ``fluoronav.cli.calibrate``

__all__ = [
    "CM_COARSE_LEVEL",
    "CM_FINE_LEVEL",
    "DEFAULT_CM_MU_PER_MM",
    "BackgroundFn",
    "CMCheckConfig",
    "CMProblem",
    "CMRegistrationConfig",
    "CMRegistrationResult",
    "CMView",
    "PredictedCMPose",
    "RollScanResult",
    "ViewROI",
    "ViewVerdict",
    "Workflow",
    "cm_pose_errors",
    "default_cm_levels",
    "edge_mask",
    "fbg_shape_prior",
    "judge_cm_views",
    "judge_motion",
    "motion_agreement",
    "register_cm",
    "register_cm_checked",
    "register_cm_multistart",
    "roll_scan",
    "roll_scan_initialization",
    "save_overlays",
    "to_uint8",
    "view_roi",
]

__getattr__, __dir__ = lazy_face(__name__)
