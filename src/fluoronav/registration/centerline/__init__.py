"""Centreline-based initialisation of the CM pose (Gao et al., IEEE TBME 69(1), 2022, sec. II-B).

Two detected 2D landmarks (A = CM base origin, B = centre of the distal plane of the last notch) fix 4
of the 6 DoF of ``camera_from_cm``. The other two are searched:

- ``depth_mm`` (d_A): the camera-frame z of A (the "depth" of :meth:`Camera.backproject`), so
  ``A3D = d_A · K⁻¹ [u_A, v_A, 1]ᵀ``.
- ``theta_deg`` (θ): the roll of the CM about the chord A→B.

For a (d_A, θ), B3D is the point of B's ray at the model chord length ``L = |AB|`` (from the CM
kinematics with the FBG control points) from A3D. ``|t·r_B − A3D| = L`` is a quadratic in ``t`` with
up to two roots, the ``near`` and ``far`` branches; both are searched (a discrete third variable).
The rotation maps the chord direction of the model onto ``(B3D − A3D)/L`` and θ turns the CM's x axis
(the normal of its bending plane) about the chord, starting from ``θ = 0`` where that axis is the
unit vector along ``r_A × (B3D − A3D)`` (perpendicular to A's ray and to the chord).

A real root exists iff the distance of A3D from B's ray is at most L; that distance is linear in d_A,
so the feasible depths are ``(0, d_max]`` with ``d_max = L / |K⁻¹[u_A, v_A, 1] × r_B|`` in closed
form. The search range (``depth_range_mm``, by default 0.3–0.7 × the source-to-detector distance) is
clipped to the feasible interval before sampling; an empty intersection raises
:class:`~fluoronav.errors.RegistrationFailure`. Candidates that are still infeasible (the near
root behind the source, the model behind the source) get cost ``inf``.

Search: ``n_samples`` (d_A, θ) samples, one uniform random sample (seeded) in each cell of a
stratified ``n_depth × n_theta`` grid (≈ 25 × 40 for 1,000), each evaluated on both branches, all
candidates in one batched evaluation. Optional refinement: the best grid local minima (up to
``n_starts``) are refined together (batched) by a compass search in (d_A, θ) on their branch: the
3 × 3 stencil of ± one step around each start, moving to its best point or halving the step.

Joint refinement (``joint_refine``, default on): the grid pins A and B exactly on the detected
landmarks' rays and the chord at the FBG shape's length, so 3 px of landmark noise or 0.5° of FBG
error moves the best (d_A, θ) far along the depth valley. Each refined minimum is therefore polished
by a robust least-squares fit of all 11 DoF (pose and control points) to the centreline (point-to-
polyline distances both ways) with the landmarks and control points as Gaussian priors
(:class:`JointFitConfig`), A's depth kept inside the search range: on synthetic scenes
(:func:`evaluate_centerline_init`) it roughly halves the grid's depth error (docs/validation.md).

Cost (pixels): the model centreline (``CMKinematics.centerline_cm``) is projected with each candidate
pose; the cost is the mean of two directed terms, model points → extracted polyline and extracted
points (resampled by arc length) → projected model polyline, each the *trimmed* mean (the largest
``trim_fraction`` of the point-to-segment distances dropped) so spurs and gaps of a centreline
extracted from a segmentation do not dominate. Both endpoints coincide with the landmarks by
construction, so the symmetric term penalises a projected model that is too short or too long.

The parts, one job each (all names are importable from here):

- :mod:`~fluoronav.registration.centerline.geometry`: poses from (d_A, θ, branch), turns about the
  chord, roll errors;
- :mod:`~fluoronav.registration.centerline.cost`: the centreline cost;
- :mod:`~fluoronav.registration.centerline.shaft_depth`: the shaft's depth from its width, a depth cue;
- :mod:`~fluoronav.registration.centerline.joint_fit`: the 11-DoF joint refinement;
- :mod:`~fluoronav.registration.centerline.single`: the single-view search
  (:class:`CenterlineInitConfig`, :func:`centerline_initialize`);
- :mod:`~fluoronav.registration.centerline.multiview`: the multi-view initialisation;
- :mod:`~fluoronav.registration.centerline.evaluate`: synthetic scenes and the accuracy on them.
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

__getattr__, __dir__ = lazy_face(
    __name__,
    {
        "fluoronav.registration.centerline.cost": ("centerline_cost", "polyline_distance_cost"),
        "fluoronav.registration.centerline.evaluate": (
            "CenterlineScene",
            "evaluate_centerline_init",
            "synthetic_centerline_scene",
        ),
        "fluoronav.registration.centerline.geometry": (
            "mirror_about_chord",
            "poses_from_depth_theta",
            "roll_about_axis_deg",
            "turn_about_chord",
        ),
        "fluoronav.registration.centerline.joint_fit": ("JointFitConfig",),
        "fluoronav.registration.centerline.multiview": (
            "MultiViewInitConfig",
            "MultiViewInitResult",
            "centerline_initialize_multiview",
            "multiview_start_poses",
        ),
        "fluoronav.registration.centerline.shaft_depth": (
            "ShaftDepthCue",
            "measure_shaft_depth",
            "shaft_depth_residual",
        ),
        "fluoronav.registration.centerline.single": (
            "ANATOMY_DEPTH_WINDOW_MM",
            "CenterlineInitConfig",
            "CenterlineInitResult",
            "centerline_initialize",
            "depth_range_about",
        ),
    },
)
