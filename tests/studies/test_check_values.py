"""The check values recorded beside a registration study's errors (the checks' ROC)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from fluoronav.geometry.camera import Camera
from fluoronav.registration.cm import CMRegistrationConfig
from fluoronav.registration.view_set import FluoroView, ViewDetection
from fluoronav.studies.check_values import check_values


def _disc(shift: int = 0) -> np.ndarray:
    yy, xx = np.mgrid[:48, :48]
    return ((xx - 24 - shift) ** 2 + (yy - 24) ** 2 < 100).astype(np.float64)


@dataclass
class _Result:
    """A stand-in registration: per view its registered landmarks and its ROI image and DRR."""

    landmarks_px: list[np.ndarray]
    roi_images: list[np.ndarray]
    roi_drrs: list[np.ndarray]
    control_points_deg: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.2, -0.3, 0.0, 0.1]))


def _view(name: str, landmarks: np.ndarray | None) -> FluoroView:
    cam = Camera(64, 64, np.array([[500.0, 0, 32], [0, 500.0, 32], [0, 0, 1]]), np.eye(4), 0.5)
    det = None
    if landmarks is not None:
        det = ViewDetection(landmarks, None, np.zeros((64, 64), bool), np.ones(2), "oracle")
    return FluoroView(name, np.zeros((64, 64)), cam, det)


def test_check_values_are_the_worst_views_and_the_shapes_departure() -> None:
    lm = np.array([[10.0, 10.0], [30.0, 20.0]])
    res = _Result(
        landmarks_px=[lm, lm + np.array([[0.0, 0.0], [3.0, 4.0]]), lm],
        roi_images=[_disc(), _disc(), _disc()],
        roi_drrs=[_disc(), _disc(), _disc(shift=12)],  # the third view's CM elsewhere
    )
    views = [_view("a", lm), _view("b", lm), _view("c", None)]
    prior = CMRegistrationConfig(control_point_sigma_deg=0.1, control_point_tolerance_deg=0.0)
    out = check_values(res, views, np.zeros(5), prior)  # type: ignore[arg-type]
    assert out["check_landmark_residual_mm"] == pytest.approx(5.0 * 0.5)  # 5 px at 0.5 mm
    assert out["check_edge_ncc"] < 0.2  # the displaced view, the others match exactly
    assert out["check_fbg_departure_sigmas"] == pytest.approx(3.0)  # 0.3° over 0.1°
    flat = CMRegistrationConfig(control_point_sigma_deg=None)
    assert check_values(res, views, np.zeros(5), flat)["check_fbg_departure_sigmas"] is None  # type: ignore[arg-type]
