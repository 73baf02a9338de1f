"""CM 2D/3D registration workflows: single-view, multi-view and multiple-CM (Gao et al. 2022, II-C).

All three are one problem: K images (views), each of the CM at one of M base poses, with known
cameras in a common world frame, and 6 + 5 unknowns (a rigid perturbation of the CM base pose, or of
the multiple-CM reference frame, plus the five control points):

- single-view: K = 1, M = 1;
- multi-view: K views of one CM pose (cameras related through the pelvis registration), M = 1;
- multiple-CM: one C-arm pose, M images of the CM at M robot poses whose relative poses are known
  (robot kinematics + hand-eye, ``base_from_cm``), K = M; parameterised by
  :class:`~fluoronav.registration.parameterization.MultiCMReference` (reference frame: identity
  rotation, mean translation of the CM base origins).

Per view the image is cropped to a square of ``roi_size_full_px`` *full-detector* pixels (authors: 500)
around the midpoint of the two landmarks and binned to the level's resolution (authors: 4×). Images
that are already binned (``CMView.binning``, e.g. 2 for a 768² image of the 1536² CIOS detector) are
cropped to ``500 / binning`` pixels and binned ``4 / binning`` times, so the working ROI is the same.
All views share the working ROI size, so the whole CMA-ES population × all views is rendered in
one :class:`~fluoronav.rendering.cm.CMRenderer` call per generation.

Cost: Σ_views patch gradient NCC (authors: patch radius round(41/4) = 10 px at 4×, stride 5 for the
CM) + the landmark reprojection prior (eqs. 2/4) with σ in full-detector pixels (authors: 100). An
optional static background per view (the anatomy rendered once at the registered bone pose) is added
to the CM DRR; see :mod:`fluoronav.registration.cm.background`.

The parts, one job each (all names are importable from here):

- :mod:`~fluoronav.registration.cm.config`: levels and :class:`CMRegistrationConfig`;
- :mod:`~fluoronav.registration.cm.views`: :class:`CMView` and the ROIs per level;
- :mod:`~fluoronav.registration.cm.problem`: :class:`CMProblem` and :func:`register_cm`;
- :mod:`~fluoronav.registration.cm.result`: :class:`CMRegistrationResult`, :func:`cm_pose_errors`;
- :mod:`~fluoronav.registration.cm.multistart`: :func:`register_cm_multistart`;
- :mod:`~fluoronav.registration.cm.roll_scan`: :func:`roll_scan` about the A→B chord;
- :mod:`~fluoronav.registration.cm.overlays`: :func:`save_overlays`;
- :mod:`~fluoronav.registration.cm.checks`: :func:`register_cm_checked`, the registration checked
  view by view (:class:`CMCheckConfig`) and against a predicted pose (:class:`PredictedCMPose`).
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

__getattr__, __dir__ = lazy_face(
    __name__,
    {
        "fluoronav.registration.cm.checks": (
            "CMCheckConfig",
            "PredictedCMPose",
            "ViewVerdict",
            "judge_cm_views",
            "judge_motion",
            "motion_agreement",
            "register_cm_checked",
        ),
        "fluoronav.registration.cm.config": (
            "CM_COARSE_LEVEL",
            "CM_FINE_LEVEL",
            "DEFAULT_CM_MU_PER_MM",
            "CMRegistrationConfig",
            "default_cm_levels",
            "fbg_shape_prior",
        ),
        "fluoronav.registration.cm.multistart": ("register_cm_multistart",),
        "fluoronav.registration.cm.overlays": ("edge_mask", "save_overlays", "to_uint8"),
        "fluoronav.registration.cm.problem": ("CMProblem", "Workflow", "register_cm"),
        "fluoronav.registration.cm.result": ("CMRegistrationResult", "cm_pose_errors"),
        "fluoronav.registration.cm.roll_scan": ("RollScanResult", "roll_scan", "roll_scan_initialization"),
        "fluoronav.registration.cm.views": ("BackgroundFn", "CMView", "ViewROI", "view_roi"),
    },
)
