"""Centreline-based initialisation of the CM pose (Gao et al., IEEE TBME 69(1), 2022, sec. II-B).

Two detected landmarks (A = CM base origin, B = centre of the distal plane of the last notch) fix 4 of the 6
DoF of ``camera_from_cm``. The search covers the other two, A's depth ``depth_mm`` (d_A, camera-frame z) and
the roll ``theta_deg`` (θ) about the chord A→B, on both roots (``near``, ``far``) of B's ray at the model's
chord length, scored by the distance of the projected model centreline to the detected one (px), then refines
the best minima jointly with the shape. docs/registration.md ("One view's search") gives the geometry, the
search and the cost. The parts (all names importable from here): ``geometry`` (poses from (d_A, θ, branch)),
``cost``, ``shaft_depth`` (a depth cue from the shaft's width), ``joint_fit`` (the 11-DoF refinement),
``single`` (:class:`CenterlineInitConfig`, :func:`centerline_initialize`), ``multiview`` and ``evaluate``
(synthetic scenes).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from fluoronav.lazy import lazy_face

if TYPE_CHECKING:
    from fluoronav.registration.centerline.cost import centerline_cost, polyline_distance_cost
    from fluoronav.registration.centerline.evaluate import (
        CenterlineScene,
        evaluate_centerline_init,
        synthetic_centerline_scene,
    )
    from fluoronav.registration.centerline.geometry import (
        mirror_about_chord,
        poses_from_depth_theta,
        roll_about_axis_deg,
        turn_about_chord,
    )
    from fluoronav.registration.centerline.joint_fit import JointFitConfig
    from fluoronav.registration.centerline.multiview import (
        MultiViewInitConfig,
        MultiViewInitResult,
        centerline_initialize_multiview,
        multiview_start_poses,
    )
    from fluoronav.registration.centerline.shaft_depth import (
        ShaftDepthCue,
        measure_shaft_depth,
        shaft_depth_residual,
    )
    from fluoronav.registration.centerline.single import (
        ANATOMY_DEPTH_WINDOW_MM,
        CenterlineInitConfig,
        CenterlineInitResult,
        centerline_initialize,
        depth_range_about,
    )

__all__ = [
    "ANATOMY_DEPTH_WINDOW_MM",
    "CenterlineInitConfig",
    "CenterlineInitResult",
    "CenterlineScene",
    "JointFitConfig",
    "MultiViewInitConfig",
    "MultiViewInitResult",
    "ShaftDepthCue",
    "centerline_cost",
    "centerline_initialize",
    "centerline_initialize_multiview",
    "depth_range_about",
    "evaluate_centerline_init",
    "measure_shaft_depth",
    "mirror_about_chord",
    "multiview_start_poses",
    "polyline_distance_cost",
    "poses_from_depth_theta",
    "roll_about_axis_deg",
    "shaft_depth_residual",
    "synthetic_centerline_scene",
    "turn_about_chord",
]

__getattr__, __dir__ = lazy_face(__name__)
