"""Checks of a navigation case that run before any registration: the plan, the labels, the images.

A registration cannot repair inputs that contradict each other, and some contradictions let the
pipeline run to a confident robot command (a plan target in soft tissue, labels whose pelvis and
femur are swapped, the same image given as two views). Each check here is cheap (a distance
transform of one label, a few image correlations, a 64² DRR per view) and names the problem in one
line: what is wrong, with which view, plan or label, and what to check.

A finding's ``kind`` says how the navigation ends: ``"input"`` is bad input (an
:class:`~fluoronav.errors.InputError`, exit status 2, see :func:`raise_for_input`); ``"plan"`` is a
plan the robot must not carry out (a refusal, exit status 3).

Frames: the CT's world frame (LPS, mm); label distances are measured on the CT's voxel grid through
its ``world_from_index`` / ``index_from_world`` transforms.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import ndimage

from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.navigation.case import NavigationCase, VerificationViews
from fluoronav.navigation.case_view import CaseView
from fluoronav.navigation.planning import Plan
from fluoronav.rendering.ct import CTRenderer

__all__ = [
    "LabelDistance",
    "PreflightConfig",
    "PreflightFinding",
    "check_intensities",
    "check_labels",
    "check_plan",
    "check_views",
    "insertion_limit_mm",
    "preflight",
    "raise_for_input",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class PreflightConfig:
    """Thresholds of the pre-registration checks (lengths in mm, volumes in mL).

    Attributes:
        target_margin_mm: the plan's CM tip target may lie at most this far outside the surface of
            the femur label (``femur_<side>``). Label maps are segmented to within a voxel or two,
            and a core-decompression plan puts the tip on the entry point, on the surface.
        entry_surface_max_mm: the plan's entry point must lie within this distance of the femur
            label's surface, inside or outside: the entry is where the CM meets the bone.
        direction_probe_mm: the point this far along the insertion direction from the entry must
            lie inside the femur label: a direction that points away from the bone (a flipped
            sign) would put the CM's body inside it.
        max_insertion_depth_mm: a site's own limit on the plan's insertion depth beyond the entry;
            None: only the CM's reach (:func:`insertion_limit_mm`) limits it.
        landmark_margin_mm: the femoral-head landmark (the head centre, ~20 mm deep in the head) may
            lie at most this far outside the femur label: clicking error, not a wrong label.
        pelvis_volume_ml: plausible (low, high) volume of the ``pelvis`` label. Wide: a CT cropped
            to one hip keeps a hemipelvis (a few hundred mL); a whole adult pelvis with the sacrum is
            ~0.6–1.3 L. Outside: a wrong label value, a label map on another grid, or wrong spacing.
        femur_volume_ml: plausible (low, high) volume of the ``femur_<side>`` label: from a head and
            neck cropped just below the trochanters (~60 mL) to a whole adult femur (~1 L).
        sdd_mm: plausible (low, high) source-to-detector distance (focal length × pixel spacing)
            of a C-arm, for views whose camera gives the pixel spacing (mobile C-arms ~1000 mm).
        pixel_spacing_mm: plausible (low, high) pixel spacing at the stored resolution: a flat
            panel's pitch (~0.1–0.2 mm) up to a 64² image of a 30 cm detector (~5 mm).
        detector_span: plausible (low, high) field of view as the detector's width over the
            source-to-detector distance (``cols / fx``, ``rows / fy``; no pixel spacing needed):
            a 9″ image intensifier at 1.2 m is ~0.2, a 43 cm panel at 1 m ~0.43, a crop less.
        max_focal_aspect: largest ratio of ``fx`` and ``fy``: C-arm pixels are square.
        identical_ncc: two images of one shape whose normalised correlation reaches this are the
            same image given twice. Views of one anatomy from orbits 15–20° apart, and images
            retaken with new noise, stay well below it; a copy rounded to 8 bits stays above.
        drr_size_px: the inversion check compares each image with a DRR at about this many pixels
            along its longer side (the image is box-binned to it).
        drr_voxel_mm: the CT is box-averaged to about this voxel size for that DRR.
        inverted_ncc: an image whose correlation with that DRR is below this (negative) value is
            taken as inverted. At an initial pose within a few cm and ~10° of the truth the DRR
            correlates positively with the image (body outline, pelvis and femur bright), and an
            inverted image as strongly negatively; poses off by 6 cm and 15° or more can correlate
            negatively by chance, hence the margin below 0.
        mirrored_ncc: an image whose left–right mirror correlates with that DRR at least this much,
            and more than the image inverted does (``−c``), looks mirrored rather than inverted. A
            mirrored image also correlates negatively (body outline and bones land on soft
            tissue), so the two are told apart by which repair explains the image better: on the
            demo's views the mirror of a mirrored image scored 0.80–0.97 against 0.05–0.66 for its
            inverse, and the mirror of an inverted image 0.05–0.63 against 0.80–0.97.
    """

    target_margin_mm: float = 3.0
    entry_surface_max_mm: float = 5.0
    direction_probe_mm: float = 10.0
    max_insertion_depth_mm: float | None = None
    landmark_margin_mm: float = 2.0
    pelvis_volume_ml: tuple[float, float] = (100.0, 3000.0)
    femur_volume_ml: tuple[float, float] = (25.0, 1500.0)
    sdd_mm: tuple[float, float] = (600.0, 1600.0)
    pixel_spacing_mm: tuple[float, float] = (0.05, 10.0)
    detector_span: tuple[float, float] = (0.05, 0.8)
    max_focal_aspect: float = 1.05
    identical_ncc: float = 0.9999
    drr_size_px: int = 64
    drr_voxel_mm: float = 4.0
    inverted_ncc: float = -0.5
    mirrored_ncc: float = 0.5


@dataclass(frozen=True)
class PreflightFinding:
    """One failed check.

    Attributes:
        kind: ``"plan"`` (the plan is refused, exit status 3) or ``"input"`` (bad input, exit 2).
        subject: what it is about: ``"plan 'entry'"``, ``"label 'femur_left'"``,
            ``"landmark 'femoral_head_left'"``, ``"view 'AP'"``, ``"verification view 'AP'"``.
        reason: one line that names the subject, says what is wrong and what to check.
        check: a short name of the check (``"target_in_femur"``, ``"identical_views"``, …).
    """

    kind: Literal["plan", "input"]
    subject: str
    reason: str
    check: str


def _finding(kind: Literal["plan", "input"], subject: str, text: str, check: str) -> PreflightFinding:
    """A finding whose reason is ``subject`` followed by ``text`` (one line)."""
    return PreflightFinding(kind, subject, " ".join(f"{subject}{text}".split()), check)


def _has_label(volume: Volume, name: str) -> bool:
    value = volume.label_value(name)
    return volume.labels is not None and value is not None and bool(np.any(volume.labels == value))


# ----- distances to a label ----------------------------------------------------------------------
class LabelDistance:
    """Signed distance (mm) from world points to the surface of one label: negative inside.

    A Euclidean distance transform of the label (and of its complement) on the CT grid, cropped to
    the label's bounding box grown by ``pad_mm``, sampled trilinearly; the surface is taken half a
    voxel beyond the outermost labelled voxel centres. Points outside that box get the distance to
    the nearest labelled voxel (the label lies wholly inside the box).

    Args:
        volume: the CT with labels.
        label: the label's name.
        pad_mm: margin of the crop, mm.

    Raises:
        ValueError: the volume has no such label, or it is empty.
    """

    def __init__(self, volume: Volume, label: str, *, pad_mm: float = 12.0) -> None:
        value = volume.label_value(label)
        if volume.labels is None or value is None:
            raise ValueError(f"the CT has no label {label!r}")
        mask = volume.labels == value
        if not mask.any():
            raise ValueError(f"label {label!r} is empty")
        self.index_from_world = volume.index_from_world
        W = volume.world_from_index
        spacing_zyx = np.asarray(volume.spacing_mm[::-1], np.float64)
        half = 0.5 * float(spacing_zyx.min())
        pad = np.ceil(pad_mm / spacing_zyx).astype(int) + 1
        nz = np.argwhere(mask)
        self.lo = np.maximum(nz.min(0) - pad, 0)
        hi = np.minimum(nz.max(0) + pad + 1, mask.shape)
        crop = mask[tuple(slice(int(a), int(b)) for a, b in zip(self.lo, hi, strict=True))]
        d_out = ndimage.distance_transform_edt(~crop, sampling=spacing_zyx)
        d_in = ndimage.distance_transform_edt(crop, sampling=spacing_zyx)
        self.field = np.where(crop, half - d_in, d_out - half).astype(np.float32)
        # labelled voxels on the label's border, world mm: the nearest one to a far point
        border = crop & ~ndimage.binary_erosion(crop)
        kji = np.argwhere(border) + self.lo
        self.border_world = kji[:, ::-1] @ W[:3, :3].T + W[:3, 3]
        self.half_mm = half

    def __call__(self, points_world: np.ndarray) -> np.ndarray:
        """(..., 3) world points, mm → (...) signed distances, mm (negative inside the label)."""
        p = np.asarray(points_world, np.float64)
        flat = p.reshape(-1, 3)
        ijk = flat @ self.index_from_world[:3, :3].T + self.index_from_world[:3, 3]
        kji = ijk[:, ::-1] - self.lo
        inside = np.all((kji >= 0) & (kji <= np.asarray(self.field.shape) - 1), axis=1)
        out = np.empty(len(flat))
        if inside.any():
            out[inside] = ndimage.map_coordinates(self.field, kji[inside].T, order=1, mode="nearest")
        for n in np.flatnonzero(~inside):
            far = np.sqrt(((self.border_world - flat[n]) ** 2).sum(axis=1).min())
            out[n] = far - self.half_mm
        return out.reshape(p.shape[:-1])


def _label_at(volume: Volume, point_world: np.ndarray) -> str | None:
    """Name of the label at the voxel nearest a world point ("" for background, None off the grid)."""
    if volume.labels is None:
        return None
    ijk = np.rint(volume.index_from_world[:3, :3] @ point_world + volume.index_from_world[:3, 3]).astype(int)
    k, j, i = ijk[::-1]
    nz, ny, nx = volume.labels.shape
    if not (0 <= k < nz and 0 <= j < ny and 0 <= i < nx):
        return None
    value = int(volume.labels[k, j, i])
    return volume.label_names.get(value, f"label value {value}") if value else ""


def _femur_distance(volume: Volume, side: str, config: PreflightConfig) -> LabelDistance:
    pad = max(config.target_margin_mm, config.entry_surface_max_mm, config.landmark_margin_mm) + 5.0
    return LabelDistance(volume, f"femur_{side}", pad_mm=pad)


# ----- the plan ----------------------------------------------------------------------------------
def insertion_limit_mm(cm_config: CMConfig, config: PreflightConfig) -> float:
    """The deepest insertion beyond the entry a plan may ask for, mm: the CM's length from its base
    landmark A to the tip (``cm_config.tip_z_mm``; deeper, the CM's base and the mount behind it
    would enter the bone), capped by ``config.max_insertion_depth_mm`` where given."""
    limit = float(cm_config.tip_z_mm)
    if config.max_insertion_depth_mm is not None:
        limit = min(limit, float(config.max_insertion_depth_mm))
    return limit


def check_plan(
    plan: Plan,
    volume: Volume,
    side: str,
    cm_config: CMConfig,
    config: PreflightConfig | None = None,
    *,
    distance: LabelDistance | None = None,
) -> list[PreflightFinding]:
    """The plan against the femur label and the CM's limits → findings of kind ``"plan"`` (none: it passes).

    Checks: the tip target inside the ``femur_<side>`` label or at most ``target_margin_mm``
    outside its surface; the entry point within ``entry_surface_max_mm`` of that surface; the point
    ``direction_probe_mm`` along the insertion direction inside the label; the insertion depth
    within :func:`insertion_limit_mm`; the planned control points within the CM's range.

    Args:
        plan: the plan (CT frame).
        volume: the CT with the ``femur_<side>`` label; side: ``"left"`` or ``"right"``.
        cm_config: the CM.
        config: thresholds (default :class:`PreflightConfig`).
        distance: the femur label's :class:`LabelDistance`, when already computed.
    """
    cfg = config or PreflightConfig()
    femur = f"femur_{side}"
    d = distance or _femur_distance(volume, side, cfg)
    subject = f"plan {plan.target_name!r}"
    out: list[PreflightFinding] = []

    def refuse(check: str, text: str) -> None:
        out.append(_finding("plan", subject, f": {text}", check))

    entry, direction = plan.entry_point_world_mm, plan.direction_world
    target_d, entry_d, probe_d = d(
        np.stack([plan.tip_target_world_mm, entry, entry + cfg.direction_probe_mm * direction])
    )
    if target_d > cfg.target_margin_mm:
        refuse(
            "target_in_femur",
            f"the target lies {target_d:.1f} mm outside the {femur} label (at most "
            f"{cfg.target_margin_mm:g} mm): check the plan's entry point, direction and insertion depth",
        )
    if abs(entry_d) > cfg.entry_surface_max_mm:
        where = "outside" if entry_d > 0 else "inside"
        refuse(
            "entry_on_surface",
            f"the entry point lies {abs(entry_d):.1f} mm {where} the {femur} label's surface (at most "
            f"{cfg.entry_surface_max_mm:g} mm either side): put the entry on the bone surface",
        )
    if probe_d > 0.0 and abs(entry_d) <= cfg.entry_surface_max_mm:
        refuse(
            "direction_into_femur",
            f"the insertion direction points out of the {femur} label ({cfg.direction_probe_mm:g} mm "
            f"along it lies {probe_d:.1f} mm outside the bone): check the direction's sign",
        )
    limit = insertion_limit_mm(cm_config, cfg)
    if plan.insertion_depth_mm > limit:
        refuse(
            "insertion_depth",
            f"insertion depth {plan.insertion_depth_mm:g} mm beyond the entry exceeds the limit of "
            f"{limit:g} mm (the CM's length from its base landmark A to the tip"
            + (", or the configured maximum" if cfg.max_insertion_depth_mm is not None else "")
            + "): plan a shallower target",
        )
    if plan.control_points_deg is not None:
        lo, hi = cm_config.control_point_range_deg
        bad = [(k, float(v)) for k, v in enumerate(plan.control_points_deg) if not lo <= v <= hi]
        if bad:
            k, v = bad[0]
            refuse(
                "control_points",
                f"control point {k} is {v:g}°, beyond the CM's range {lo:g}…{hi:g}°: "
                "plan a shape the CM can bend to",
            )
    return out


# ----- labels and landmarks ----------------------------------------------------------------------
def _volume_findings(volume: Volume, side: str, cfg: PreflightConfig) -> list[PreflightFinding]:
    out = []
    voxel_ml = float(np.prod(volume.spacing_mm)) / 1000.0
    for name, (lo, hi), what in (
        ("pelvis", cfg.pelvis_volume_ml, "a pelvis"),
        (f"femur_{side}", cfg.femur_volume_ml, "a femur"),
    ):
        value = volume.label_value(name)
        count = 0 if volume.labels is None or value is None else int(np.count_nonzero(volume.labels == value))
        ml = count * voxel_ml
        if not lo <= ml <= hi:
            text = (
                f" holds {ml:.0f} mL, outside the {lo:g}–{hi:g} mL plausible for {what}: check the label "
                "values, the label-name file and that the label map is on the CT's grid"
            )
            out.append(_finding("input", f"label {name!r}", text, "label_volume"))
    return out


def _landmark_finding(
    volume: Volume, name: str, femur: str, signed_mm: float, limit_mm: float
) -> PreflightFinding:
    subject = f"landmark {name!r}"
    point = np.asarray(volume.landmarks_world[name], np.float64)
    found = _label_at(volume, point)
    if found == "pelvis":
        text = f"lies in the 'pelvis' label, not in {femur!r}: are the pelvis and femur labels swapped?"
    elif found and found.startswith("femur_"):
        text = f"lies in the {found!r} label, not in {femur!r}: check the side and the landmark names"
    else:
        where = "off the CT's grid" if found is None else "in no label"
        text = (
            f"lies {signed_mm:.1f} mm outside the {femur} label (at most {limit_mm:g} mm; {where}): "
            "check the landmarks' coordinate system (LPS or RAS) and that they belong to this CT"
        )
    return _finding("input", subject, f" {text}", "landmark_in_femur")


def check_labels(
    volume: Volume,
    side: str,
    config: PreflightConfig | None = None,
    *,
    distance: LabelDistance | None = None,
) -> list[PreflightFinding]:
    """The label map and the landmarks against each other (all findings of kind ``"input"``).

    Checks: the ``pelvis`` and ``femur_<side>`` label volumes within their plausible ranges; the
    ``femoral_head_<side>`` landmark inside the femur label (at most ``landmark_margin_mm``
    outside); the ``entry_<side>`` landmark, where given, within ``entry_surface_max_mm`` outside
    it. A head landmark in the ``pelvis`` label reads as swapped labels.

    Args:
        volume: the CT with labels and landmarks; side: ``"left"`` or ``"right"``.
        config: thresholds (default :class:`PreflightConfig`).
        distance: the femur label's :class:`LabelDistance`, when already computed.
    """
    cfg = config or PreflightConfig()
    femur = f"femur_{side}"
    volumes = _volume_findings(volume, side, cfg)
    if not _has_label(volume, femur):
        return volumes  # the volume finding names the empty label
    out: list[PreflightFinding] = []  # landmark findings first: they name the cause (a swap, a side)
    d = distance or _femur_distance(volume, side, cfg)
    for name, limit in (
        (f"femoral_head_{side}", cfg.landmark_margin_mm),
        (f"entry_{side}", cfg.entry_surface_max_mm),
    ):
        if name not in volume.landmarks_world:
            if name.startswith("femoral_head"):
                out.append(
                    _finding("input", f"landmark {name!r}", " is missing: give it", "landmark_in_femur")
                )
            continue
        signed = float(d(np.asarray(volume.landmarks_world[name], np.float64)))
        if signed > limit:
            out.append(_landmark_finding(volume, name, femur, signed, limit))
    return out + volumes


# ----- the images --------------------------------------------------------------------------------
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
                out.append(_finding("input", subject, text, "identical_views"))
            reason = _intrinsics_reason(v.camera, cfg)
            if reason is not None:
                out.append(_finding("input", subject, f": {reason}", "intrinsics"))
    for v in later:
        c, w = _first_identical(v, tuple(views), cfg.identical_ncc)
        if w is not None:
            text = (
                f" is the same image as the first view {w.name!r} (correlation {c:.5f}): give the images "
                "taken after the robot moved"
            )
            out.append(_finding("input", f"verification view {v.name!r}", text, "verification_repeats_views"))
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
            out.append(_finding("input", f"{what} {v.name!r}", text, "inverted_image"))
    if mirrored and len(mirrored) == len(views):
        # every view flipped: the detector's orientation, not one view (which the bones' per-view
        # checks leave out)
        name, c, c_mirror = mirrored[0]
        text = (
            f" look mirrored left–right ({what} {name!r}: correlation {c:.2f} with a DRR of the CT at "
            f"its camera, {c_mirror:.2f} mirrored): check the detector orientation (flip the images "
            "or the cameras' u axis)"
        )
        out.append(_finding("input", f"all {len(views)} {what}s", text, "mirrored_images"))
    return out


# ----- the case ----------------------------------------------------------------------------------
def preflight(case: NavigationCase, config: PreflightConfig | None = None) -> list[PreflightFinding]:
    """Every pre-registration check of a case.

    The label checks run first; the plan is checked against the femur label only when they pass
    (a plan measured against swapped labels would be refused for the labels' fault).

    Returns:
        the findings (empty when the case passes): ``"input"`` findings (bad input, exit status 2)
        before ``"plan"`` findings (refusal, exit status 3). ``config``: default
        :class:`PreflightConfig`.
    """
    cfg = config or PreflightConfig()
    volume, side = case.volume, case.side
    distance = _femur_distance(volume, side, cfg) if _has_label(volume, f"femur_{side}") else None
    labels = check_labels(volume, side, cfg, distance=distance)
    views = check_views(case.views, case.verification, cfg)
    images = check_intensities(case.views, volume, cfg)
    if case.verification is not None:
        images += check_intensities(case.verification.views, volume, cfg, what="verification view")
    plan: list[PreflightFinding] = []
    if not labels and distance is not None:
        plan = check_plan(case.plan, volume, side, case.cm_config, cfg, distance=distance)
    findings = labels + views + images + plan
    for f in findings:
        # the caller reports them (an input error, a refusal): logged here for the record only
        logger.info("preflight %s: %s", f.check, f.reason)
    return findings


def raise_for_input(findings: Sequence[PreflightFinding], source: str) -> None:
    """Raise the :class:`~fluoronav.errors.InputError` (exit status 2) of the first ``"input"``
    finding, naming ``source`` (the case file) and how many more there are; nothing otherwise."""
    bad = [f for f in findings if f.kind == "input"]
    if not bad:
        return
    more = f" (and {len(bad) - 1} more input problem(s))" if len(bad) > 1 else ""
    raise InputError(source, bad[0].reason + more)
