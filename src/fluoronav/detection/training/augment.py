"""X-ray augmentations of a square view with consistent mask and landmark handling.

Geometric: one affine about the view centre combining a flip, a rotation by a multiple of 90° and a
small rotation; the landmarks keep their identity (A stays A). Photometric (on the normalised image):
blur, gamma, contrast/brightness and Gaussian noise. Dose (on the log image before resampling, when
the data set records its photons per pixel): the quantum noise of a lower dose (:func:`lower_dose`).
Field of view (on the whole sample, before its views are made): a collimated window of the detector
(:func:`collimation_window`), so that the coarse stage sees images without air around the body and
CMs at other sizes relative to the image.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class AugmentConfig:
    """Augmentation ranges (each drawn uniformly).

    Attributes:
        p_flip: probability of a left-right flip.
        p_rot90: probability of a rotation by 90°, 180° or 270°.
        max_angle_deg: extra small rotation in [−max_angle_deg, max_angle_deg].
        gamma: range of the gamma exponent applied to |x| (sign kept).
        contrast: range of the gain.
        brightness: range ± of the offset (normalised units).
        noise_std: upper bound of the Gaussian noise std (normalised units).
        blur_sigma_px: upper bound of the Gaussian blur σ (pixels), applied with probability p_blur.
        p_low_dose: probability of re-imaging the sample at a lower dose (:func:`lower_dose`; only
            for data sets that record their photons per pixel).
        min_dose_fraction: the dose fraction is log-uniform in [min_dose_fraction, 1].
        p_collimate: probability of cropping the sample to a collimated window
            (:func:`collimation_window`) before its views are made.
        min_field_frac: each side of that window is at least this fraction of the image's side.
        p_partial_roi: probability that the fine stage's ROI is fitted to a part of the CM only
            (:func:`~fluoronav.detection.training.dataset.partial_cm_points`), so that the CM runs out of the
            ROI: at inference a coarse detection can find only part of a CM, and the fine stage must
            then segment the CM up to the ROI's edge (which adds a pass on a wider ROI) instead of
            ending it inside.
        partial_frac: range of the fraction of the CM's length (along A–B) that such a ROI is fitted to.
        p_edge_negative_roi: probability that a CM-free sample's fine ROI is centred on a strong edge
            of the image (:func:`edge_point`: bone rims, the hip joint) instead of anywhere: the coarse
            stage's false alarms start on such structures, which a random window seldom shows.
        edge_quantile: such a centre is drawn uniformly among the pixels whose smoothed gradient
            magnitude is at or above this quantile of the image's.
    """

    p_flip: float = 0.5
    p_rot90: float = 0.75
    max_angle_deg: float = 15.0
    gamma: tuple[float, float] = (0.7, 1.4)
    contrast: tuple[float, float] = (0.8, 1.25)
    brightness: float = 0.1
    noise_std: float = 0.05
    blur_sigma_px: float = 1.0
    p_blur: float = 0.3
    p_low_dose: float = 0.3
    min_dose_fraction: float = 0.25
    p_collimate: float = 0.0
    min_field_frac: float = 0.35
    p_partial_roi: float = 0.0
    partial_frac: tuple[float, float] = (0.35, 0.75)
    p_edge_negative_roi: float = 0.0
    edge_quantile: float = 0.95


def edge_point(
    image: np.ndarray, rng: np.random.Generator, *, quantile: float = 0.95, sigma_px: float = 2.0
) -> np.ndarray:
    """A pixel (u, v) of ``image`` (rows, cols) drawn uniformly among those whose gradient magnitude,
    after a Gaussian blur of ``sigma_px``, is at or above its ``quantile`` over the pixels that have
    a gradient (strong edges: bone rims and the joint in an X-ray; the blur keeps noise out of the
    choice). A flat image gives a pixel drawn uniformly."""
    img = np.asarray(image, dtype=np.float32)
    smooth = cv2.GaussianBlur(img, (0, 0), sigma_px)
    gu = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3)
    gv = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.hypot(gu, gv)
    live = mag > 1e-6 * float(mag.max()) if mag.max() > 0 else np.ones(mag.shape, bool)
    v, u = np.nonzero(live & (mag >= np.quantile(mag[live], quantile)))
    k = int(rng.integers(len(u)))
    return np.array([u[k], v[k]], dtype=np.float64)


def collimation_window(
    rng: np.random.Generator,
    shape: tuple[int, int],
    keep_box: tuple[float, float, float, float] | None,
    *,
    min_field_frac: float,
    max_field_frac: float = 1.0,
    margin_px: float = 4.0,
) -> tuple[int, int, int, int]:
    """A random rectangular field of view ``(x0, y0, x1, y1)`` (pixel edges, x1/y1 exclusive).

    Each side is uniform in [``min_field_frac``, ``max_field_frac``] of the image's side (equal
    bounds: a fixed field, as ``fluoronav evaluate --field-frac``) and the window lies inside
    the image; it contains ``keep_box`` (u0, v0, u1, v1) in pixels (the CM's mask and landmarks)
    with ``margin_px`` around it, widened where it would not fit.

    Real fluoroscopy is often collimated to a part of the detector; then there is no air in the
    image, its percentiles (and so the normalised intensities) differ from a full view, and the
    CM covers more of it.
    """
    rows, cols = shape
    # per axis: image size, then the CM's first and last pixel along it (None: no CM to keep)
    axes: list[tuple[int, float | None, float | None]] = [(cols, None, None), (rows, None, None)]
    if keep_box is not None:
        axes = [(cols, keep_box[0], keep_box[2]), (rows, keep_box[1], keep_box[3])]
    out: list[int] = []
    for n, lo_keep, hi_keep in axes:
        side = max(round(rng.uniform(min_field_frac, max_field_frac) * n), 1)
        lo_min, hi_max = 0, n - side  # range of the window's start
        if lo_keep is not None and hi_keep is not None:
            need_lo = int(np.ceil(max(hi_keep + margin_px + 1.0 - side, 0.0)))
            need_hi = int(np.floor(min(lo_keep - margin_px, float(n))))
            if need_lo > need_hi:  # the CM does not fit: widen the window to its box
                start = int(np.clip(np.floor(lo_keep - margin_px), 0, n - 1))
                stop = int(np.clip(np.ceil(hi_keep + margin_px + 1.0), start + 1, n))
                out += [start, stop]
                continue
            lo_min, hi_max = max(lo_min, need_lo), min(hi_max, need_hi)
        start = int(rng.integers(lo_min, max(hi_max, lo_min) + 1))
        out += [start, min(start + side, n)]
    x0, x1, y0, y1 = out
    return x0, y0, x1, y1


def view_affine(size: int, *, flip: bool, angle_deg: float) -> np.ndarray:
    """Forward 2×3 affine (pixel-centre coordinates) of a flip then a rotation about the view centre."""
    c = (size - 1) / 2.0
    a = np.deg2rad(angle_deg)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    F = np.diag([-1.0, 1.0]) if flip else np.eye(2)
    A = R @ F
    t = np.array([c, c]) - A @ np.array([c, c])
    return np.concatenate([A, t[:, None]], axis=1)


def apply_affine(
    affine: np.ndarray,
    image: np.ndarray,
    mask: np.ndarray,
    landmarks_uv: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Warp a square view (image, soft mask) and its landmarks (2, 2) (or None) by a forward affine."""
    size = image.shape[1], image.shape[0]
    img = cv2.warpAffine(image, affine, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    msk = cv2.warpAffine(
        mask, affine, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0
    )
    lm = None
    if landmarks_uv is not None:
        lm = np.asarray(landmarks_uv, dtype=np.float64) @ affine[:, :2].T + affine[:, 2]
    return img, msk, lm


def augment_geometric(
    rng: np.random.Generator,
    image: np.ndarray,
    mask: np.ndarray,
    landmarks_uv: np.ndarray | None,
    config: AugmentConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Random flip / 90° rotation / small rotation of a square view (rows == cols)."""
    if image.shape[0] != image.shape[1]:
        raise ValueError(f"views are square, got {image.shape}")
    flip = bool(rng.random() < config.p_flip)
    k = int(rng.integers(1, 4)) if rng.random() < config.p_rot90 else 0
    angle = 90.0 * k + float(rng.uniform(-config.max_angle_deg, config.max_angle_deg))
    return apply_affine(view_affine(image.shape[0], flip=flip, angle_deg=angle), image, mask, landmarks_uv)


def augment_photometric(rng: np.random.Generator, image: np.ndarray, config: AugmentConfig) -> np.ndarray:
    """Random blur, gamma, contrast/brightness and noise of a normalised image (values ≈ [0, 1])."""
    img: np.ndarray = np.asarray(image, dtype=np.float32)
    if config.blur_sigma_px > 0 and rng.random() < config.p_blur:
        img = cv2.GaussianBlur(img, (0, 0), float(rng.uniform(0.3, config.blur_sigma_px)))
    gamma = float(rng.uniform(*config.gamma))
    img = np.sign(img) * np.abs(img) ** gamma
    img = img * float(rng.uniform(*config.contrast)) + float(
        rng.uniform(-config.brightness, config.brightness)
    )
    noise = float(rng.uniform(0.0, config.noise_std))
    if noise > 0:
        img = img + rng.normal(0.0, noise, size=img.shape)
    return img.astype(np.float32)


def lower_dose(
    rng: np.random.Generator, log_image: np.ndarray, *, photons_per_pixel: float, dose_fraction: float
) -> np.ndarray:
    """The log image ``p = −ln(N/N0)`` as if taken with ``dose_fraction`` of the photons.

    Counts N ~ Poisson(N0·e^−p) have a log image of variance ≈ e^p / N0 per pixel; at the dose
    fraction f it is e^p / (f·N0), so Gaussian noise of variance e^p·(1/f − 1)/N0 is added (the
    sample's own noise supplies the rest). Where the added std would exceed 1 (fewer than about one
    photon) it is capped there, as the simulator clips counts at 1 photon.

    Args:
        rng: random generator.
        log_image: (rows, cols) log image at the data set's stored pixels (not resampled).
        photons_per_pixel: N0, flat-field photons per stored pixel of the data set.
        dose_fraction: f in (0, 1].
    """
    if not 0.0 < dose_fraction <= 1.0:
        raise ValueError(f"dose_fraction must be in (0, 1], got {dose_fraction}")
    img = np.asarray(log_image, dtype=np.float32)
    if dose_fraction == 1.0:
        return img
    var = np.exp(np.clip(img, None, 30.0)) * (1.0 / dose_fraction - 1.0) / photons_per_pixel
    std = np.minimum(np.sqrt(var), 1.0)
    return (img + std * rng.standard_normal(img.shape)).astype(np.float32)
