"""2D/3D registration: the bones and the CM from C-arm images (Gao et al., IEEE TBME 69(1), 2022, II-B, II-C).

The methods are packages: :mod:`~fluoronav.registration.bone` (the pelvis per view, the fiducial
relating the views, and the femur about its head), :mod:`~fluoronav.registration.centerline` (the
CM's start from its landmarks and 2D centreline), :mod:`~fluoronav.registration.cm` (the CM's pose
and shape, single-view, multi-view and multiple-CM, and its checks) and
:mod:`~fluoronav.registration.view_set` (one set of views registered, bones then CM, as the
navigation does). The machinery beside them, one job each: ``engine`` (levels of an ask/tell
optimiser over a parameterisation), ``optimizer``, ``linearized``, ``levels``, ``parameterization``,
``similarity``, ``priors``, ``roi``, ``trace``, the error metrics (``metrics``) and the stage records
of a view set (``stages``); docs/architecture.md ("Registration").
"""

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.registration.engine import Registration, RegistrationResult
    from fluoronav.registration.levels import LevelConfig
    from fluoronav.registration.linearized import LinearizedRefiner
    from fluoronav.registration.metrics import axis_error_deg, base_error, cm_errors, point_error_mm
    from fluoronav.registration.optimizer import CMAES, NelderMead, OptimizationResult, Optimizer
    from fluoronav.registration.parameterization import (
        CMPoseShape,
        HandEye,
        MultiCMReference,
        Parameterization,
        RigidAboutPoint,
        RotationAboutPoint,
    )
    from fluoronav.registration.priors import LandmarkPrior, control_point_prior, gaussian_parameter_prior
    from fluoronav.registration.similarity import NCC, GradNCC, PatchGradNCC
    from fluoronav.registration.stages import StageRecord, StageRecorder
    from fluoronav.registration.trace import LevelTrace, RegistrationTrace
    from fluoronav.registration.view_set import (
        FluoroView,
        ViewDetection,
        ViewSetPrior,
        ViewSetRegistration,
        ViewSetSettings,
        register_view_set,
    )

__all__ = [
    "CMAES",  # CMA-ES (pycma) behind the ask/tell optimiser interface
    "NCC",  # normalised cross-correlation similarity
    "CMPoseShape",  # CM base pose (6) and control points (5) as optimisation parameters
    "FluoroView",  # one C-arm image with its camera and its CM detection, as a view set holds it
    "GradNCC",  # gradient NCC similarity
    "HandEye",  # hand-eye matrix parameters (image-based calibration)
    "LandmarkPrior",  # reprojection prior of the CM landmarks A and B (paper eqs. 2/4)
    "LevelConfig",  # one resolution level: binning, optimiser, population, σ, similarity
    "LevelTrace",  # what one level did: iterations, costs, seconds
    "LinearizedRefiner",  # Gauss-Newton-like refinement on linearised images (a level kind)
    "MultiCMReference",  # the multiple-CM reference frame and control points as parameters
    "NelderMead",  # Nelder-Mead behind the ask/tell optimiser interface
    "OptimizationResult",  # an optimiser's best parameters, cost and history
    "Optimizer",  # the ask/tell optimiser protocol
    "Parameterization",  # the protocol mapping parameter vectors to poses (and shapes)
    "PatchGradNCC",  # patch gradient NCC (the paper's similarity), CPU kernel or torch
    "Registration",  # the engine: levels of optimiser × renderer × similarity × prior
    "RegistrationResult",  # the engine's result: parameters, pose, cost, trace
    "RegistrationTrace",  # the per-level trace of one registration (JSON-serialisable)
    "RigidAboutPoint",  # 6-DoF rigid motion about a centre, in a reference frame's axes
    "RotationAboutPoint",  # 3-DoF rotation about a centre (the femur about its head)
    "StageRecord",  # seconds and diagnostics of one stage of a view set
    "StageRecorder",  # what a view set reports its stages to (timing, progress)
    "ViewDetection",  # a view's CM detection: landmarks, centreline, mask, confidence
    "ViewSetPrior",  # what a verification knows before it registers: femur, CM start and prediction
    "ViewSetRegistration",  # a registered view set: pelvis per view, cameras in the CT, femur, CM
    "ViewSetSettings",  # the view set's settings, the device given once
    "axis_error_deg",  # angle between two axes, degrees
    "base_error",  # CM base pose error: translation (mm) and rotation (deg) per axis
    "cm_errors",  # the paper's CM errors: tip, entry, relative, base, notches
    "control_point_prior",  # Gaussian prior on the CM's control points about a reading (FBG)
    "gaussian_parameter_prior",  # Gaussian prior on any parameters
    "point_error_mm",  # distance between two points, mm
    "register_view_set",  # one set of views registered: pelvis per view, femur, CM, with checks
]

__getattr__, __dir__ = lazy_face(__name__)
