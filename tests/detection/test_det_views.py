"""View resampling follows the pixel-centre convention u' = (u − x0 + 0.5)/s − 0.5."""

from __future__ import annotations

import numpy as np
import pytest

from fluoronav.detection.views import View, full_view, normalize_intensity, paste, resample, roi_view


def test_to_input_from_input_roundtrip() -> None:
    v = View(x0=-7, y0=12, side=90, size=64)
    uv = np.random.default_rng(0).uniform(-5, 70, size=(10, 2))
    np.testing.assert_allclose(v.to_input(v.from_input(uv)), uv, atol=1e-12)
    # the view's outer pixel edges are the window's edges
    np.testing.assert_allclose(v.to_input(np.array([-0.5, -0.5])), [-7.5, 11.5])
    np.testing.assert_allclose(v.to_input(np.array([63.5, 63.5])), [-7.5 + 90, 11.5 + 90])


@pytest.mark.parametrize(("side", "size"), [(300, 64), (40, 64), (64, 64)])
def test_resample_of_a_linear_ramp_matches_the_mapping(side: int, size: int) -> None:
    # area averages and bilinear samples of a linear function equal its value at the sample centre
    rows, cols = 360, 400
    vv, uu = np.mgrid[0:rows, 0:cols].astype(np.float64)
    ramp = (0.3 * uu + 0.7 * vv).astype(np.float32)
    view = View(x0=20, y0=33, side=side, size=size)
    out = resample(ramp, view)
    gv, gu = np.mgrid[0:size, 0:size].astype(np.float64)
    centres = view.to_input(np.stack([gu, gv], axis=-1))
    expected = 0.3 * centres[..., 0] + 0.7 * centres[..., 1]
    # away from the last row/column where bilinear enlargement clamps at the window edge
    np.testing.assert_allclose(out[1:-1, 1:-1], expected[1:-1, 1:-1], atol=1e-2 * max(side / size, 1))


def test_full_view_widened_to_a_min_side_centres_the_image_and_repeats_its_edges() -> None:
    img = np.zeros((100, 200), np.float32)
    img[:, :10] = 1.0  # a bright left edge, repeated to the left of the image
    view = full_view(img.shape, 100, min_side_px=400.0)
    assert (view.x0, view.y0, view.side) == (-100, -150, 400) and view.scale == 4.0
    out = resample(img, view)
    # the image's centre is the view's centre; its top-left pixel centre maps back exactly
    np.testing.assert_allclose(view.to_input(np.array([49.5, 49.5])), [99.5, 49.5])
    # (0 + 100 + 0.5) / 4 − 0.5 and (0 + 150 + 0.5) / 4 − 0.5
    np.testing.assert_allclose(view.from_input(np.array([0.0, 0.0])), [24.625, 37.125])
    assert out[50, :25].min() > 0.99  # repeated bright edge (rows inside the image)
    assert out[50, 28:74].max() == 0.0 and out[5, 60] == 0.0  # the dark middle, above it repeated too
    # a min side at or below the longer side changes nothing
    assert full_view(img.shape, 100, min_side_px=200.0) == full_view(img.shape, 100)
    assert full_view(img.shape, 100, min_side_px=200.4) == full_view(img.shape, 100)  # rounds to 200


def test_full_view_pads_non_square_images_at_the_bottom_right() -> None:
    img = np.zeros((100, 200), np.float32)
    img[40:60, 90:110] = 1.0
    view = full_view(img.shape, 50)
    assert view.scale == 4.0 and (view.x0, view.y0) == (0, 0)
    out = resample(img, view)
    assert out.shape == (50, 50)
    vv, uu = np.nonzero(out > 0.5)
    np.testing.assert_allclose(view.to_input(np.array([uu.mean(), vv.mean()])), [99.5, 49.5], atol=0.01)


def test_paste_inverts_resample_of_a_window() -> None:
    img = np.zeros((120, 130), np.float32)
    img[30:70, 40:90] = 1.0
    view = roi_view(np.array([[40.0, 30.0], [89.0, 69.0]]), 32, margin_frac=0.25)
    back = paste(resample(img, view), view, img.shape)
    assert np.mean(np.abs((back > 0.5) - img)) < 0.02
    inside = roi_view(np.array([[0.0, 0.0]]), 16, margin_frac=0.0, min_side_px=10.0)
    assert inside.side == 10


def test_paste_into_a_box_is_that_part_of_the_full_grid() -> None:
    vals = np.random.default_rng(2).normal(size=(16, 16)).astype(np.float32)
    view = View(x0=-6, y0=20, side=40, size=16)  # partly left of the image
    full = paste(vals, view, (70, 80), fill=-3.0)
    for box in ((0, 0, 80, 70), (5, 18, 50, 66), (40, 0, 80, 10)):  # overlapping, inside, disjoint
        x0, y0, x1, y1 = box
        np.testing.assert_array_equal(paste(vals, view, (70, 80), fill=-3.0, box=box), full[y0:y1, x0:x1])


def test_window_partly_outside_repeats_the_edge_and_normalisation_is_robust() -> None:
    img = np.arange(100, dtype=np.float32).reshape(10, 10)
    out = resample(img, View(-5, -5, 10, 10))
    assert out[0, 0] == img[0, 0] and out[-1, -1] == img[4, 4]
    x = np.random.default_rng(1).normal(5.0, 2.0, (64, 64)).astype(np.float32)
    x[0, 0] = 1e6  # one hot pixel does not set the scale
    n = normalize_intensity(x)
    assert np.percentile(n, 1) == pytest.approx(0.0, abs=1e-6)
    assert np.percentile(n, 99) == pytest.approx(1.0, abs=1e-6)
    assert not normalize_intensity(np.ones((8, 8))).any()
