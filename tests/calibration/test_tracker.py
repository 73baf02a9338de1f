"""Simulated optical tracker: exact Kabsch fit and marker-noise statistics."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fluoronav.calibration.tracker import DEFAULT_BODY, OpticalTracker, RigidBody, kabsch
from fluoronav.geometry import se3


def _random_poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    R = Rotation.random(n, random_state=seed).as_matrix()
    return se3.make(R, rng.uniform(-500, 500, (n, 3)) + np.array([0.0, 0.0, -1500.0]))


def test_kabsch_recovers_pose_exactly_and_batched():
    T = _random_poses(16, 0)
    pts = np.einsum("nij,kj->nki", T[:, :3, :3], DEFAULT_BODY.markers) + T[:, None, :3, 3]
    est = kabsch(np.broadcast_to(DEFAULT_BODY.markers, pts.shape), pts)
    np.testing.assert_allclose(est, T, atol=1e-9)
    assert np.allclose(np.linalg.det(est[:, :3, :3]), 1.0)


def test_noise_free_tracker_is_exact():
    T = _random_poses(8, 1)
    tp = OpticalTracker(marker_sigma_mm=0.0).track(T, DEFAULT_BODY, rng=np.random.default_rng(0))
    np.testing.assert_allclose(tp.tracker_from_body, T, atol=1e-9)
    assert np.all(tp.fre_rms_mm < 1e-9)


def test_marker_noise_statistics():
    sigma = 0.2
    n = 4000
    T = np.broadcast_to(_random_poses(1, 2)[0], (n, 4, 4))
    tracker = OpticalTracker(marker_sigma_mm=sigma)
    tp = tracker.track(T, DEFAULT_BODY, rng=np.random.default_rng(5))
    exact = np.einsum("ij,kj->ki", T[0, :3, :3], DEFAULT_BODY.markers) + T[0, :3, 3]
    noise = tp.markers_tracker_mm - exact
    assert abs(noise.std() - sigma) < 0.02 * sigma
    # A rigid fit of N = 4 markers absorbs 6 of 3N degrees of freedom: E[FRE²] = σ²(3N − 6)/N.
    nm = DEFAULT_BODY.markers.shape[0]
    assert abs(np.mean(tp.fre_rms_mm**2) / (sigma**2 * (3 * nm - 6) / nm) - 1.0) < 0.05
    # The centroid of the fitted body errs by the mean marker noise: E|e|² = 3σ²/N.
    c_body = DEFAULT_BODY.markers.mean(axis=0)
    c_est = np.einsum("nij,j->ni", tp.tracker_from_body[:, :3, :3], c_body) + tp.tracker_from_body[:, :3, 3]
    c_true = T[0, :3, :3] @ c_body + T[0, :3, 3]
    assert abs(np.mean(np.sum((c_est - c_true) ** 2, axis=-1)) / (3 * sigma**2 / nm) - 1.0) < 0.05


def test_tracking_is_seeded():
    T = _random_poses(3, 3)
    tr = OpticalTracker(0.25)
    a = tr.track(T, DEFAULT_BODY, rng=np.random.default_rng(9)).tracker_from_body
    b = tr.track(T, DEFAULT_BODY, rng=np.random.default_rng(9)).tracker_from_body
    c = tr.track(T, DEFAULT_BODY, rng=np.random.default_rng(10)).tracker_from_body
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_rigid_body_validation():
    with pytest.raises(ValueError, match="collinear"):
        RigidBody("line", ((0, 0, 0), (0, 0, 10), (0, 0, 20), (0, 0, 30)))
    with pytest.raises(ValueError, match="at least 3"):
        RigidBody("two", ((0, 0, 0), (0, 0, 10)))
