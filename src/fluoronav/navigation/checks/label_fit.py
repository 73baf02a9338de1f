"""Pre-registration check that the bone labels sit on the CT's bone (the CT ↔ labels pairing).

A label map mirrored left–right against its CT, shifted (another origin) or taken from another CT
passes the label-volume and landmark checks when its landmarks came with it, and the registration
then fits the images to bone that is not there. On the CT and labels sampled every ~2 mm, each
bone label's outermost layer is compared with the layer just outside it, relative to the label's
bright bone (:func:`bone_fit`): labels that fit no bone are named, with the shift that would fit
them; a label map that fits better mirrored than as given is named mirrored. A mirror of a
left–right symmetric anatomy fits as well as the truth and cannot be told (docs/validation.md).
Findings are of kind ``"input"``; thresholds in :class:`.preflight_config.PreflightConfig`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from fluoronav.anatomy.volume import Volume
from fluoronav.navigation.checks.preflight_config import PreflightConfig, PreflightFinding, finding

__all__ = [
    "BoneFit",
    "SampledCT",
    "bone_fit",
    "check_label_fit",
    "label_depth_mm",
    "mirrored_labels",
    "sample_ct",
]

logger = logging.getLogger(__name__)

#: the contrast's denominator is at least this (HU): a label without bright bone scores ~0
_MIN_BONE_SPAN_HU = 100.0
#: the shifted label map is searched this many sampled voxels from where it is, at most
_MAX_SHIFT_STEPS = 8
#: a label's box is grown by this many sampled voxels (room for its outer layer)
_PAD = 2


@dataclass(frozen=True)
class SampledCT:
    """The CT and its labels sampled every ``stride`` voxels (the label-fit grid).

    Attributes:
        hu: (nz', ny', nx') float32 HU.
        labels: (nz', ny', nx') the label values at the same voxels.
        stride_zyx: (3,) the sampling step along each array axis, voxels.
        step_world: (3, 3) world mm of one sampled step along each array axis (rows: z, y, x).
    """

    hu: np.ndarray
    labels: np.ndarray
    stride_zyx: tuple[int, int, int]
    step_world: np.ndarray


def _strides(volume: Volume, voxel_mm: float) -> tuple[int, int, int]:
    sx, sy, sz = volume.spacing_mm
    return tuple(max(1, round(voxel_mm / float(s))) for s in (sz, sy, sx))  # type: ignore[return-value]


def sample_ct(volume: Volume, voxel_mm: float) -> SampledCT:
    """``volume`` (with labels) sampled every ~``voxel_mm`` along each axis: every k-th voxel, no
    averaging (which would blur the cortex)."""
    if volume.labels is None:
        raise ValueError("the CT has no labels")
    kz, ky, kx = _strides(volume, voxel_mm)
    step = (slice(None, None, kz), slice(None, None, ky), slice(None, None, kx))
    W = volume.world_from_index[:3, :3]
    step_world = np.stack([W[:, 2] * kz, W[:, 1] * ky, W[:, 0] * kx])
    return SampledCT(
        np.asarray(volume.data[step], np.float32),
        np.ascontiguousarray(volume.labels[step]),
        (kz, ky, kx),
        step_world,
    )


def mirrored_labels(volume: Volume, s: SampledCT) -> np.ndarray:
    """``volume``'s label map flipped left–right (its array along the axis nearest the world's x,
    about the array's centre: a flip in a file's orientation), sampled on ``s``'s grid."""
    if volume.labels is None:
        raise ValueError("the CT has no labels")
    flip = [slice(None)] * 3
    flip[2 - int(np.argmax(np.abs(volume.direction[0])))] = slice(None, None, -1)
    kz, ky, kx = s.stride_zyx
    return np.ascontiguousarray(volume.labels[tuple(flip)][::kz, ::ky, ::kx])


@dataclass(frozen=True)
class BoneFit:
    """How well one label sits on the CT's bone (:func:`bone_fit`); ~1 on bone, ~0 off it.

    Attributes:
        contrast: (median HU of the label's outermost layer − median HU of the layer just outside
            it) / (the label's 95th-percentile HU − that outside median): robust, it falls only
            where most of the surface is off the bone (and, by :func:`bone_fit`'s default, not for
            a boundary one voxel off).
        mean_contrast: the same with the layers' means of HU clipped to [that outside median, that
            95th percentile]: it falls with every part of the surface that is off the bone.
    """

    contrast: float
    mean_contrast: float


def _box(mask: np.ndarray, pad: int) -> tuple[slice, slice, slice] | None:
    """The bounding box of a 3-D mask grown by ``pad`` voxels (within the array); None when empty."""
    out = []
    for axis in range(3):
        hit = np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != axis)))
        if hit.size == 0:
            return None
        out.append(slice(max(int(hit[0]) - pad, 0), int(hit[-1]) + pad + 1))
    return out[0], out[1], out[2]


def _layer_fit(h: np.ndarray, m: np.ndarray, other: np.ndarray) -> BoneFit | None:
    """:class:`BoneFit` of the mask ``m`` on the HU ``h`` (one box of both), ``other`` labels left out
    of its outside layer; None where a layer is empty."""
    inner = m & ~ndimage.binary_erosion(m, border_value=1)
    outer = ndimage.binary_dilation(m) & ~m & ~other
    if not inner.any() or not outer.any():
        return None
    h_in, h_out = h[inner], h[outer]
    med_out, bright = float(np.median(h_out)), float(np.percentile(h[m], 95))
    span = max(bright - med_out, _MIN_BONE_SPAN_HU)
    clipped = [float(np.clip(x, med_out, max(bright, med_out)).mean()) for x in (h_in, h_out)]
    return BoneFit((float(np.median(h_in)) - med_out) / span, (clipped[0] - clipped[1]) / span)


def bone_fit(hu: np.ndarray, labels: np.ndarray, value: int, *, tolerant: bool = True) -> BoneFit | None:
    """How well label ``value`` sits on bone (:class:`BoneFit`); None for an empty label.

    The label's outermost layer against the layer just outside it, on the sampled grid. The outside
    layer leaves other labels' voxels out (a joint's neighbour bone); faces cut by the array's edge
    are not surface. The denominator is at least :data:`_MIN_BONE_SPAN_HU`. ``tolerant``: the robust
    contrast is the best of the label as given, one sampled voxel smaller and one larger (a boundary
    drawn up to a voxel off, e.g. a generous segmentation, still sits on the bone).
    """
    mask = labels == value
    box = _box(mask, _PAD)
    if box is None:
        return None
    m, h = mask[box], hu[box]
    other = (labels[box] != 0) & ~m
    fit = _layer_fit(h, m, other)
    if fit is None or not tolerant:
        return fit
    best = fit.contrast
    for moved in (ndimage.binary_erosion(m, border_value=1), ndimage.binary_dilation(m) & ~other):
        f = _layer_fit(h, moved, other) if moved.any() else None
        if f is not None:
            best = max(best, f.contrast)
    return BoneFit(best, fit.mean_contrast)


def label_depth_mm(s: SampledCT, value: int) -> float | None:
    """The radius of the largest ball inside label ``value``, mm (a femur's: its femoral head's), to
    about half a sampled voxel; None for an empty label."""
    mask = s.labels == value
    box = _box(mask, 0)
    if box is None:
        return None
    steps = np.linalg.norm(s.step_world, axis=1)
    crop = np.pad(mask[box], 1)  # background around it: the label's every face is surface
    depth = ndimage.distance_transform_edt(crop, sampling=steps)
    return float(depth.max()) - 0.5 * float(steps.min())


def _fits(
    hu: np.ndarray, labels: np.ndarray, values: dict[str, int], *, tolerant: bool = True
) -> dict[str, BoneFit]:
    """Each label's :func:`bone_fit` (an empty label fits nothing)."""
    return {
        name: bone_fit(hu, labels, v, tolerant=tolerant) or BoneFit(0.0, 0.0) for name, v in values.items()
    }


def _worst(fits: dict[str, BoneFit]) -> float:
    """The lowest robust contrast among the labels: the check's statistic."""
    return min(f.contrast for f in fits.values())


def _worst_mean(fits: dict[str, BoneFit]) -> float:
    return min(f.mean_contrast for f in fits.values())


def _shifted(labels: np.ndarray, d: tuple[int, int, int]) -> np.ndarray:
    """``labels`` moved by ``d`` voxels (z, y, x), background shifted in."""
    out = np.zeros_like(labels)
    src, dst = [], []
    for n, k in zip(labels.shape, d, strict=True):
        src.append(slice(max(0, -k), n - max(0, k)))
        dst.append(slice(max(0, k), n - max(0, -k)))
    out[tuple(dst)] = labels[tuple(src)]
    return out


def _best_shift(s: SampledCT, values: dict[str, int]) -> tuple[tuple[int, int, int], float]:
    """The label map's shift (sampled voxels, z y x) that fits the bone best, by steps of one voxel
    along an axis while the worst label's contrast improves, and that contrast."""
    d = (0, 0, 0)
    best = _worst(_fits(s.hu, s.labels, values, tolerant=False))  # climbed on the strict fit: faster
    for _ in range(_MAX_SHIFT_STEPS):
        trials = []
        for step in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)):
            t = (d[0] + step[0], d[1] + step[1], d[2] + step[2])
            trials.append((_worst(_fits(s.hu, _shifted(s.labels, t), values, tolerant=False)), t))
        score, t = max(trials)
        if score <= best:
            break
        best, d = score, t
    return d, _worst(_fits(s.hu, _shifted(s.labels, d), values))


def _shift_hint(s: SampledCT, values: dict[str, int], cfg: PreflightConfig) -> str:
    """Which pairing fault labels that fit no bone look like: shifted (by how much) or another CT's."""
    d, score = _best_shift(s, values)
    if score >= cfg.min_bone_contrast and d != (0, 0, 0):
        mm = np.asarray(d, np.float64) @ s.step_world
        return (
            f"shifted? (moved by {mm[0]:+.0f}, {mm[1]:+.0f}, {mm[2]:+.0f} mm in x, y, z they score "
            f"{score:.2f}): check the label map's origin against the CT's"
        )
    return "mirrored, shifted or from another CT? Check that the label map was made on this CT"


def _listed(fits: dict[str, BoneFit], mean: bool = False) -> str:
    return ", ".join(f"{n!r} {f.mean_contrast if mean else f.contrast:.2f}" for n, f in fits.items())


def check_label_fit(
    volume: Volume,
    side: str,
    config: PreflightConfig | None = None,
    *,
    sampled: SampledCT | None = None,
) -> list[PreflightFinding]:
    """The ``pelvis`` and ``femur_<side>`` labels on the CT's bone (at most one finding, of kind
    ``"input"``).

    Checks: ``labels_mirrored``: the label map mirrored left–right fits the bone better than as
    given, its worst label's mean contrast (:class:`BoneFit`) higher by ``mirror_margin`` or more;
    ``labels_on_bone``: each label's robust contrast at least ``min_bone_contrast``, the reason
    naming the pairing fault it looks like (shifted, by how much, or another CT's).

    Args:
        volume: the CT with labels; side: ``"left"`` or ``"right"``.
        config: thresholds (default :class:`PreflightConfig`).
        sampled: :func:`sample_ct` of ``volume`` at ``contrast_voxel_mm``, when already made.
    """
    cfg = config or PreflightConfig()
    if volume.labels is None:
        return []
    values = {n: v for n in ("pelvis", f"femur_{side}") if (v := volume.label_value(n)) is not None}
    s = sampled or sample_ct(volume, cfg.contrast_voxel_mm)
    values = {n: v for n, v in values.items() if np.any(s.labels == v)}
    if not values:
        return []
    fits = _fits(s.hu, s.labels, values)
    mirrored = _fits(s.hu, mirrored_labels(volume, s), values, tolerant=False)  # its mean only
    logger.debug("bone fit %s, mirrored %s", fits, mirrored)
    gain = _worst_mean(mirrored) - _worst_mean(fits)
    if gain >= cfg.mirror_margin:
        text = (
            f" fit the CT's bone better mirrored left–right (mean contrast {_listed(fits, True)}; "
            f"mirrored {_listed(mirrored, True)}: {gain:.2f} better, at most {cfg.mirror_margin:g}): "
            "is the label map, or the CT, mirrored against the other (a left–right flip in one file's "
            "orientation)? Flip one so that they match (mirror_margin)"
        )
        return [finding("input", "'labels'", text, "labels_mirrored")]
    if _worst(fits) >= cfg.min_bone_contrast:
        return []
    text = (
        f" do not sit on the CT's bone (bone contrast {_listed(fits)}; at least "
        f"{cfg.min_bone_contrast:g}): {_shift_hint(s, values, cfg)} (min_bone_contrast)"
    )
    return [finding("input", "'labels'", text, "labels_on_bone")]
