"""Cross-section profile of a tube (the CM's shaft) in an X-ray image: its scale and the image's response.

Across a tube of outer radius ``R`` and inner radius ``Rᵢ`` (mm) the line integral is ``μ·c(x)`` with the
annulus chord ``c(x) = 2·(√(R² − x²)₊ − √(Rᵢ² − x²)₊)`` (x: distance from the axis, mm at the tube). The
fitted image model, blurred by a Gaussian on a quadratic background ``b``, is ``y(x) = b(x) − ln((1 −
f)·exp(−μ·c(x)) + f)``: the veil ``f`` (the fraction of the flat field that passes unattenuated) captures
scatter, glare and beam hardening (docs/registration.md, "The image's response to the CM"). Fitted to the
median of profiles normal to the tube's projected axis (re-centred on the model and refitted), it gives the
tube's scale (``px_per_mm`` at the tube; its depth is ``focal_px / px_per_mm``) when it is not given, and the
response ``(μ, f)`` the CM registration applies to its DRR. The shaft is used, not the notched CM: notches cut
one side of the tube at a time and change the profile's shape with the viewing angle.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import ndimage

from fluoronav.detection.centerline import end_direction, resample_polyline

if TYPE_CHECKING:
    from scipy import optimize

__all__ = ["TubeProfileFit", "annulus_chord", "fit_tube_profile", "shaft_axis_px"]

logger = logging.getLogger(__name__)

_FINE_MM = 0.01  # model sampling step across the tube, mm


@dataclass(frozen=True)
class TubeProfileFit:
    """Result of :func:`fit_tube_profile`.

    Attributes:
        px_per_mm: scale of the tube's projection, image pixels per mm at the tube.
        mu_per_mm: fitted attenuation per mm of chord, image units.
        veil: fitted unattenuated fraction ``f`` in [0, 1).
        blur_mm: fitted Gaussian blur σ, mm at the tube.
        rms_residual: RMS of the fit's residual over the median profile, image units.
        n_profiles: number of profiles whose median was fitted.
    """

    px_per_mm: float
    mu_per_mm: float
    veil: float
    blur_mm: float
    rms_residual: float
    n_profiles: int

    def depth_mm(self, focal_px: float) -> float:
        """Distance of the tube from the source (camera-frame z) for a camera of focal length
        ``focal_px`` (pixels of the same image)."""
        return float(focal_px / self.px_per_mm)


def annulus_chord(x: np.ndarray, outer_radius: float, inner_radius: float) -> np.ndarray:
    """Chord length of an annulus along lines at signed distance ``x`` from its centre (same units)."""
    x2 = np.square(x)
    return 2.0 * (
        np.sqrt(np.clip(outer_radius**2 - x2, 0.0, None)) - np.sqrt(np.clip(inner_radius**2 - x2, 0.0, None))
    )


def shaft_axis_px(
    centerline_px: np.ndarray,
    *,
    start_fraction: float = 0.1,
    stop_fraction: float = 0.9,
    n_points: int = 40,
    direction_fraction: float = 0.125,
) -> np.ndarray:
    """Points on the straight continuation of a centreline beyond its first point (landmark A), where
    the CM's shaft lies: from ``start_fraction`` to ``stop_fraction`` of the centreline's length behind
    A, along the direction of its first ``direction_fraction`` (the straight base). (n_points, 2)."""
    cl = np.asarray(centerline_px, dtype=np.float64)
    if cl.ndim != 2 or cl.shape[1] != 2 or cl.shape[0] < 2:
        raise ValueError(f"centerline_px must have shape (P >= 2, 2), got {cl.shape}")
    length = float(np.linalg.norm(np.diff(cl, axis=0), axis=1).sum())
    if length <= 0.0:
        raise ValueError("the centreline has no length")
    d = end_direction(cl, direction_fraction, at_start=True)
    t = np.linspace(start_fraction * length, stop_fraction * length, n_points)
    return cl[0][None] + t[:, None] * d[None]


def _model(p: np.ndarray, x_px: np.ndarray, fine: np.ndarray, R: float, Ri: float) -> np.ndarray:
    """Profile model at ``x_px``; p = (px_per_mm, μ, f, blur_mm, x0_mm, c0, c1, c2), background per mm."""
    s, mu, f, blur, x0, c0, c1, c2 = p
    y = -np.log((1.0 - f) * np.exp(-mu * annulus_chord(fine - x0, R, Ri)) + f)
    y = ndimage.gaussian_filter1d(y, max(blur, 1e-3) / _FINE_MM, mode="nearest")
    xm = x_px / s
    return np.interp(xm, fine, y) + c0 + c1 * xm + c2 * xm * xm


def _fit(
    y: np.ndarray,
    x_px: np.ndarray,
    R: float,
    Ri: float,
    scale_range: tuple[float, float],
    fixed_scale: bool,
    start: np.ndarray | None,
) -> optimize.OptimizeResult | None:
    s_lo, s_hi = scale_range
    fine = np.arange(x_px[0] / s_lo - 2.0 * R, x_px[-1] / s_lo + 2.0 * R, _FINE_MM)
    if start is None:
        # coarse search over the scale with a linear response (μ and background solved exactly)
        best: tuple[float, np.ndarray] | None = None
        scales = [s_lo] if fixed_scale else np.geomspace(s_lo, s_hi, 24)
        for s in scales:
            unit = _model(np.array([s, 1e-3, 0.0, 0.05, 0.0, 0.0, 0.0, 0.0]), x_px, fine, R, Ri) / 1e-3
            xm = x_px / s
            A = np.stack([unit, np.ones_like(xm), xm, xm * xm], axis=1)
            coef, *_ = np.linalg.lstsq(A, y, rcond=None)
            if coef[0] <= 0:
                continue
            err = float(np.sum((A @ coef - y) ** 2))
            if best is None or err < best[0]:
                best = (err, np.array([s, coef[0], 0.1, 0.1, 0.0, coef[1], coef[2], coef[3]]))
        if best is None:
            return None
        start = best[1]
    lo = np.array([s_lo, 0.0, 0.0, 0.01, -R, -np.inf, -np.inf, -np.inf])
    hi = np.array([s_hi, 20.0, 0.95, R / 2.0, R, np.inf, np.inf, np.inf])
    if fixed_scale:
        hi[0] = s_lo * (1.0 + 1e-9)
    p0 = np.clip(np.asarray(start, dtype=np.float64), lo + 1e-12, hi - 1e-12)
    from scipy.optimize import least_squares  # here: a slow import, not needed at start-up

    try:
        return least_squares(lambda p: _model(p, x_px, fine, R, Ri) - y, p0, bounds=(lo, hi), x_scale="jac")
    except (ValueError, np.linalg.LinAlgError) as exc:  # pragma: no cover - defensive
        logger.debug("tube profile fit failed: %s", exc)
        return None


def fit_tube_profile(
    image: np.ndarray,
    axis_px: np.ndarray,
    *,
    outer_radius_mm: float,
    inner_radius_mm: float,
    px_per_mm: float | None = None,
    px_per_mm_range: tuple[float, float] | None = None,
    n_profiles: int = 48,
    trim_fraction: float = 0.0,
    step_px: float = 0.25,
    align_iterations: int = 2,
) -> TubeProfileFit | None:
    """Fit the tube profile model (module docstring) along a projected tube axis.

    Args:
        image: (H, W) −log image (the tube bright).
        axis_px: (P, 2) points (u, v) along the tube's projected axis, in order, P ≥ 2.
        outer_radius_mm, inner_radius_mm: the tube's radii.
        px_per_mm: the tube's known scale (pixels per mm at the tube): only the response is fitted.
        px_per_mm_range: (min, max) plausible scale when it is fitted (exactly one of the two).
        n_profiles: profiles sampled along the axis (evenly by arc length).
        trim_fraction: fraction of the axis left out at each end.
        step_px: sampling step along each profile, pixels.
        align_iterations: rounds of re-centring each profile on the fitted model before refitting.

    Returns:
        :class:`TubeProfileFit`, or None when too few profiles lie in the image or the fit is
        implausible (scale on a bound of the range, no contrast, a residual half the contrast or a
        contrast under three times the single profiles' spread about their median):
        callers then go without it.
    """
    if (px_per_mm is None) == (px_per_mm_range is None):
        raise ValueError("give exactly one of px_per_mm and px_per_mm_range")
    img = np.asarray(image, dtype=np.float64)
    ax = np.asarray(axis_px, dtype=np.float64)
    if img.ndim != 2 or ax.ndim != 2 or ax.shape[1] != 2 or ax.shape[0] < 2:
        raise ValueError(f"need a 2D image and a (P >= 2, 2) axis, got {img.shape} and {ax.shape}")
    fixed = px_per_mm is not None
    if px_per_mm is not None:
        s_lo = s_hi = float(px_per_mm)
    else:
        assert px_per_mm_range is not None
        s_lo, s_hi = float(px_per_mm_range[0]), float(px_per_mm_range[1])
    if not 0.0 < s_lo <= s_hi:
        raise ValueError(f"the scale must be positive, got {s_lo}..{s_hi}")
    R, Ri = float(outer_radius_mm), float(inner_radius_mm)

    sampled = _sample_profiles(img, ax, n_profiles, trim_fraction, 2.5 * R * s_hi, step_px)
    if sampled is None:
        return None
    prof, x, n_kept = sampled
    aligned = _aligned_fit(prof, x, R, Ri, (s_lo, s_hi), fixed, step_px, align_iterations)
    if aligned is None:
        return None
    fit, prof = aligned
    s, mu, f, blur = (float(v) for v in fit.x[:4])
    rms = float(np.sqrt(np.mean(fit.fun**2)))
    peak = float(-np.log((1.0 - f) * np.exp(-mu * annulus_chord(np.array([Ri]), R, Ri)[0]) + f))
    on_bound = not fixed and (s <= s_lo * 1.001 or s >= s_hi * 0.999)
    # spread of the single profiles about their median (robust): a tube stands out of it, noise
    # re-centred on a fitted template does not
    spread = 1.4826 * float(np.median(np.abs(prof - np.median(prof, axis=0, keepdims=True))))
    if on_bound or mu <= 0.0 or rms >= 0.5 * peak or peak < 3.0 * spread:
        logger.debug(
            "tube profile rejected: scale %.3g in [%.3g, %.3g], peak %.3g, rms %.3g, spread %.3g",
            s, s_lo, s_hi, peak, rms, spread,
        )  # fmt: skip
        return None
    return TubeProfileFit(
        px_per_mm=s, mu_per_mm=mu, veil=f, blur_mm=blur, rms_residual=rms, n_profiles=n_kept
    )


def _sample_profiles(
    img: np.ndarray, ax: np.ndarray, n_profiles: int, trim_fraction: float, half_px: float, step_px: float
) -> tuple[np.ndarray, np.ndarray, int] | None:
    """Profiles normal to the axis, ``half_px`` either side of it: ``(profiles (N, X), offsets (X,)
    pixels, N)``; None where the axis has a repeated point or fewer than 3 profiles lie in the image."""
    pts = resample_polyline(ax, n_profiles + 2)
    tangent = np.gradient(pts, axis=0)
    norm = np.linalg.norm(tangent, axis=1, keepdims=True)
    if np.any(norm < 1e-9):
        return None
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1) / norm
    k = max(1, round(trim_fraction * len(pts)))
    pts, normal = pts[k:-k], normal[k:-k]
    x = np.arange(-half_px, half_px + 0.5 * step_px, step_px)
    q = pts[:, None, :] + x[None, :, None] * normal[:, None, :]  # (N, X, 2)
    h, w = img.shape
    keep = ((q[..., 0] >= 0) & (q[..., 0] <= w - 1) & (q[..., 1] >= 0) & (q[..., 1] <= h - 1)).all(axis=1)
    if keep.sum() < 3:
        return None
    q = q[keep]
    prof = ndimage.map_coordinates(img, [q[..., 1].ravel(), q[..., 0].ravel()], order=1).reshape(q.shape[:2])
    return prof, x, int(keep.sum())


def _aligned_fit(
    prof: np.ndarray,
    x: np.ndarray,
    R: float,
    Ri: float,
    scale_range: tuple[float, float],
    fixed: bool,
    step_px: float,
    align_iterations: int,
) -> tuple[optimize.OptimizeResult, np.ndarray] | None:
    """The model fitted to the profiles' median, each profile re-centred on the fitted model and the
    fit repeated ``align_iterations`` times: ``(fit, re-centred profiles (N, X))``; None where a fit fails."""
    s_lo, s_hi = scale_range
    fit = _fit(np.median(prof, axis=0), x, R, Ri, (s_lo, s_hi), fixed, None)
    max_shift = round(R * s_hi / step_px)
    shifts = np.arange(-max_shift, max_shift + 1)
    for _ in range(align_iterations):
        if fit is None:
            return None
        s = fit.x[0]
        fine = np.arange(x[0] / s - 2.0 * R, x[-1] / s + 2.0 * R, _FINE_MM)
        template = _model(np.r_[fit.x[:4], 0.0, 0.0, 0.0, 0.0], x, fine, R, Ri)
        detr = prof - np.median(prof, axis=1, keepdims=True)
        scores = np.stack([detr @ np.roll(template, int(j)) for j in shifts], axis=1)
        offset = shifts[np.argmax(scores, axis=1)] * step_px
        prof = np.stack([np.interp(x + o, x, row) for o, row in zip(offset, prof, strict=True)])
        fit = _fit(np.median(prof, axis=0), x, R, Ri, (s_lo, s_hi), fixed, np.r_[fit.x[:4], 0.0, fit.x[5:]])
    if fit is None:
        return None
    return fit, prof
