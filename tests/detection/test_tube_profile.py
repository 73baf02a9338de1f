"""Tube profile fit: scale (depth cue) and veil response recovered from synthetic tube images."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from fluoronav.detection.tube_profile import annulus_chord, fit_tube_profile, shaft_axis_px

R_MM, RI_MM = 3.0, 2.0


def _tube_image(
    *, px_per_mm: float, veil: float, mu: float, blur_mm: float, noise: float, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """A straight tube at 30° through (120, 100) on a sloped background, and points on its axis.
    Rendered on a 4× finer grid and area-binned (a detector integrates over its pixels)."""
    f = 4
    n = 240 * f
    yy, xx = np.mgrid[0:n, 0:n]
    u, v = (xx + 0.5) / f - 0.5, (yy + 0.5) / f - 0.5
    c, d = np.array([120.0, 100.0]), np.array([np.cos(np.pi / 6), np.sin(np.pi / 6)])
    dist_mm = ((u - c[0]) * -d[1] + (v - c[1]) * d[0]) / px_per_mm
    chord = annulus_chord(dist_mm, R_MM, RI_MM)
    y = -np.log((1.0 - veil) * np.exp(-mu * chord) + veil)
    y = ndimage.gaussian_filter(y, blur_mm * px_per_mm * f)
    y = y.reshape(240, f, 240, f).mean(axis=(1, 3))
    y += 1.0 + 0.002 * np.arange(240)[None, :]
    y += np.random.default_rng(seed).normal(0.0, noise, y.shape)
    axis = c[None] + np.linspace(-60.0, 60.0, 30)[:, None] * d[None]
    return y, axis


@pytest.mark.parametrize("veil", [0.0, 0.15])
def test_fit_recovers_scale_and_veil(veil: float) -> None:
    img, axis = _tube_image(px_per_mm=5.5, veil=veil, mu=0.9, blur_mm=0.1, noise=0.01)
    fit = fit_tube_profile(img, axis, outer_radius_mm=R_MM, inner_radius_mm=RI_MM, px_per_mm_range=(3.0, 9.0))
    assert fit is not None
    assert fit.px_per_mm == pytest.approx(5.5, rel=0.01)
    assert fit.veil == pytest.approx(veil, abs=0.02)
    assert fit.mu_per_mm == pytest.approx(0.9, rel=0.05)
    assert fit.depth_mm(1000.0) == pytest.approx(1000.0 / fit.px_per_mm)


def test_fit_at_a_known_scale_recovers_the_veil_from_an_offset_axis() -> None:
    img, axis = _tube_image(px_per_mm=5.5, veil=0.15, mu=0.9, blur_mm=0.1, noise=0.01, seed=1)
    # an axis 2 px off the tube and slightly rotated: profiles are re-centred before the median
    off = axis + np.array([0.0, 2.0]) + np.linspace(-1.0, 1.0, len(axis))[:, None] * np.array([0.0, 1.0])
    fit = fit_tube_profile(img, off, outer_radius_mm=R_MM, inner_radius_mm=RI_MM, px_per_mm=5.5)
    assert fit is not None
    assert fit.px_per_mm == pytest.approx(5.5)
    assert fit.veil == pytest.approx(0.15, abs=0.02)


def test_no_tube_gives_no_fit() -> None:
    img = 1.0 + np.random.default_rng(2).normal(0.0, 0.01, (240, 240))
    axis = np.array([[60.0, 60.0], [180.0, 180.0]])
    assert (
        fit_tube_profile(img, axis, outer_radius_mm=R_MM, inner_radius_mm=RI_MM, px_per_mm_range=(3.0, 9.0))
        is None
    )


def test_fit_needs_exactly_one_scale_argument() -> None:
    img, axis = _tube_image(px_per_mm=5.5, veil=0.0, mu=0.9, blur_mm=0.1, noise=0.0)
    with pytest.raises(ValueError, match="exactly one"):
        fit_tube_profile(img, axis, outer_radius_mm=R_MM, inner_radius_mm=RI_MM)


def test_shaft_axis_continues_the_centreline_behind_its_start() -> None:
    cl = np.stack([np.linspace(100.0, 200.0, 51), np.full(51, 50.0)], axis=1)  # A at u = 100, B at 200
    pts = shaft_axis_px(cl, start_fraction=0.1, stop_fraction=0.9, n_points=9)
    np.testing.assert_allclose(pts[:, 1], 50.0)
    np.testing.assert_allclose(pts[:, 0], np.linspace(90.0, 10.0, 9))
