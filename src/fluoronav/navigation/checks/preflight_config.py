"""The pre-registration checks' thresholds and what a failed check reports.

:class:`PreflightConfig` holds every threshold of :mod:`fluoronav.navigation.checks.preflight` (the plan
and the labels) and :mod:`fluoronav.navigation.checks.preflight_images` (the images and cameras);
:class:`PreflightFinding` is one failed check, its ``kind`` saying how the navigation ends
(``"input"``: bad input, exit status 2; ``"plan"``: a refusal, exit status 3; ``"note"``: recorded,
nothing refused).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from fluoronav.settings import setting

__all__ = [
    "FindingKind",
    "PreflightConfig",
    "PreflightFinding",
    "finding",
]

#: how a finding ends the navigation: ``"input"`` exit 2, ``"plan"`` a refusal (exit 3), ``"note"`` not
FindingKind = Literal["plan", "input", "note"]


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
        fbg_margin_deg: an FBG control point may exceed the angle at which the CM's notches close
            (``CMConfig.max_bend_deg``) by at most this, or by 3 of the case's ``fbg_sigma_deg``
            where that is more: the reading's error. Beyond it no CM of that config bends so far (a
            reading in another unit, or of another CM).
        ct_spacing_mm: plausible (low, high) voxel spacing of a pelvis CT along each axis: thin-slice
            reconstructions reach ~0.3 mm, thick slices 5 mm. A spacing in cm reads 10× too small.
        ct_extent_mm: plausible (low, high) extent of the CT along each axis: a femoral head with its
            socket spans ~60 mm, a whole-body scan ~2 m.
        bone_ball_radius_mm: plausible (low, high) radius of the largest ball inside the ``pelvis``
            and ``femur_<side>`` labels: the femoral head's (adults 18–30 mm). A CT whose spacing is
            off by a factor scales it by that factor, the label volumes by its cube.
        bone_min_median_hu: a bone label whose median HU is below this does not look like bone:
            cancellous bone is ~150–400 HU and the cortex ~1000–2000 HU, muscle ~40, fat ~−100.
            Labels on soft tissue, or a CT whose values are not HU (μ, a normalised image).
        contrast_voxel_mm: the label-fit check samples the CT and the labels every this many mm
            (every k-th voxel along each axis, k the nearest whole number, at least 1).
        min_bone_contrast: each of the ``pelvis`` and ``femur_<side>`` labels must sit on the CT's
            bone: its bone contrast, (median HU of its outermost layer of sampled voxels − median HU
            of the layer just outside it, other labels left out) over (its 95th percentile HU − that
            outside median), must reach this; the best of the label as given and one sampled voxel
            larger or smaller (a boundary drawn a voxel off). The figures that set it:
            docs/validation.md.
        mirror_margin: the label map mirrored left–right (its array flipped along the axis nearest
            the world's x) must not fit the bone better than as given by this much: the worst
            label's mean contrast (the layers' means of HU clipped to [outside median, 95th
            percentile]), which falls with every part of the surface off the bone. Both maps share
            the segmentation's quality; a correct pair fits worse mirrored (or as well, for a
            symmetric anatomy).
    """

    target_margin_mm: float = setting(
        3.0, "the plan's tip target at most this far outside the femur label", unit="mm", ge=0
    )
    entry_surface_max_mm: float = setting(
        5.0, "the plan's entry point within this of the femur label's surface", unit="mm", gt=0
    )
    direction_probe_mm: float = setting(
        10.0,
        "this far along the insertion direction from the entry must be inside the femur",
        unit="mm",
        gt=0,
    )
    max_insertion_depth_mm: float | None = setting(
        None, "a site's limit on the plan's insertion depth; none: the CM's reach", unit="mm", gt=0
    )
    landmark_margin_mm: float = setting(
        2.0, "the femoral-head landmark at most this far outside the femur label", unit="mm", ge=0
    )
    pelvis_volume_ml: tuple[float, float] = setting(
        (100.0, 3000.0), "plausible (low, high) volume of the pelvis label", unit="mL", ge=0
    )
    femur_volume_ml: tuple[float, float] = setting(
        (25.0, 1500.0), "plausible (low, high) volume of the femur label", unit="mL", ge=0
    )
    sdd_mm: tuple[float, float] = setting(
        (600.0, 1600.0), "plausible (low, high) source-to-detector distance", unit="mm", gt=0
    )
    pixel_spacing_mm: tuple[float, float] = setting(
        (0.05, 10.0), "plausible (low, high) pixel spacing at the stored resolution", unit="mm", gt=0
    )
    detector_span: tuple[float, float] = setting(
        (0.05, 0.8), "plausible (low, high) detector width over the source-to-detector distance", gt=0
    )
    max_focal_aspect: float = setting(1.05, "largest ratio of fx and fy (C-arm pixels are square)", ge=1)
    identical_ncc: float = setting(
        0.9999, "two images whose correlation reaches this are one image given twice", ge=-1, le=1
    )
    drr_size_px: int = setting(
        64, "the inversion check's DRR size along the image's longer side", unit="px", ge=1
    )
    drr_voxel_mm: float = setting(4.0, "the CT's voxel size for that DRR", unit="mm", gt=0)
    inverted_ncc: float = setting(
        -0.5, "an image correlating with that DRR below this is taken as inverted", ge=-1, le=1
    )
    mirrored_ncc: float = setting(
        0.5, "an image whose mirror correlates with that DRR this well looks mirrored", ge=-1, le=1
    )
    fbg_margin_deg: float = setting(
        0.5, "an FBG control point at most this beyond the angle at which a notch closes", unit="deg", ge=0
    )
    ct_spacing_mm: tuple[float, float] = setting(
        (0.2, 5.0), "plausible (low, high) voxel spacing of a pelvis CT, each axis", unit="mm", gt=0
    )
    ct_extent_mm: tuple[float, float] = setting(
        (50.0, 2500.0), "plausible (low, high) extent of a pelvis CT, each axis", unit="mm", gt=0
    )
    bone_ball_radius_mm: tuple[float, float] = setting(
        (14.0, 36.0),
        "plausible (low, high) radius of the largest ball inside the bone labels",
        unit="mm",
        gt=0,
    )
    bone_min_median_hu: float = setting(100.0, "a bone label's median HU at least this", unit="HU")
    contrast_voxel_mm: float = setting(
        2.0, "the label-fit check samples the CT about this often", unit="mm", gt=0
    )
    min_bone_contrast: float = setting(
        0.65, "each of the pelvis and femur labels sits on bone at least this well", ge=-1, le=1
    )
    mirror_margin: float = setting(
        0.15, "the labels mirrored left–right fit the bone at most this much better", ge=0
    )


@dataclass(frozen=True)
class PreflightFinding:
    """One failed check (or a note).

    Attributes:
        kind: ``"plan"`` (the plan is refused, exit status 3), ``"input"`` (bad input, exit 2) or
            ``"note"`` (recorded with the preflight, nothing refused: e.g. the side inferred).
        subject: what it is about: ``"plan 'entry'"``, ``"label 'femur_left'"``,
            ``"landmark 'femoral_head_left'"``, ``"view 'AP'"``, ``"verification view 'AP'"``.
        reason: one line that names the subject, says what is wrong and what to check.
        check: a short name of the check (``"target_in_femur"``, ``"identical_views"``, …).
    """

    kind: FindingKind
    subject: str
    reason: str
    check: str


def finding(kind: FindingKind, subject: str, text: str, check: str) -> PreflightFinding:
    """A finding whose reason is ``subject`` followed by ``text``, its whitespace runs made single
    spaces (one line)."""
    return PreflightFinding(kind, subject, " ".join(f"{subject}{text}".split()), check)
