"""Pre-registration checks of a case's images and cameras: repeated images, implausible
intrinsics, inverted and mirrored images.

Each check is cheap (a few image correlations, a 64² DRR per view) and names the problem in one
line: what is wrong, with which view, and what to check. All findings are of kind ``"input"`` (bad
input, exit status 2); :func:`~fluoronav.navigation.checks.preflight.preflight` runs them with the label
and plan checks.

Frames: each view's camera holds ``camera_from_ct`` (the CT's world frame, LPS, mm); images are
log images (bright = attenuating), (rows, cols).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from fluoronav.anatomy.volume import Volume
from fluoronav.geometry.camera import Camera
from fluoronav.navigation.case.model import VerificationViews
from fluoronav.navigation.case.view import CaseView
from fluoronav.navigation.checks.preflight_config import PreflightConfig, PreflightFinding, finding
from fluoronav.rendering.ct import CTRenderer

__all__ = [
    "check_intensities",
    "check_views",
]

logger = logging.getLogger(__name__)


def _ncc(a: np.ndarray, b: np.ndarray) -> float | None:
    """Normalised correlation of two arrays of one shape; None where either is constant."""
    x = np.asarray(a, np.float64).ravel()
    y = np.asarray(b, np.float64).ravel()
    x = x - x.mean()
    y = y - y.mean()
    nx, ny = float(np.sqrt(x @ x)), float(np.sqrt(y @ y))
    if nx == 0.0 or ny == 0.0 or not (math.isfinite(nx) and math.isfinite(ny)):
        return None
    return float(x @ y) / (nx * ny)


def _first_identical(
    view: CaseView, others: Sequence[CaseView], threshold: float
) -> tuple[float, CaseView | None]:
    """The first of ``others`` whose image is ``view``'s (equal, or correlated ≥ ``threshold``)."""
    a = np.asarray(view.image)
    for w in others:
        b = np.asarray(w.image)
        if a.shape != b.shape:
            continue
        c = 1.0 if np.array_equal(a, b) else _ncc(a, b)
        if c is not None and c >= threshold:
            return c, w
    return 0.0, None


def _intrinsics_reason(camera: Camera, cfg: PreflightConfig) -> str | None:
    """What is implausible about a camera's intrinsics, or None."""
    fx, fy = float(camera.K[0, 0]), float(camera.K[1, 1])
    cx, cy = float(camera.K[0, 2]), float(camera.K[1, 2])
    if not (0.0 <= cx <= camera.cols - 1 and 0.0 <= cy <= camera.rows - 1):
        return (
            f"principal point (u, v) = ({cx:.1f}, {cy:.1f}) px lies outside the {camera.cols} × "
            f"{camera.rows} image: check cx, cy in K"
        )
    if max(fx, fy) / min(fx, fy) > cfg.max_focal_aspect:
        return (
            f"focal lengths fx = {fx:.0f} px and fy = {fy:.0f} px differ (C-arm pixels are square): check K"
        )
    ps = camera.pixel_spacing_mm
    if ps is not None:
        lo, hi = cfg.pixel_spacing_mm
        if not lo <= ps <= hi:
            return f"pixel spacing {ps:g} mm is implausible ({lo:g}–{hi:g} mm): check pixel_spacing_mm"
        sdd = 0.5 * (fx + fy) * ps
        lo, hi = cfg.sdd_mm
        if not lo <= sdd <= hi:
            return (
                f"focal length {fx:.0f} px at {ps:g} mm pixels is a source-to-detector distance of "
                f"{sdd:.0f} mm (plausible {lo:g}–{hi:g} mm): check K and pixel_spacing_mm"
            )
    lo, hi = cfg.detector_span
    span = max(camera.cols / fx, camera.rows / fy)
    if not lo <= span <= hi:
        return (
            f"focal length {fx:.0f} px makes the detector {span:.2f} times as wide as the source-to-"
            f"detector distance (plausible {lo:g}–{hi:g}): check the focal length in K"
        )
    return None


def check_views(
    views: Sequence[CaseView],
    verification: VerificationViews | None = None,
    config: PreflightConfig | None = None,
) -> list[PreflightFinding]:
    """The images and cameras of a case, without the CT (all findings of kind ``"input"``).

    Checks: no view is the same image as another (equal arrays, or a normalised correlation of at
    least ``identical_ncc``); no verification image is one of the first images; every camera's
    intrinsics are plausible (principal point inside the image, square pixels, the detector's
    span over the source-to-detector distance, and with a pixel spacing that distance in mm).

    Args:
        views: the first views.
        verification: the views after the move, or None.
        config: thresholds (default :class:`PreflightConfig`).
    """
    cfg = config or PreflightConfig()
    later = () if verification is None else tuple(verification.views)
    out: list[PreflightFinding] = []
    for group, what in ((tuple(views), "view"), (later, "verification view")):
        for k, v in enumerate(group):
            subject = f"{what} {v.name!r}"
            c, w = _first_identical(v, group[:k], cfg.identical_ncc)
            if w is not None:
                text = (
                    f" is the same image as {what} {w.name!r} (correlation {c:.5f}; a copy, or a retake "
                    "without moving the C-arm or the CM): give each view its own image"
                )
                out.append(finding("input", subject, text, "identical_views"))
            reason = _intrinsics_reason(v.camera, cfg)
            if reason is not None:
                out.append(finding("input", subject, f": {reason}", "intrinsics"))
    for v in later:
        c, w = _first_identical(v, tuple(views), cfg.identical_ncc)
        if w is not None:
            text = (
                f" is the same image as the first view {w.name!r} (correlation {c:.5f}): give the images "
                "taken after the robot moved"
            )
            out.append(finding("input", f"verification view {v.name!r}", text, "verification_repeats_views"))
    return out


def _coarse_ct(volume: Volume, voxel_mm: float) -> Volume:
    """The CT box-averaged by integer factors to about ``voxel_mm`` voxels (HU, no labels)."""
    f_xyz = [
        max(1, min(n, round(voxel_mm / s))) for s, n in zip(volume.spacing_mm, volume.shape_xyz, strict=True)
    ]
    fx, fy, fz = f_xyz
    nz, ny, nx = (n // f * f for n, f in zip(volume.data.shape, (fz, fy, fx), strict=True))
    data = np.asarray(volume.data[:nz, :ny, :nx], np.float32)
    data = data.reshape(nz // fz, fz, ny // fy, fy, nx // fx, fx).mean(axis=(1, 3, 5), dtype=np.float32)
    # coarse voxel i sits at fine index f·i + (f − 1)/2
    origin = volume.world_from_index @ np.append((np.asarray(f_xyz, np.float64) - 1.0) / 2.0, 1.0)
    spacing = tuple(float(s * f) for s, f in zip(volume.spacing_mm, f_xyz, strict=True))
    return Volume(data=data, spacing_mm=spacing, origin_mm=tuple(origin[:3]), direction=volume.direction)  # type: ignore[arg-type]


def _binned(image: np.ndarray, factor: int) -> np.ndarray:
    """(rows, cols) box-binned by ``factor`` (trailing pixels dropped, as :meth:`Camera.downsample`)."""
    r, c = (n // factor * factor for n in image.shape)
    a = np.asarray(image[:r, :c], np.float64)
    return a.reshape(r // factor, factor, c // factor, factor).mean(axis=(1, 3))


def check_intensities(
    views: Sequence[CaseView],
    volume: Volume,
    config: PreflightConfig | None = None,
    *,
    what: str = "view",
) -> list[PreflightFinding]:
    """Inverted and mirrored images: each image, and its mirror, against a coarse DRR of the CT at
    its initial camera.

    fluoronav images are log images (bright = attenuating); a MONOCHROME1 image read as
    MONOCHROME2 has its grey levels reversed. Each image is box-binned to about ``drr_size_px``
    pixels and correlated with a DRR of the CT box-averaged to ``drr_voxel_mm`` voxels, rendered at
    the view's camera binned alike; a correlation below ``inverted_ncc`` is a finding (``"input"``),
    unless the image's mirror explains it better (``mirrored_ncc``): a set whose every view looks
    mirrored is a finding (the detector's orientation); a single mirrored view is left to the
    bones' per-view checks, which leave it out of the registration.

    Notes:
        The test assumes that the view's initial ``camera_from_ct`` shows roughly the anatomy the
        image shows (within a few centimetres and ~10°: a C-arm calibration, DICOM geometry with
        the CT at the isocentre, or a manual alignment), so that body outline and bones overlap.
        It is insensitive to any increasing grey-level map (gain, offset, gamma, detector
        response), to the CM and to noise. Failure modes: an initial pose far off, or an image
        collimated to a region the CT does not cover, mostly gives a correlation near 0 and no
        finding (an inverted image then goes unnoticed here), but a pose off by 6 cm and 15° or
        more can correlate negatively by chance; so can an image whose dominant contrast is
        something the CT lacks (a large metal implant, a lead apron). Such a false finding gives
        its correlation in the reason. Cost: one DRR of ``drr_size_px``² per view.

    Args:
        views: the views (first or verification) whose cameras hold ``camera_from_ct``.
        volume: the CT (HU).
        config: thresholds (default :class:`PreflightConfig`).
        what: how the findings name the views (``"view"`` or ``"verification view"``).
    """
    cfg = config or PreflightConfig()
    if not views:
        return []
    renderer = CTRenderer.from_hu(_coarse_ct(volume, cfg.drr_voxel_mm), device="cpu", mipmap=False)
    out, mirrored = [], []
    for v in views:
        image = np.asarray(v.image)
        if image.shape != (v.camera.rows, v.camera.cols):
            continue  # the case reader refuses such a view; nothing to compare here
        factor = max(1, math.ceil(max(image.shape) / cfg.drr_size_px))
        drr = renderer.render_one(v.camera.downsample(factor)).cpu().numpy()
        binned = _binned(image, factor)
        c, c_mirror = _ncc(binned, drr), _ncc(binned[:, ::-1], drr)
        logger.debug("%s %s: correlation with the DRR %s, mirrored %s", what, v.name, c, c_mirror)
        if c is None:
            continue
        if c_mirror is not None and c_mirror >= cfg.mirrored_ncc and c_mirror > -c:
            mirrored.append((v.name, c, c_mirror))
        elif c < cfg.inverted_ncc:
            text = (
                f" looks inverted (correlation {c:.2f} with a DRR of the CT at its camera; bone should be "
                "bright): a MONOCHROME1 image read as MONOCHROME2? Invert it"
            )
            out.append(finding("input", f"{what} {v.name!r}", text, "inverted_image"))
    if mirrored and len(mirrored) == len(views):
        # every view flipped: the detector's orientation, not one view (which the bones' per-view
        # checks leave out)
        name, c, c_mirror = mirrored[0]
        text = (
            f" look mirrored left–right ({what} {name!r}: correlation {c:.2f} with a DRR of the CT at "
            f"its camera, {c_mirror:.2f} mirrored): check the detector orientation (flip the images "
            "or the cameras' u axis)"
        )
        out.append(finding("input", f"all {len(views)} {what}s", text, "mirrored_images"))
    return out
