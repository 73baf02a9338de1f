"""Checks of a navigation case that run before any registration: the plan, the labels, the images.

A registration cannot repair inputs that contradict each other, and some contradictions let the
pipeline run to a confident robot command (a plan target in soft tissue, swapped pelvis and femur
labels, one image given as two views). Each check is cheap and names the problem in one line: what
is wrong, with which view, plan or label, and what to check (the list: docs/navigation.md). Other
modules of :mod:`fluoronav.navigation.checks` hold the shared inputs' ranges (``inputs``), the
labels' fit to the CT (``label_fit``), which femur (``side``), the images (``preflight_images``),
the thresholds and findings (``preflight_config``); :func:`preflight` runs them all. A finding's
``kind``: ``"input"`` (an :class:`~fluoronav.errors.InputError`, exit 2, :func:`raise_for_input`),
``"plan"`` (a refusal, exit 3) or ``"note"``. Frames: the CT's world frame (LPS, mm).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from scipy import ndimage

from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError
from fluoronav.manipulator.config import CMConfig
from fluoronav.navigation.case.model import NavigationCase
from fluoronav.navigation.checks.inputs import check_bone_hu, check_bone_size, check_ct_geometry, check_fbg
from fluoronav.navigation.checks.label_fit import SampledCT, check_label_fit, label_depth_mm, sample_ct
from fluoronav.navigation.checks.preflight_config import PreflightConfig, PreflightFinding, finding
from fluoronav.navigation.checks.preflight_images import check_intensities, check_views
from fluoronav.navigation.checks.side import check_side
from fluoronav.navigation.planning import Plan

__all__ = [
    "LabelDistance",
    "PreflightConfig",
    "PreflightFinding",
    "PreflightInputError",
    "check_intensities",
    "check_labels",
    "check_plan",
    "check_shared_inputs",
    "check_views",
    "insertion_limit_mm",
    "preflight",
    "raise_for_input",
]

logger = logging.getLogger(__name__)


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
        out.append(finding("plan", subject, f": {text}", check))

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
            out.append(finding("input", f"label {name!r}", text, "label_volume"))
    return out


def _landmarkfinding(
    volume: Volume, name: str, femur: str, signed_mm: float, limit_mm: float
) -> PreflightFinding:
    subject = f"landmark {name!r}"
    point = np.asarray(volume.landmarks_world[name], np.float64)
    found = _label_at(volume, point)
    if found == "pelvis":
        text = f"lies in the 'pelvis' label, not in {femur!r}: are the pelvis and femur labels swapped?"
    elif found and found.startswith("femur_"):
        text = (
            f"lies in the {found!r} label, not in {femur!r}: is the label map mirrored left–right against "
            "the landmarks? Else check the side and the landmark names"
        )
    else:
        where = "off the CT's grid" if found is None else "in no label"
        text = (
            f"lies {signed_mm:.1f} mm outside the {femur} label (at most {limit_mm:g} mm; {where}): "
            "check the landmarks' coordinate system (LPS or RAS) and that they belong to this CT"
        )
    return finding("input", subject, f" {text}", "landmark_in_femur")


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
                    finding("input", f"landmark {name!r}", " is missing: give it", "landmark_in_femur")
                )
            continue
        signed = float(d(np.asarray(volume.landmarks_world[name], np.float64)))
        if signed > limit:
            out.append(_landmarkfinding(volume, name, femur, signed, limit))
    return out + volumes


# ----- the case ----------------------------------------------------------------------------------
def _largest_ball(s: SampledCT, names: dict[str, int], cfg: PreflightConfig) -> tuple[str, float] | None:
    """(label, radius mm) of the largest ball inside the femur label, or inside the pelvis label where
    that is larger and the femur's is implausible (swapped labels must not read as a wrong spacing)."""
    best: tuple[str, float] | None = None
    lo, hi = cfg.bone_ball_radius_mm
    for name in sorted(names, key=lambda n: not n.startswith("femur_")):  # the femur first
        depth = label_depth_mm(s, names[name])
        if depth is not None and (best is None or depth > best[1]):
            best = (name, depth)
        if best is not None and lo <= best[1] <= hi:
            break  # plausible: the pelvis's (a large label) is not needed
    return best


def check_shared_inputs(case: NavigationCase, cfg: PreflightConfig) -> list[PreflightFinding]:
    """The inputs every view shares against their ranges and each other (:mod:`.inputs`,
    :mod:`.label_fit`): the FBG reading, the CT's geometry, the bone labels' size, HU and fit."""
    volume, side = case.volume, case.side
    fbg = check_fbg(case.fbg_control_points_deg, case.cm_config, case.fbg_sigma_deg, cfg)
    geometry = check_ct_geometry(volume, cfg)
    if geometry or volume.labels is None:
        return fbg + geometry  # on a grid of the wrong size the labels' checks would mislead
    sampled = sample_ct(volume, cfg.contrast_voxel_mm)
    names = {n: v for n in ("pelvis", f"femur_{side}") if (v := volume.label_value(n)) is not None}
    ball = _largest_ball(sampled, names, cfg)
    size = [] if ball is None else check_bone_size(volume, ball[1], ball[0], cfg)
    if size:
        return fbg + size
    hu = check_bone_hu(sampled.hu, sampled.labels, names, cfg)
    # a label that is not bone at all needs no pairing hint
    return fbg + (hu or check_label_fit(volume, side, cfg, sampled=sampled))


def preflight(case: NavigationCase, config: PreflightConfig | None = None) -> list[PreflightFinding]:
    """Every pre-registration check of a case.

    The shared inputs' ranges and the labels' fit to the CT run first (:mod:`.inputs`,
    :mod:`.label_fit`), then the label and landmark checks and which femur (:mod:`.side`); the plan
    is checked against the femur label only when they pass (a plan measured against swapped labels
    would be refused for the labels' fault).

    Returns:
        the findings (empty when the case passes): ``"input"`` findings (bad input, exit status 2)
        before ``"plan"`` findings (refusal, exit status 3), and ``"note"`` findings for the record
        (the side inferred). ``config``: default :class:`PreflightConfig`.
    """
    cfg = config or PreflightConfig()
    volume, side = case.volume, case.side
    distance = _femur_distance(volume, side, cfg) if _has_label(volume, f"femur_{side}") else None
    shared = check_shared_inputs(case, cfg)
    labels = check_labels(volume, side, cfg, distance=distance)
    sides = check_side(case)
    views = check_views(case.views, case.verification, cfg)
    images = check_intensities(case.views, volume, cfg)
    if case.verification is not None:
        images += check_intensities(case.verification.views, volume, cfg, what="verification view")
    plan: list[PreflightFinding] = []
    bad_anatomy = [f for f in shared + labels + sides if f.kind == "input"]
    if not bad_anatomy and distance is not None:
        plan = check_plan(case.plan, volume, side, case.cm_config, cfg, distance=distance)
    findings = shared + labels + sides + views + images + plan
    for f in findings:
        # the caller reports them (an input error, a refusal): logged here for the record only
        logger.info("preflight %s: %s", f.check, f.reason)
    return findings


class PreflightInputError(InputError):
    """Bad input found by the preflight (exit status 2); ``check`` names its first finding's check."""

    def __init__(self, source: str, problem: str, *, check: str) -> None:
        super().__init__(source, problem)
        self.check = check


def raise_for_input(findings: Sequence[PreflightFinding], source: str) -> None:
    """Raise the :class:`PreflightInputError` (an InputError: exit status 2) of the first ``"input"``
    finding, naming ``source`` (the case file) and how many more there are; nothing otherwise."""
    bad = [f for f in findings if f.kind == "input"]
    if not bad:
        return
    more = f" (and {len(bad) - 1} more input problem(s))" if len(bad) > 1 else ""
    raise PreflightInputError(source, bad[0].reason + more, check=bad[0].check)
