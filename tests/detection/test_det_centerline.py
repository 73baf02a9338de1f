"""Centreline extraction against the known axis of synthetic tube masks."""

from __future__ import annotations

import numpy as np
import pytest
from det_synthetic import arc_mask

from fluoronav.detection.centerline import extract_centerline, resample_polyline


@pytest.mark.parametrize(("radius", "span"), [(150.0, 0.9), (80.0, 1.6), (400.0, 0.35)])
def test_centerline_follows_arc_axis(radius: float, span: float) -> None:
    centre = np.array([20.3, 15.7])
    theta0 = 0.3
    mask, lm = arc_mask((520, 480), centre, radius, theta0, theta0 + span, 20.0)
    cl = extract_centerline(mask, lm[0], lm[1], n_points=120)
    assert cl.shape == (120, 2)
    np.testing.assert_allclose(cl[0], lm[0], atol=1e-9)
    np.testing.assert_allclose(cl[-1], lm[1], atol=1e-9)
    dist = np.abs(np.linalg.norm(cl - centre, axis=1) - radius)
    assert dist[1:-1].max() < 1.0  # interior points within 1 px of the true axis
    # ordered A → B: the angle increases monotonically
    ang = np.unwrap(np.arctan2(cl[:, 1] - centre[1], cl[:, 0] - centre[0]))
    assert np.all(np.diff(ang) > 0)
    # uniform arc-length spacing
    steps = np.linalg.norm(np.diff(cl, axis=0), axis=1)
    assert steps.std() / steps.mean() < 0.05


def test_wide_tube_on_a_pooled_path_grid_is_centred_at_full_resolution() -> None:
    centre = np.array([-200.3, -215.7])
    mask, lm = arc_mask((1000, 1000), centre, 700.0, 0.5, 1.0, 60.0)
    cl = extract_centerline(mask, lm[0], lm[1], n_points=60, path_grid_px=160)  # pooled 4×
    assert np.abs(np.linalg.norm(cl - centre, axis=1) - 700.0)[1:-1].max() < 1.0


def test_centerline_reversed_landmarks_reverse_the_path() -> None:
    mask, lm = arc_mask((300, 300), np.array([0.0, 0.0]), 200.0, 0.4, 1.1, 16.0)
    fwd = extract_centerline(mask, lm[0], lm[1], n_points=50)
    bwd = extract_centerline(mask, lm[1], lm[0], n_points=50)
    assert np.max(np.linalg.norm(fwd - bwd[::-1], axis=1)) < 1.0


def test_centerline_bridges_small_gaps_in_the_mask() -> None:
    mask, lm = arc_mask((300, 300), np.array([0.0, 0.0]), 200.0, 0.4, 1.1, 16.0)
    gap = mask.copy()
    gap[:, 140:142] = False  # a 2-pixel cut across the tube
    cl = extract_centerline(gap, lm[0], lm[1])
    assert np.abs(np.linalg.norm(cl, axis=1) - 200.0)[1:-1].max() < 1.5


def test_resample_polyline_uniform() -> None:
    pts = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    out = resample_polyline(pts, 5)
    np.testing.assert_allclose(out, [[0, 0], [5, 0], [10, 0], [10, 5], [10, 10]], atol=1e-12)
