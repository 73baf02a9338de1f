"""Image evidence of a detection: the gradient ratio on a mask's boundary, and whether a tube goes on
beyond a mask's end."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest
from scipy import ndimage as ndi

from fluoronav.detection.evidence import end_continuation, local_tube_width_px, mask_edge_ratio

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


def stub_scene(
    *, shaft_deg: float | None = 0.0, noise: float = 0.05, scale: int = 1, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 20-px-wide CM tube from (100, 100) to (200, 100) over a ramp with noise, its mask, and its
    end at A (100, 100) (u, v). ``shaft_deg``: the shaft goes on from A for 60 px at that angle from
    the CM's axis (0: straight on, 90: a sharp bend); None: no shaft, A is a free end. ``scale``
    draws the scene with ``scale``² pixels per pixel."""
    rng = np.random.default_rng(seed)
    n = 260 * scale
    yy, xx = np.mgrid[0:n, 0:n] / scale
    s = scale
    cm = np.zeros((n, n), np.uint8)
    cv2.line(cm, (100 * s, 100 * s), (200 * s, 100 * s), 1, thickness=20 * s)
    tube = cm.copy()
    if shaft_deg is not None:
        a = np.deg2rad(180.0 + shaft_deg)
        end = (round((100 + 60 * np.cos(a)) * s), round((100 + 60 * np.sin(a)) * s))
        cv2.line(tube, (100 * s, 100 * s), end, 1, thickness=20 * s)
    img = 0.003 * xx + 0.002 * yy + tube + noise * rng.standard_normal((n, n))
    mask = cm.astype(bool)
    mask[:, : 100 * s] = False  # the label mask stops at A's plane
    return img, mask, np.array([100.0, 100.0]) * s


@pytest.mark.parametrize("shaft_deg", [0.0, 45.0, 90.0])
def test_a_shaft_beyond_the_mask_end_is_a_continuation_whatever_its_angle(shaft_deg: float) -> None:
    img, mask, a = stub_scene(shaft_deg=shaft_deg)
    assert local_tube_width_px(mask, a) == pytest.approx(20.0, abs=2.0)
    assert end_continuation(img, mask, a) > 0.8


def test_a_free_end_has_no_continuation_and_one_bright_pixel_does_not_make_one() -> None:
    img, mask, a = stub_scene(shaft_deg=None)
    assert end_continuation(img, mask, a) < 0.2
    # a speck as bright as the tube on the circle around the end: the running median ignores it
    img[100, 74] = img[100, 75] = 1.0
    assert end_continuation(img, mask, a) < 0.2


def test_the_far_end_of_a_mask_covering_a_stub_is_free_and_the_junction_is_not() -> None:
    # the fine stage's mistake: the mask covers the CM and a shaft stub, A at the stub's far end
    img, _, a = stub_scene(shaft_deg=0.0)
    both = np.zeros(img.shape, np.uint8)
    cv2.line(both, (40, 100), (200, 100), 1, thickness=20)
    both_mask = both.astype(bool)
    both_mask[:, :40] = False
    assert end_continuation(img, both_mask, np.array([40.0, 100.0])) < 0.2
    cut = both_mask.copy()
    cut[:, :100] = False
    assert end_continuation(img, cut, a) > 0.8


def test_continuation_ignores_intensity_scale_and_resolution() -> None:
    img, mask, a = stub_scene(shaft_deg=30.0, seed=4)
    ref = end_continuation(img, mask, a)
    assert end_continuation(5.0 * img + 12.0, mask, a) == pytest.approx(ref, rel=1e-9)
    fine_img, fine_mask, fine_a = stub_scene(shaft_deg=30.0, scale=3, seed=4)
    assert end_continuation(fine_img, fine_mask, fine_a + 1.0) == pytest.approx(ref, abs=0.2)
    # with the pixel size given, the fine image is binned to the coarse one's first: the same value
    binned = end_continuation(fine_img, fine_mask, fine_a + 1.0, pixel_spacing_mm=SPACING_MM / 3)
    assert binned == pytest.approx(ref, abs=0.2)
    free_img, free_mask, free_a = stub_scene(shaft_deg=None, scale=3, seed=4)
    assert end_continuation(free_img, free_mask, free_a + 1.0, pixel_spacing_mm=SPACING_MM / 3) < 0.2
    with pytest.raises(ValueError, match="pixel_spacing_mm"):
        end_continuation(img, mask, a, pixel_spacing_mm=0.0)


def test_continuation_is_undefined_where_it_cannot_be_measured() -> None:
    img, mask, a = stub_scene()
    assert end_continuation(img, np.zeros_like(mask), a) is None
    assert local_tube_width_px(np.zeros_like(mask), a) is None
    assert end_continuation(np.zeros_like(img), mask, a) is None  # no tube brighter than its background
    thin = np.zeros_like(mask)
    thin[100, 100:200] = True
    assert end_continuation(img, thin, a) is None  # a one-pixel line is no tube
    with pytest.raises(ValueError, match="one shape"):
        end_continuation(img, mask[:-1], a)
