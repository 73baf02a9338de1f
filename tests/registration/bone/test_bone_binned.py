"""A bone view binned to a working resolution with its unused pixels filled there
(``BoneView.binned``): hand-computed means and a harmonic fill that reproduces a ramp."""

from __future__ import annotations

import numpy as np

from fluoronav.geometry.camera import Camera, DetectorSpec
from fluoronav.registration.bone import BoneView

SPEC = DetectorSpec(rows=24, cols=24, pixel_spacing_mm=1.0, sdd_mm=1000.0)


def test_without_a_mask_it_is_the_block_mean() -> None:
    img = np.arange(24 * 24, dtype=np.float64).reshape(24, 24)
    out, use = BoneView(img, Camera.from_detector(SPEC)).binned(3)
    assert use is None and out.shape == (8, 8)
    np.testing.assert_allclose(out[0, 0], img[:3, :3].mean())
    np.testing.assert_allclose(out[5, 2], img[15:18, 6:9].mean())


def test_used_pixels_average_their_used_pixels_and_the_rest_is_filled_harmonically() -> None:
    rows, cols = np.mgrid[:24, :24]
    ramp = 2.0 * cols + 0.5 * rows  # harmonic: the fill reproduces it exactly
    img = ramp.copy()
    mask = np.ones((24, 24), bool)
    mask[9:15, 9:15] = False  # a 6×6 instrument: two whole 3×3 blocks per side
    img[~mask] = 100.0  # metal
    mask[3, 3] = False  # one unused pixel in an otherwise used block
    img[3, 3] = 100.0
    view = BoneView(img, Camera.from_detector(SPEC), mask)
    out, use = view.binned(3)
    assert use is not None and use.shape == (8, 8)
    assert not use[3:5, 3:5].any() and use.sum() == 64 - 4
    block = [(r, c) for r in range(3, 6) for c in range(3, 6) if (r, c) != (3, 3)]
    np.testing.assert_allclose(out[1, 1], np.mean([ramp[r, c] for r, c in block]))  # metal not mixed in
    # the binned ramp is a ramp too; the filled blocks continue it
    binned_ramp = ramp.reshape(8, 3, 8, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(out[3:5, 3:5], binned_ramp[3:5, 3:5], atol=1e-9)
    assert view.binned(3) is view.binned(3)  # computed once


def test_another_camera_shares_what_was_binned() -> None:
    img = np.ones((24, 24))
    view = BoneView(img, Camera.from_detector(SPEC), np.ones((24, 24), bool))
    first = view.binned(2)
    moved = view.with_camera(Camera.from_detector(SPEC, np.diag([1.0, 1.0, 1.0, 1.0])))
    assert moved.binned(2) is first
