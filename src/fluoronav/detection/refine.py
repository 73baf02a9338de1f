"""Landmark refinement on tube-aligned patches: the detector's third stage.

The fine stage sees the whole CM in a 128² ROI, about one stored pixel per ROI pixel, so where the
notch pattern starts (A) and ends (B) along the tube is set to about a pixel (0.6 mm at 0.582 mm
pixels). Most of the remaining error is along the tube (measured on validation: ~1 px RMS along,
~0.3 px across). This stage resamples a small patch around each landmark, aligned with the tube and
at a fixed scale at the detector (``refine_step_mm`` per patch pixel, twice the training images'
sampling), and a small U-Net predicts the landmark's heatmap there (a spatial softmax, as the other
stages).

Patch geometry (``rows × cols`` patch pixels, ``s`` input pixels per patch pixel, unit tangent ``t``
pointing from the landmark into the CM, normal ``n = (−t_v, t_u)``): patch pixel (col k, row j) samples
the input at

    c + s·((k − (cols − 1)/2)·t + (j − (rows − 1)/2)·n)

so the landmark to refine (``c``) is the patch centre and flipping the rows mirrors the patch exactly
about the tube's axis (the mirror test-time augmentation). The tangent is the direction from the
landmark to the mean of the CM mask's pixels in a ring around it (:func:`landmark_direction`): the same
estimate from the true mask in training and from the detected mask at inference.

At inference the patch's log-probabilities get a Gaussian prior around the fine stage's landmark
(σ = ``refine_prior_px`` patch pixels): the patch shows the tube's end (beyond B) or the base (before
A) a few millimetres off, which the small patch alone can mistake for the landmark; the fine stage,
which sees the whole CM, tells them apart. The detector can also read each landmark from several
patches moved along the tube (``refine_shifts_px``), the prior staying at the fine stage's landmark,
and take the mean: the network's estimate depends a little on where the landmark falls in its patch
and on the pixel grid, and that part of the error averages out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from fluoronav.detection.heatmaps import decode_logit_heatmaps

__all__ = [
    "RefineJitter",
    "RefinePatch",
    "add_center_prior",
    "decode_refine_logits",
    "landmark_direction",
    "moved_frame",
    "photometric_change",
    "refine_patch",
    "training_patch",
]

#: ring around a landmark, in patch pixels, whose mask pixels give the tube's direction
DIRECTION_RING_PATCH_PX = (8.0, 32.0)


@dataclass(frozen=True)
class RefinePatch:
    """A tube-aligned patch's frame.

    Attributes:
        center_px: (2,) (u, v) input pixels of the patch centre.
        tangent: (2,) unit vector (input pixels), along the tube, into the CM.
        step_px: input pixels per patch pixel.
        shape: (rows, cols) of the patch.
    """

    center_px: np.ndarray
    tangent: np.ndarray
    step_px: float
    shape: tuple[int, int]

    @property
    def normal(self) -> np.ndarray:
        return np.array([-self.tangent[1], self.tangent[0]])

    def shifted(self, along_px: float) -> RefinePatch:
        """The same frame with its centre moved ``along_px`` patch pixels along the tube (into the
        CM where positive)."""
        center = self.center_px + float(along_px) * self.step_px * self.tangent
        return RefinePatch(center, self.tangent, self.step_px, self.shape)

    def _origin(self) -> np.ndarray:
        rows, cols = self.shape
        return np.array([(cols - 1) / 2.0, (rows - 1) / 2.0])

    def to_input(self, points_patch: np.ndarray) -> np.ndarray:
        """(..., 2) (col, row) patch pixels → (..., 2) (u, v) input pixels."""
        q = np.asarray(points_patch, dtype=np.float64) - self._origin()
        return self.center_px + self.step_px * (q[..., :1] * self.tangent + q[..., 1:] * self.normal)

    def from_input(self, points_px: np.ndarray) -> np.ndarray:
        """(..., 2) (u, v) input pixels → (..., 2) (col, row) patch pixels."""
        d = (np.asarray(points_px, dtype=np.float64) - self.center_px) / self.step_px
        return np.stack([d @ self.tangent, d @ self.normal], axis=-1) + self._origin()

    def sample(self, image: np.ndarray) -> np.ndarray:
        """The (rows, cols) float32 patch of ``image`` (bilinear, edges repeated), zero mean and unit
        standard deviation (the image's units cancel: −log images of any dose or scale)."""
        rows, cols = self.shape
        jj, kk = np.mgrid[0:rows, 0:cols].astype(np.float64)
        uv = self.to_input(np.stack([kk, jj], axis=-1))
        v = ndimage.map_coordinates(
            np.asarray(image, dtype=np.float32), [uv[..., 1], uv[..., 0]], order=1, mode="nearest"
        )
        return ((v - v.mean()) / (v.std() + 1e-6)).astype(np.float32)


def landmark_direction(
    mask: np.ndarray, point_px: np.ndarray, *, ring_px: tuple[float, float]
) -> np.ndarray | None:
    """Unit vector (u, v) from ``point_px`` to the mean of the ``mask`` pixels at distance
    ``ring_px[0]``–``ring_px[1]`` from it (the CM's direction at one end), or None where fewer than
    5 mask pixels are in the ring."""
    # only the window around the ring: a full-size mask of a 1536² image is 2.4 M pixels
    r1 = ring_px[1]
    v0, u0 = max(int(np.floor(point_px[1] - r1)), 0), max(int(np.floor(point_px[0] - r1)), 0)
    v1, u1 = int(np.ceil(point_px[1] + r1)) + 1, int(np.ceil(point_px[0] + r1)) + 1
    vv, uu = np.nonzero(mask[v0:v1, u0:u1])
    vv, uu = vv + v0, uu + u0
    d = np.hypot(uu - point_px[0], vv - point_px[1])
    ring = (d >= ring_px[0]) & (d <= ring_px[1])
    if int(ring.sum()) < 5:
        return None
    vec = np.array([uu[ring].mean() - point_px[0], vv[ring].mean() - point_px[1]])
    norm = float(np.linalg.norm(vec))
    return vec / norm if norm > 1e-6 else None


def refine_patch(
    mask: np.ndarray, point_px: np.ndarray, *, step_px: float, shape: tuple[int, int]
) -> RefinePatch | None:
    """The patch frame around a landmark (its direction from ``mask``), or None where the mask
    gives no direction (a CM seen end-on, or a mask that ends at the landmark)."""
    lo, hi = DIRECTION_RING_PATCH_PX
    t = landmark_direction(mask, point_px, ring_px=(lo * step_px, hi * step_px))
    if t is None:
        return None
    return RefinePatch(np.asarray(point_px, dtype=np.float64), t, float(step_px), shape)


def add_center_prior(
    log_probs: torch.Tensor, *, sigma_px: float, center_px: torch.Tensor | None = None
) -> torch.Tensor:
    """(N, K, rows, cols) log-probabilities + log of an isotropic Gaussian of σ = ``sigma_px`` patch
    pixels (0: unchanged) at ``center_px`` (N, 2) (col, row) patch pixels, one per patch (None: the
    patch centre)."""
    if sigma_px <= 0:
        return log_probs
    rows, cols = log_probs.shape[-2:]
    dtype, device = log_probs.dtype, log_probs.device
    if center_px is None:
        center = torch.tensor([[(cols - 1) / 2.0, (rows - 1) / 2.0]], dtype=dtype, device=device)
    else:
        center = torch.as_tensor(center_px, dtype=dtype, device=device).reshape(-1, 2)
    v = torch.arange(rows, dtype=dtype, device=device)[None, :] - center[:, 1:]  # (N|1, rows)
    u = torch.arange(cols, dtype=dtype, device=device)[None, :] - center[:, :1]  # (N|1, cols)
    r2 = v[:, :, None] ** 2 + u[:, None, :] ** 2  # (N|1, rows, cols)
    return log_probs - r2[:, None] / (2.0 * sigma_px**2)


def decode_refine_logits(
    logits: torch.Tensor,
    *,
    sigma_px: float,
    prior_px: float,
    prior_center_px: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 1, rows, cols) refinement logits → sub-pixel peaks (N, 2) (col, row) and confidences (N,),
    after the prior (:func:`add_center_prior`; ``prior_center_px`` (N, 2), None: the patch centre)."""
    logp = torch.log_softmax(logits.flatten(-2).float(), dim=-1).reshape(logits.shape)
    prior = add_center_prior(logp, sigma_px=prior_px, center_px=prior_center_px)
    pts, conf = decode_logit_heatmaps(prior, sigma_px=sigma_px)
    return pts[:, 0], conf[:, 0]


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
