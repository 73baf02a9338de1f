"""What the navigation's CM checks would see of a study's (unchecked) CM registration.

The registration studies register without checks and measure every result against the truth; the
values the navigation's checks (:mod:`fluoronav.registration.cm.checks`) would judge are recorded
beside those errors, so that a study's rows give the checks' ROC: how well each value separates
accurate registrations from wrong ones.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from fluoronav.registration.cm import CMRegistrationConfig, CMRegistrationResult
from fluoronav.registration.cm.checks import shape_departure_sigmas
from fluoronav.registration.cm.diagnostics import cm_view_diagnostics
from fluoronav.registration.view_set import FluoroView

__all__ = ["check_values"]


def check_values(
    res: CMRegistrationResult,
    views: Sequence[FluoroView],
    reading_deg: np.ndarray,
    prior: CMRegistrationConfig,
) -> dict[str, Any]:
    """The check values of a CM registration of ``views`` (in its view order).

    Args:
        res: the registration.
        views: its views with their detections (a view without one has no landmark residual).
        reading_deg: (n_control_points,) the FBG reading the shape's prior is centred on.
        prior: the registration's settings (the prior's σ and tolerance).

    Returns:
        ``check_edge_ncc``: the worst view's edge NCC; ``check_landmark_residual_mm``: the worst
        view's landmark residual (mm at the detector; None without a detection);
        ``check_fbg_departure_sigmas``: the shape's departure from the reading in the prior's σ
        (:func:`~fluoronav.registration.cm.checks.shape_departure_sigmas`; None without a prior).
    """
    diags = cm_view_diagnostics(
        res,
        [None if v.detection is None else v.detection.landmarks_px for v in views],
        [v.camera.pixel_spacing_mm for v in views],
    )
    residuals = [d.landmark_residual_mm for d in diags if d.landmark_residual_mm is not None]
    out: dict[str, Any] = {
        "check_edge_ncc": min(d.edge_ncc for d in diags),
        "check_landmark_residual_mm": max(residuals) if residuals else None,
        "check_fbg_departure_sigmas": None,
    }
    if prior.control_point_sigma_deg is not None:
        out["check_fbg_departure_sigmas"] = shape_departure_sigmas(
            res.control_points_deg,
            reading_deg,
            sigma_deg=prior.control_point_sigma_deg,
            tolerance_deg=prior.control_point_tolerance_deg,
        )
    return out
