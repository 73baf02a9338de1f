"""Instrument mask: the CM segmentation and its shaft band behind landmark A, with a margin."""

from __future__ import annotations

import numpy as np
import pytest

from fluoronav.detection.instrument import instrument_mask


def _tube(shape, a, b, half_width):
    """Bool mask of the segment a→b (u, v) thickened to ``half_width`` px, and its centreline."""
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    d = (b - a) / np.linalg.norm(b - a)
    t = (u - a[0]) * d[0] + (v - a[1]) * d[1]
    across = np.abs(-(u - a[0]) * d[1] + (v - a[1]) * d[0])
    length = np.linalg.norm(b - a)
    mask = (t >= 0) & (t <= length) & (across <= half_width)
    cl = a[None] + np.linspace(0.0, 1.0, 30)[:, None] * (b - a)[None]
    return mask, cl


def test_shaft_band_runs_from_a_to_the_border_and_nowhere_else():
    a, b = np.array([100.0, 120.0]), np.array([150.0, 70.0])  # B up-right of A; the shaft goes down-left
    cm, cl = _tube((200, 220), a, b, half_width=4.0)
    out = instrument_mask(cm, cl, margin_px=3.0)
    assert out.shape == cm.shape and out.dtype == bool
    assert out[cm].all()
    d = (a - b) / np.linalg.norm(a - b)
    # on the shaft's axis up to the border, and inside its half width (4 px tube + 3 px margin)
    for s in (10.0, 50.0, 95.0):
        u, v = a + s * d
        assert out[round(v), round(u)], s
        n = np.array([-d[1], d[0]])
        u2, v2 = a + s * d + 6.5 * n
        assert out[round(v2), round(u2)], s
        u3, v3 = a + s * d + 9.0 * n
        assert not out[round(v3), round(u3)], s
    # beyond B only the solid tip: 1.5 tube widths (~15 px here), then nothing
    e = (b - a) / np.linalg.norm(b - a)
    u, v = b + 10.0 * e
    assert out[round(v), round(u)]
    u, v = b + 22.0 * e
    assert not out[round(v), round(u)]
    assert out[round(b[1] - 2 * d[1]), round(b[0] - 2 * d[0])]
    assert out.sum() < 0.2 * out.size


def test_without_shaft_is_the_dilated_segmentation():
    a, b = np.array([60.0, 60.0]), np.array([100.0, 60.0])
    cm, cl = _tube((120, 160), a, b, half_width=3.0)
    out = instrument_mask(cm, cl, margin_px=2.0, shaft=False)
    assert out[60, 40] == False  # noqa: E712 (numpy bool)
    assert out[60, 58] and out[65, 80] and not out[67, 80]


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="empty"):
        instrument_mask(np.zeros((10, 10), bool), np.array([[1.0, 1.0], [5.0, 5.0]]))
    cm = np.zeros((10, 10), bool)
    cm[4:6, 2:8] = True
    with pytest.raises(ValueError, match="centerline_px"):
        instrument_mask(cm, np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="no length"):
        instrument_mask(cm, np.array([[3.0, 5.0], [3.0, 5.0], [7.0, 5.0]]))


def test_from_landmarks_extracts_the_centreline_and_fails_softly():
    from fluoronav.detection.instrument import instrument_mask_from_landmarks, instrument_masks

    a, b = np.array([40.0, 90.0]), np.array([120.0, 50.0])
    cm, cl = _tube((140, 160), a, b, half_width=4.0)
    out = instrument_mask_from_landmarks(cm, np.stack([a, b]), margin_px=3.0)
    assert out is not None
    ref = instrument_mask(cm, cl, margin_px=3.0)
    assert (out != ref).mean() < 0.01  # the same shaft direction from the extracted centreline
    assert instrument_mask_from_landmarks(np.zeros_like(cm), np.stack([a, b])) is None
    both = instrument_masks([cm, None, np.zeros_like(cm)], [cl, cl, cl], margin_px=3.0)
    assert both[1] is None and both[2] is None
    np.testing.assert_array_equal(both[0], ref)


def test_shaft_direction_is_refined_on_the_image():
    """The centreline's base points 8° off the real shaft: far from A only the image finds it."""
    from fluoronav.detection.instrument import shaft_direction

    shape = (300, 400)
    a = np.array([300.0, 150.0])
    b = np.array([360.0, 150.0])  # the base direction behind A is (−1, 0)
    cm, cl = _tube(shape, a, b, half_width=4.0)
    ang = np.radians(180.0 + 8.0)
    d_true = np.array([np.cos(ang), np.sin(ang)])
    shaft_img, _ = _tube(shape, a + 280.0 * d_true, a, half_width=4.0)
    rng = np.random.default_rng(0)
    image = 0.5 + 2.0 * (shaft_img | cm) + rng.normal(0.0, 0.2, shape)
    d = shaft_direction(image, a, np.array([-1.0, 0.0]), 10.0)
    assert np.degrees(np.arccos(np.clip(d @ d_true, -1, 1))) < 1.0  # a tube, not a line: a plateau
    far = a + 250.0 * d_true
    with_image = instrument_mask(cm, cl, image=image, margin_px=3.0)
    without = instrument_mask(cm, cl, margin_px=3.0)
    assert with_image[round(far[1]), round(far[0])]
    assert not without[round(far[1]), round(far[0])]
