"""Image evidence of a detection: the gradient ratio on a mask's boundary."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest
from scipy import ndimage as ndi

from fluoronav.detection.evidence import mask_edge_ratio

SPACING_MM = 0.582


def tube_scene(
    *, contrast: float = 1.0, noise: float = 0.05, blur_px: float = 0.0, scale: int = 1, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """A 24-px-wide bar (a tube at 0.582 mm per pixel) over a smooth ramp with white noise, and its
    mask; ``scale`` draws the same scene with ``scale``² pixels per pixel."""
    rng = np.random.default_rng(seed)
    n = 200 * scale
    yy, xx = np.mgrid[0:n, 0:n] / scale
    mask = np.zeros((n, n), np.uint8)
    cv2.line(mask, (40 * scale, 60 * scale), (160 * scale, 140 * scale), 1, thickness=24 * scale)
    bar = mask.astype(np.float64)
    if blur_px > 0.0:
        bar = ndi.gaussian_filter(bar, blur_px * scale)
    img = 0.004 * xx + 0.002 * yy + contrast * bar + noise * rng.standard_normal((n, n))
    return img, mask.astype(bool)


def test_a_tube_boundary_is_an_edge_and_a_random_one_is_not() -> None:
    img, mask = tube_scene()
    sharp = mask_edge_ratio(img, mask, pixel_spacing_mm=SPACING_MM)
    assert sharp > 8.0
    # a blob of the same size drawn elsewhere, on ramp and noise only: about 1
    blob = np.zeros_like(mask)
    blob[150:190, 20:60] = True
    assert 0.7 < mask_edge_ratio(img, blob, pixel_spacing_mm=SPACING_MM) < 1.5
    # the same bar, blurred over 6 px (a bone's soft rim, not a metal tube): no edge on its boundary
    soft, _ = tube_scene(blur_px=6.0)
    assert mask_edge_ratio(soft, mask, pixel_spacing_mm=SPACING_MM) < 3.0


def test_ratio_ignores_the_intensity_scale_and_offset() -> None:
    img, mask = tube_scene(seed=3)
    ref = mask_edge_ratio(img, mask, pixel_spacing_mm=SPACING_MM)
    scaled = mask_edge_ratio(7.5 * img - 40.0, mask, pixel_spacing_mm=SPACING_MM)
    assert scaled == pytest.approx(ref, rel=1e-9)


def test_ratio_is_about_the_same_at_three_times_the_resolution() -> None:
    # the same scene on a 3× finer grid (smoothing and ring in mm): the noise is made 3× stronger per
    # pixel so that its power per mm² is the same as on the coarse grid
    coarse_img, coarse_mask = tube_scene(noise=0.2, seed=1)
    fine_img, fine_mask = tube_scene(noise=0.6, scale=3, seed=2)
    coarse = mask_edge_ratio(coarse_img, coarse_mask, pixel_spacing_mm=SPACING_MM)
    fine = mask_edge_ratio(fine_img, fine_mask, pixel_spacing_mm=SPACING_MM / 3)
    assert fine == pytest.approx(coarse, rel=0.3)


def test_weak_contrast_in_heavy_noise_lowers_the_ratio_monotonically() -> None:
    ratios = [
        mask_edge_ratio(*tube_scene(contrast=c, noise=0.3, seed=5), pixel_spacing_mm=SPACING_MM)
        for c in (2.0, 1.0, 0.5, 0.0)
    ]
    assert all(a > b for a, b in itertools.pairwise(ratios))
    assert ratios[-1] < 1.5  # no tube at all: the texture's own level


def test_degenerate_masks_and_bad_input() -> None:
    img, mask = tube_scene()
    assert mask_edge_ratio(img, np.zeros_like(mask), pixel_spacing_mm=SPACING_MM) == 0.0
    assert mask_edge_ratio(img, np.ones_like(mask), pixel_spacing_mm=SPACING_MM) == float("inf")
    flat = np.zeros_like(img)
    assert mask_edge_ratio(flat, mask, pixel_spacing_mm=SPACING_MM) == float("inf")
    with pytest.raises(ValueError, match="one shape"):
        mask_edge_ratio(img, mask[:-1], pixel_spacing_mm=SPACING_MM)
    with pytest.raises(ValueError, match="pixel_spacing_mm"):
        mask_edge_ratio(img, mask, pixel_spacing_mm=0.0)
