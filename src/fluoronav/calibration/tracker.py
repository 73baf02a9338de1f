"""Simulated optical tracker (NDI Polaris-like): rigid marker bodies, noisy markers, Kabsch poses.

Frames: ``tracker`` is the camera frame of the tracker; each rigid body has its own frame in which
its marker positions are given (mm). The tracker reports ``tracker_from_body`` estimated from the
noisy 3D marker positions by a least-squares rigid fit (Kabsch/Umeyama without scale).

Noise model: every marker position gets independent isotropic Gaussian noise of σ
``marker_sigma_mm`` per axis (default 0.1 mm, i.e. 0.17 mm 3D RMS — between the Polaris Vega's
0.12 mm and the Polaris Spectra's 0.25 mm volumetric RMS specification).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluoronav.geometry import se3

__all__ = [
    "DEFAULT_BODY",
    "OpticalTracker",
    "RigidBody",
    "TrackedPose",
    "kabsch",
]


@dataclass(frozen=True)
class RigidBody:
    """A marker body: ``markers_mm`` (N, 3) marker centres in the body frame, N ≥ 3 not collinear."""

    name: str
    markers_mm: tuple[tuple[float, float, float], ...]

    def __post_init__(self) -> None:
        m = self.markers
        if m.ndim != 2 or m.shape[1] != 3 or m.shape[0] < 3:
            raise ValueError(f"rigid body {self.name!r} needs at least 3 markers of 3 coordinates")
        centred = m - m.mean(axis=0)
        if np.linalg.svd(centred, compute_uv=False)[1] < 1e-6 * max(1.0, float(np.abs(m).max())):
            raise ValueError(f"rigid body {self.name!r}: markers are collinear")

    @property
    def markers(self) -> np.ndarray:
        """(N, 3) float64 marker positions in the body frame, mm."""
        return np.asarray(self.markers_mm, dtype=np.float64)


# Planar, asymmetric 4-marker layout with the inter-marker spacing (≈ 50–90 mm) of NDI passive tools;
# asymmetry keeps marker identities unambiguous.
DEFAULT_BODY = RigidBody(
    name="four_marker_body",
    markers_mm=((0.0, 0.0, 0.0), (0.0, 28.59, 41.02), (0.0, 0.0, 88.0), (0.0, -44.32, 40.45)),
)


def kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform mapping ``source`` points onto ``target`` points.

    Args:
        source: (..., N, 3) points in frame b.
        target: (..., N, 3) corresponding points in frame a.

    Returns:
        (..., 4, 4) ``a_from_b`` minimising Σ ||a_from_b · source − target||² (rotation with det +1).
    """
    src = np.asarray(source, dtype=np.float64)
    tgt = np.asarray(target, dtype=np.float64)
    cs = src.mean(axis=-2, keepdims=True)
    ct = tgt.mean(axis=-2, keepdims=True)
    H = np.swapaxes(src - cs, -1, -2) @ (tgt - ct)  # (..., 3, 3)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    D = np.zeros_like(H)
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    R = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
    t = ct[..., 0, :] - np.einsum("...ij,...j->...i", R, cs[..., 0, :])
    return se3.make(R, t)


@dataclass(frozen=True)
class TrackedPose:
    """A tracker reading of one body.

    Attributes:
        tracker_from_body: (..., 4, 4) estimated pose.
        markers_tracker_mm: (..., N, 3) the noisy marker positions it was fitted to.
        fre_rms_mm: (...) fiducial registration error (RMS fit residual) of each reading.
    """

    tracker_from_body: np.ndarray
    markers_tracker_mm: np.ndarray
    fre_rms_mm: np.ndarray


@dataclass(frozen=True)
class OpticalTracker:
    """Simulated optical tracker.

    Args:
        marker_sigma_mm: per-axis σ of the isotropic Gaussian marker localisation noise.
    """

    marker_sigma_mm: float = 0.1

    def observe_markers(
        self, tracker_from_body: np.ndarray, body: RigidBody, *, rng: np.random.Generator
    ) -> np.ndarray:
        """Noisy marker positions: (..., 4, 4) true poses → (..., N, 3) in the tracker frame, mm."""
        T = se3.as_transform_array(tracker_from_body, "tracker_from_body")
        exact = np.einsum("...ij,nj->...ni", T[..., :3, :3], body.markers) + T[..., None, :3, 3]
        return exact + rng.normal(0.0, self.marker_sigma_mm, exact.shape)

    @staticmethod
    def estimate_pose(markers_tracker_mm: np.ndarray, body: RigidBody) -> TrackedPose:
        """Fit the body to measured markers (..., N, 3) → :class:`TrackedPose`."""
        m = np.asarray(markers_tracker_mm, dtype=np.float64)
        src = np.broadcast_to(body.markers, m.shape)
        T = kabsch(src, m)
        fitted = np.einsum("...ij,...nj->...ni", T[..., :3, :3], src) + T[..., None, :3, 3]
        fre = np.sqrt(np.mean(np.sum((fitted - m) ** 2, axis=-1), axis=-1))
        return TrackedPose(tracker_from_body=T, markers_tracker_mm=m, fre_rms_mm=fre)

    def track(
        self, tracker_from_body: np.ndarray, body: RigidBody, *, rng: np.random.Generator
    ) -> TrackedPose:
        """Simulate one reading per pose: observe the markers with noise, then fit the body."""
        return self.estimate_pose(self.observe_markers(tracker_from_body, body, rng=rng), body)
