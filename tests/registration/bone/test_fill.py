"""Harmonic fill of masked pixels."""

from __future__ import annotations

import numpy as np
import pytest

from fluoronav.registration.bone.fill import harmonic_fill


def test_linear_ramp_is_reproduced_inside_and_known_pixels_kept():
    v, u = np.mgrid[0:60, 0:80].astype(float)
    ramp = 2.0 + 0.3 * u - 0.7 * v
    fill = np.zeros(ramp.shape, bool)
    fill[20:35, 10:70] = True
    fill[5:50, 40:48] = True
    garbage = np.where(fill, 1e3, ramp)
    out = harmonic_fill(garbage, fill)
    np.testing.assert_allclose(out, ramp, atol=1e-8)
    assert out.dtype == np.float64


def test_filled_values_depend_on_the_known_pixels_only():
    rng = np.random.default_rng(0)
    img = rng.random((40, 50))
    fill = np.zeros(img.shape, bool)
    fill[10:20, :30] = True  # touches the border: Neumann there
    a = harmonic_fill(np.where(fill, 5.0, img), fill)
    b = harmonic_fill(np.where(fill, -3.0, img), fill)
    np.testing.assert_array_equal(a, b)
    assert a[fill].min() >= img.min() and a[fill].max() <= img.max()  # maximum principle


def test_nothing_or_everything_to_fill_and_bad_shapes():
    img = np.arange(12.0).reshape(3, 4)
    np.testing.assert_array_equal(harmonic_fill(img, np.zeros((3, 4), bool)), img)
    np.testing.assert_array_equal(harmonic_fill(img, np.ones((3, 4), bool)), img)
    with pytest.raises(ValueError, match="shape"):
        harmonic_fill(img, np.zeros((4, 3), bool))
