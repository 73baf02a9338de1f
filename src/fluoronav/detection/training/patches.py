"""Jittered training patches of the patch stages, and their labels.

The refinement stage learns from patches around each true landmark, moved and turned as the fine
stage's errors would place them (:class:`RefineJitter`: on validation ~1 px RMS along the tube,
0.3 px across, a few up to 7 px); the mask-end stage from patches around each true landmark as the
refined landmark's error places them (:class:`EndJitter`), labelled with the true mask; the
tube-mask and shaft stages from patches centred at random points of the true centreline (and, for
the shaft stage, of the projected mounting shaft, labelled not-CM).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from fluoronav.detection.patches import (
    RefinePatch,
    inside_length_px,
    patch_grid_px,
    polyline_frame,
    refine_patch,
)

__all__ = [
    "EndJitter",
    "RefineJitter",
    "moved_frame",
    "photometric_change",
    "training_end_patch",
    "training_patch",
    "training_tube_patch",
]


@dataclass(frozen=True)
class RefineJitter:
    """How far training patches start from the true landmark, in patch pixels and degrees: the fine
    stage's errors (on validation ~1 px RMS along the tube, 0.3 px across, a few up to 7 px, at
    0.5 input px per patch pixel) and those of the direction estimate.

    Attributes:
        along_sigma_px: σ of the Gaussian shift along the tube.
        along_wide_px: with probability ``p_wide`` the shift along is uniform in ± this instead.
        p_wide: probability of the wide shift.
        across_sigma_px: σ of the Gaussian shift across the tube.
        angle_sigma_deg: σ of the rotation of the patch's tangent.
        p_mirror: probability of mirroring the patch about the tube's axis.
        contrast: range of the factor on the normalised patch.
        max_noise: largest σ of Gaussian noise added to the normalised patch (uniform in [0, this]).
    """

    along_sigma_px: float = 4.0
    along_wide_px: float = 14.0
    p_wide: float = 0.2
    across_sigma_px: float = 1.6
    angle_sigma_deg: float = 6.0
    p_mirror: float = 0.5
    contrast: tuple[float, float] = (0.7, 1.3)
    max_noise: float = 0.25


def training_patch(
    image: np.ndarray,
    mask: np.ndarray,
    landmark_px: np.ndarray,
    rng: np.random.Generator,
    *,
    step_px: float,
    shape: tuple[int, int],
    jitter: RefineJitter,
    photometric: bool,
) -> tuple[np.ndarray, np.ndarray] | None:
    """A jittered training patch (rows, cols) float32 around a true landmark and the landmark in its
    pixels (2,) (col, row); None where the true mask gives no direction."""
    frame = refine_patch(mask, landmark_px, step_px=step_px, shape=shape)
    if frame is None:
        return None
    angle = rng.normal(0.0, jitter.angle_sigma_deg)
    along = (
        rng.uniform(-jitter.along_wide_px, jitter.along_wide_px)
        if rng.random() < jitter.p_wide
        else rng.normal(0.0, jitter.along_sigma_px)
    )
    across = rng.normal(0.0, jitter.across_sigma_px)
    frame = moved_frame(frame, landmark_px, angle_deg=angle, along_px=along, across_px=across)
    patch, target = frame.sample(image), frame.from_input(landmark_px)
    if rng.random() < jitter.p_mirror:  # exact mirror about the axis: rows j ↔ rows − 1 − j
        patch, target = patch[::-1].copy(), np.array([target[0], shape[0] - 1 - target[1]])
    if photometric:
        patch = photometric_change(patch, rng, contrast=jitter.contrast, max_noise=jitter.max_noise)
    return patch.astype(np.float32), target


def moved_frame(
    frame: RefinePatch, point_px: np.ndarray, *, angle_deg: float, along_px: float, across_px: float
) -> RefinePatch:
    """``frame``'s tangent turned by ``angle_deg`` and its centre put ``along_px`` and ``across_px``
    patch pixels from ``point_px`` along and across the turned tube (a training start)."""
    a = np.deg2rad(angle_deg)
    t = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ frame.tangent
    n = np.array([-t[1], t[0]])
    centre = np.asarray(point_px, dtype=np.float64) + frame.step_px * (along_px * t + across_px * n)
    return RefinePatch(centre, t, frame.step_px, frame.shape)


def photometric_change(
    patch: np.ndarray, rng: np.random.Generator, *, contrast: tuple[float, float], max_noise: float
) -> np.ndarray:
    """A normalised patch × a contrast factor uniform in ``contrast`` + Gaussian noise of a σ
    uniform in [0, ``max_noise``]."""
    return patch * rng.uniform(*contrast) + rng.normal(0.0, rng.uniform(0.0, max_noise), patch.shape)


@dataclass(frozen=True)
class EndJitter:
    """How far training patches start from the true landmark (patch pixels, degrees): the refined
    landmark's error (on validation a median of 0.3 input px, 0.6 patch px) and the direction's.

    Attributes:
        along_sigma_px: σ of the Gaussian shift along the tube.
        across_sigma_px: σ of the Gaussian shift across the tube.
        angle_sigma_deg: σ of the rotation of the patch's tangent.
        p_mirror: probability of mirroring the patch about the tube's axis.
        contrast: range of the factor on the normalised patch.
        max_noise: largest σ of Gaussian noise added to the normalised patch (uniform in [0, this]).
    """

    along_sigma_px: float = 1.0
    across_sigma_px: float = 0.6
    angle_sigma_deg: float = 5.0
    p_mirror: float = 0.5
    contrast: tuple[float, float] = (0.7, 1.3)
    max_noise: float = 0.25


def training_end_patch(
    image: np.ndarray,
    mask: np.ndarray,
    landmark_px: np.ndarray,
    rng: np.random.Generator,
    *,
    step_px: float,
    shape: tuple[int, int],
    jitter: EndJitter,
    photometric: bool,
) -> tuple[np.ndarray, np.ndarray] | None:
    """A jittered training patch (rows, cols) float32 around a true landmark and the true mask on its
    pixels (rows, cols) float32 0/1 (the label of the input pixel each patch pixel falls in); None
    where the true mask gives no direction."""
    frame = refine_patch(mask, landmark_px, step_px=step_px, shape=shape)
    if frame is None:
        return None
    angle = rng.normal(0.0, jitter.angle_sigma_deg)
    along, across = rng.normal(0.0, jitter.along_sigma_px), rng.normal(0.0, jitter.across_sigma_px)
    frame = moved_frame(frame, landmark_px, angle_deg=angle, along_px=along, across_px=across)
    return _patch_and_label(image, mask, frame, rng, jitter=jitter, photometric=photometric)


def _patch_and_label(
    image: np.ndarray,
    mask: np.ndarray,
    frame: RefinePatch,
    rng: np.random.Generator,
    *,
    jitter: EndJitter,
    photometric: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """``frame``'s patch of ``image`` and the label of ``mask`` on it (float32 0/1), mirrored about
    the tube's axis with probability ``p_mirror``, with photometric changes where asked."""
    uv = patch_grid_px(frame)
    # nearest input pixel: the label is defined per input pixel (its centre inside the envelope)
    target = ndimage.map_coordinates(
        np.asarray(mask, dtype=np.float32), [uv[..., 1], uv[..., 0]], order=0, mode="constant"
    )
    patch = frame.sample(image)
    if rng.random() < jitter.p_mirror:  # exact mirror about the axis: rows j ↔ rows − 1 − j
        patch, target = patch[::-1].copy(), target[::-1].copy()
    if photometric:
        patch = photometric_change(patch, rng, contrast=jitter.contrast, max_noise=jitter.max_noise)
    return patch.astype(np.float32), target.astype(np.float32)


def training_tube_patch(
    image: np.ndarray,
    mask: np.ndarray,
    centerline_px: np.ndarray,
    rng: np.random.Generator,
    *,
    step_px: float,
    shape: tuple[int, int],
    jitter: EndJitter,
    photometric: bool,
    shaft_px: np.ndarray | None = None,
    shaft_prob: float = 0.0,
) -> tuple[np.ndarray, np.ndarray] | None:
    """A training patch (rows, cols) float32 centred at a uniformly drawn point of the true
    centreline (N, 2), aligned with it (tangent jittered by ``angle_sigma_deg``, centre moved across
    by ``across_sigma_px`` patch px), and the true mask on its pixels (rows, cols) float32 0/1; None
    where the centreline has no length.

    With probability ``shaft_prob`` the point is drawn instead on the part inside the image of the
    projected mounting shaft ``shaft_px`` (2, 2) (A, then the shaft's far end; u, v), the patch
    aligned with the shaft: the true mask there is the CM's only, so the stage learns that a plain
    tube beyond A is not the CM (the fine stage sometimes takes a short shaft for part of it)."""
    pts = np.asarray(centerline_px, dtype=np.float64)
    length = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()) if len(pts) > 1 else 0.0
    if length <= 0.0:
        return None
    chord = 0.25 * shape[1] * step_px
    inside = inside_length_px(shaft_px, image.shape) if shaft_px is not None and shaft_prob > 0.0 else 0.0
    if inside > 0.0 and rng.random() < shaft_prob:
        assert shaft_px is not None
        a, far = np.asarray(shaft_px, dtype=np.float64)
        direction = (far - a) / np.linalg.norm(far - a)
        c, t = a + rng.uniform(0.0, inside) * direction, -direction
    else:
        c, t = polyline_frame(pts, rng.uniform(0.0, length), chord_px=chord)
    angle = rng.normal(0.0, jitter.angle_sigma_deg)
    if rng.random() < 0.5:  # either direction along the tube
        t = -t
    frame = moved_frame(
        RefinePatch(c, t, float(step_px), shape),
        c,
        angle_deg=angle,
        along_px=0.0,
        across_px=rng.normal(0.0, jitter.across_sigma_px),
    )
    return _patch_and_label(image, mask, frame, rng, jitter=jitter, photometric=photometric)
