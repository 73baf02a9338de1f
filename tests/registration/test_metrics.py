"""Study metrics against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fluoronav.registration.metrics import axis_error_deg, base_error, cm_errors, relative_error_mm
from fluoronav.studies.figures import study_figures
from fluoronav.studies.summary import summarize


def _pose(rx_deg: float = 0.0, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    a = math.radians(rx_deg)
    T = np.eye(4)
    T[1:3, 1:3] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    T[:3, 3] = t
    return T


def test_base_error_is_expressed_in_the_cm_frame() -> None:
    true = _pose(30.0, (10.0, 20.0, 400.0))
    # estimated CM frame = true frame moved by 2 mm along its own x axis and rotated 1° about its z
    delta = np.eye(4)
    delta[:3, 3] = [2.0, 0.0, 0.0]
    c, s = math.cos(math.radians(1.0)), math.sin(math.radians(1.0))
    delta[:2, :2] = [[c, -s], [s, c]]
    est = true @ delta
    e = base_error(est, true)
    assert e["base_rotation_deg"] == pytest.approx(1.0, abs=1e-9)
    assert e["base_translation_mm"] == pytest.approx(2.0, abs=1e-9)
    assert e["base_rz_deg"] == pytest.approx(-1.0, abs=1e-9)  # δ maps true → estimated frame


def test_cm_errors_translation_only() -> None:
    true = _pose(10.0, (0.0, 0.0, 450.0))
    est = true.copy()
    est[:3, 3] += [0.0, 0.0, 3.0]
    cp = np.array([1.0, 2.0, 3.0, 2.0, 1.0])
    e = cm_errors(
        carm_from_cm_est=est, carm_from_cm_true=true, control_points_est_deg=cp, control_points_true_deg=cp
    )
    assert e["tip_mm"] == pytest.approx(3.0, abs=1e-9)
    assert e["base_depth_mm"] == pytest.approx(3.0, abs=1e-9)
    assert e["notch_rotation_deg"] == pytest.approx(0.0, abs=1e-9)  # round-off of R_est^T R_true
    e2 = cm_errors(
        carm_from_cm_est=true,
        carm_from_cm_true=true,
        control_points_est_deg=cp + 0.5,
        control_points_true_deg=cp,
    )
    assert e2["notch_rotation_deg"] == pytest.approx(0.5, abs=1e-9)  # the spline is linear: +0.5 everywhere
    assert e2["tip_mm"] > 0.1


def test_relative_error() -> None:
    assert relative_error_mm(np.array([1.0, 0, 0]), np.zeros(3), np.zeros(3), np.zeros(3)) == 1.0
    # a common offset cancels
    assert relative_error_mm(
        np.array([5.0, 1, 1]), np.array([4.0, 1, 1]), np.array([1.0, 0, 0]), np.zeros(3)
    ) == pytest.approx(0.0)


def test_summary_counts_failures_and_figures(tmp_path) -> None:
    rows = [
        {
            "trial": i,
            "status": "ok",
            "tip_mm": 1.0 + i,
            "base_depth_mm": 0.5 * i,
            "seconds": 2.0,
            "base_tx_mm": 0.1,
            "base_ty_mm": 0.2,
            "base_tz_mm": 0.3,
            "base_rx_deg": 0.1,
            "base_ry_deg": 0.2,
            "base_rz_deg": 0.0,
        }
        for i in range(5)
    ]
    rows.append({"trial": 5, "status": "failed", "reason": "not converged", "tip_mm": "", "seconds": 9.0})
    s = summarize("single-view", rows, ["tip_mm"], trials=6, device="cpu")
    assert s["completed"] == 6 and s["failed"] == 1
    assert s["metrics"]["tip_mm"]["mean"] == pytest.approx(3.0)
    assert s["failure_reasons"] == {"not converged": 1}
    paths = study_figures(rows, tmp_path, workflow="single-view")
    assert {p.name for p in paths} == {"error_histograms.png", "per_axis_boxplots.png", "tip_vs_depth.png"}


def test_axis_error_is_the_angle_between_directions_whatever_their_length() -> None:
    assert axis_error_deg(np.array([1.0, 0, 0]), np.array([3.0, 3.0, 0])) == pytest.approx(45.0, abs=1e-12)
    assert axis_error_deg(np.array([0, 0, 2.0]), np.array([0, 0, -1.0])) == pytest.approx(180.0, abs=1e-12)
    assert axis_error_deg(np.array([0, 1.0, 0]), np.array([0, 2.0, 0])) == pytest.approx(0.0, abs=1e-6)
