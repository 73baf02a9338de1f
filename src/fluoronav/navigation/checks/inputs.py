"""Pre-registration checks of the inputs every view shares, each against its plausible range.

The FBG reading against the CM's bending range, the CT's voxel spacing and extent against a pelvis
CT's, the femur label's size against an adult femoral head's (a spacing off by a factor scales it),
and each bone label's HU content against bone's. A wrong shared input otherwise reaches a view's
check, which then blames one view. All findings are of kind ``"input"`` (bad input, exit status 2);
:func:`~fluoronav.navigation.checks.preflight.preflight` runs them first. Thresholds:
:class:`~fluoronav.navigation.checks.preflight_config.PreflightConfig`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fluoronav.anatomy.volume import Volume
from fluoronav.manipulator.config import CMConfig
from fluoronav.navigation.checks.preflight_config import PreflightConfig, PreflightFinding, finding

__all__ = [
    "check_bone_hu",
    "check_bone_size",
    "check_ct_geometry",
    "check_fbg",
    "fbg_limit_deg",
]

#: an adult femoral head's typical radius, mm (for the scale a wrong spacing looks like)
_TYPICAL_HEAD_RADIUS_MM = 23.0


def _bend_limit_deg(cm_config: CMConfig) -> float:
    """The CM's bending limit, degrees: the angle at which its notches close
    (``CMConfig.max_bend_deg``), or its configured control-point range where that is wider."""
    return max(float(cm_config.max_bend_deg), *(abs(float(v)) for v in cm_config.control_point_range_deg))


def fbg_limit_deg(cm_config: CMConfig, fbg_sigma_deg: float | None, config: PreflightConfig) -> float:
    """The largest magnitude an FBG control point may read, degrees: the joint angle at which the
    CM's notches close (or its configured range, where wider) plus the reading's error (the larger of
    ``fbg_margin_deg`` and 3 ``fbg_sigma_deg``)."""
    physical = _bend_limit_deg(cm_config)
    margin = float(config.fbg_margin_deg)
    if fbg_sigma_deg is not None:
        margin = max(margin, 3.0 * float(fbg_sigma_deg))
    return physical + margin


def check_fbg(
    reading_deg: Sequence[float] | np.ndarray | None,
    cm_config: CMConfig,
    fbg_sigma_deg: float | None = None,
    config: PreflightConfig | None = None,
) -> list[PreflightFinding]:
    """The case's FBG reading (``fbg_control_points_deg``) within the CM's physical range
    (:func:`fbg_limit_deg`); no reading, no finding."""
    if reading_deg is None:
        return []
    cfg = config or PreflightConfig()
    limit = fbg_limit_deg(cm_config, fbg_sigma_deg, cfg)
    cp = np.asarray(reading_deg, np.float64)
    bad = np.flatnonzero(~(np.abs(cp) <= limit))
    if bad.size == 0:
        return []
    k = int(bad[0])
    text = (
        f" = {cp[k]:g}° is beyond what the CM can bend (±{_bend_limit_deg(cm_config):.2f}°, where its "
        f"notches close; at most ±{limit:.2f}° with the reading's error): check the reading's unit "
        "(degrees) and that it is this CM's shape (fbg_margin_deg)"
    )
    return [finding("input", f"fbg_control_points_deg[{k}]", text, "fbg_range")]


def _spacing_text(volume: Volume) -> str:
    return " × ".join(f"{s:g}" for s in volume.spacing_mm) + " mm"


def check_ct_geometry(volume: Volume, config: PreflightConfig | None = None) -> list[PreflightFinding]:
    """The CT's voxel spacing and extent against a pelvis CT's (``ct_spacing_mm``, ``ct_extent_mm``)."""
    cfg = config or PreflightConfig()
    spacing = np.asarray(volume.spacing_mm, np.float64)
    extent = spacing * np.asarray(volume.shape_xyz, np.float64)
    lo, hi = cfg.ct_spacing_mm
    if not np.all((spacing >= lo) & (spacing <= hi)):
        text = (
            f": voxel spacing {_spacing_text(volume)} is implausible for a pelvis CT ({lo:g}–{hi:g} mm "
            f"per axis): {_unit_hint(spacing, lo, hi)}"
        )
        return [finding("input", "'ct'", text, "ct_spacing")]
    lo, hi = cfg.ct_extent_mm
    if not np.all((extent >= lo) & (extent <= hi)):
        small = bool(np.any(extent < lo))
        what = "too small to hold a pelvis" if small else "larger than any CT"
        hint = "spacing looks like cm (or 10× too small)" if small else "spacing looks too large"
        text = (
            f": spans {' × '.join(f'{e:.0f}' for e in extent)} mm, {what} ({lo:g}–{hi:g} mm per axis): "
            f"{hint}: check the voxel spacing ({_spacing_text(volume)}) and its units (mm)"
        )
        return [finding("input", "'ct'", text, "ct_extent")]
    return []


def check_bone_size(
    volume: Volume, ball_radius_mm: float, ball_label: str, config: PreflightConfig | None = None
) -> list[PreflightFinding]:
    """The bone labels' size against an adult's (``bone_ball_radius_mm``): a CT whose voxel spacing
    is off by a factor scales them by it.

    Args:
        volume: the CT (for its spacing, in the message).
        ball_radius_mm: the radius of the largest ball inside the pelvis and femur labels (a femoral
            head's; the larger of the two, so that swapped labels change nothing), mm.
        ball_label: the label that holds that ball.
        config: thresholds (default :class:`PreflightConfig`).
    """
    cfg = config or PreflightConfig()
    lo, hi = cfg.bone_ball_radius_mm
    r = float(ball_radius_mm)
    if lo <= r <= hi:
        return []
    factor = r / _TYPICAL_HEAD_RADIUS_MM
    how = f"{factor:.2g}× too large" if factor > 1.0 else f"{1.0 / factor:.2g}× too small"
    text = (
        f": the largest ball inside the {ball_label} label has a radius of {r:.1f} mm (an adult femoral "
        f"head's is 18–30 mm; plausible {lo:g}–{hi:g} mm): the CT's voxel spacing "
        f"({_spacing_text(volume)}) looks about {how}: check the spacing and its units (mm), and that "
        "the labels are filled"
    )
    return [finding("input", "'ct'", text, "ct_scale")]


def _unit_hint(spacing: np.ndarray, lo: float, hi: float) -> str:
    """What a spacing outside ``lo``–``hi`` mm looks like."""
    if np.all(spacing < lo) and np.all((spacing * 10.0 >= lo) & (spacing * 10.0 <= hi)):
        return "spacing looks like cm: give it in mm (× 10)"
    if np.all(spacing > hi) and np.all((spacing / 10.0 >= lo) & (spacing / 10.0 <= hi)):
        return "spacing looks 10× too large: check the spacing and its units (mm)"
    return "check the spacing and its units (mm)"


def check_bone_hu(
    hu: np.ndarray,
    labels: np.ndarray,
    names: dict[str, int],
    config: PreflightConfig | None = None,
) -> list[PreflightFinding]:
    """Each bone label's median HU against bone's (``bone_min_median_hu``).

    Args:
        hu: the CT's HU, sampled (any grid that ``labels`` shares: the label-fit check's).
        labels: the label values on that grid.
        names: the labels checked, name → value.
        config: thresholds (default :class:`PreflightConfig`).
    """
    cfg = config or PreflightConfig()
    out = []
    for name, value in names.items():
        inside = hu[labels == value]
        if inside.size == 0:
            continue
        median = float(np.median(inside))
        if median < cfg.bone_min_median_hu:
            text = (
                f"'s median HU is {median:.0f}, far below bone's (at least {cfg.bone_min_median_hu:g}; "
                "cancellous bone ~150–400, cortex ~1000–2000, muscle ~40): labels of soft tissue, or a "
                "CT whose values are not HU (rescale slope and intercept?)"
            )
            out.append(finding("input", f"label {name!r}", text, "label_hu"))
    return out
