"""Why a simulated navigation refused: the cause the simulation knows against the one the refusal named.

The simulation knows each refusal's cause (:func:`true_cause`): the injected fault
(:mod:`fluoronav.simulation.navigation.faults`), a hand-eye matrix further from the truth than its
stated uncertainty allows, or a wrong detection: a view of the refused set of images whose detected
landmarks lie more than :data:`WRONG_DETECTION_MM` from the true projected ones (another structure
found). The refusal names one by its check (:func:`named_cause`); :func:`named_right` says whether
the two agree. The navigation study's rows carry both and its summary the fraction named right.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np

from fluoronav.navigation.kinematic_prior import KinematicUncertainty
from fluoronav.simulation.navigation.faults import Fault, names_fault

__all__ = [
    "HANDEYE_FAULT_SIGMAS",
    "WRONG_DETECTION_MM",
    "NamedCause",
    "TrueCause",
    "detection_errors_mm",
    "named_cause",
    "named_right",
    "refusal_causes",
    "refused_at",
    "refused_view",
    "true_cause",
]

#: the causes the simulation knows (``none_known``: none of them)
TrueCause = Literal["wrong_detection", "hand_eye", "joint_readings", "image", "case_input", "none_known"]
#: the causes a refusal names (``cannot_tell``: the detection or the kinematics, one view cannot
#: say which; ``unnamed``: a registration's check or a command's bound, no cause)
NamedCause = Literal[
    "wrong_detection", "hand_eye_or_joints", "joint_readings", "cannot_tell", "image", "case_input", "unnamed"
]

#: a view whose detected landmarks lie further than this from the true projected ones (the larger
#: of A and B, mm at the detector) found something else than the CM's landmarks
WRONG_DETECTION_MM = 3.0
#: a hand-eye matrix further from the truth than this many of its stated σ
#: (:class:`~fluoronav.navigation.kinematic_prior.KinematicUncertainty`) is a fault
HANDEYE_FAULT_SIGMAS = 3.0

#: the checks that name each cause (a preflight refusal not listed names the case's inputs)
_NAMED: dict[str, NamedCause] = {
    "detection_disagrees": "wrong_detection",
    "kinematics_disagree": "hand_eye_or_joints",
    "joint_readings": "joint_readings",
    "detection_or_kinematics": "cannot_tell",
    "views_with_cm": "image",
    "mirrored": "image",
    "mirrored_images": "image",
    "intrinsics": "image",
    "inverted_image": "image",
    "identical_views": "image",
    "verification_repeats_views": "image",
    "fbg_shape": "case_input",
    "fbg_reading": "case_input",
    "ct_scale": "case_input",
    "odd_view": "image",
}


def detection_errors_mm(
    detected_px: Sequence[np.ndarray | None], true_px: Sequence[np.ndarray | None], spacing_mm: float
) -> list[float | None]:
    """Per view the larger distance of the detected landmarks A, B from the true projected ones (mm
    at the detector; pixels of the image, ``spacing_mm`` each); None where either is missing."""
    out: list[float | None] = []
    for d, t in zip(detected_px, true_px, strict=True):
        if d is None or t is None:
            out.append(None)
            continue
        out.append(
            float(np.linalg.norm(np.asarray(d, float) - np.asarray(t, float), axis=1).max() * spacing_mm)
        )
    return out


def _handeye_fault(handeye_error_mm: float, handeye_error_deg: float, u: KinematicUncertainty) -> bool:
    return (
        handeye_error_mm > HANDEYE_FAULT_SIGMAS * u.handeye_mm
        or handeye_error_deg > HANDEYE_FAULT_SIGMAS * u.handeye_deg
    )


def _fault_cause(fault: Fault) -> TrueCause | None:
    if fault.handeye_error_mm is not None:
        return "hand_eye"
    if fault.verify_joint_offset_deg is not None:
        return "joint_readings"
    if (
        fault.mirror
        or fault.invert
        or fault.focal_scale is not None
        or fault.without_cm
        or fault.other_patient
    ):
        return "image"
    if fault.verify_images_before_move:
        return "image"
    return "case_input" if fault.where == "case" else None


def true_cause(
    fault: Fault | None,
    *,
    handeye_error_mm: float,
    handeye_error_deg: float,
    detection_mm: Sequence[float | None],
    uncertainty: KinematicUncertainty | None = None,
) -> TrueCause:
    """The cause the simulation knows, first found of: the injected fault, a hand-eye matrix beyond
    :data:`HANDEYE_FAULT_SIGMAS` of its stated σ, a wrong detection in the refused set of images
    (``detection_mm``: :func:`detection_errors_mm`); ``none_known`` otherwise."""
    cause = None if fault is None else _fault_cause(fault)
    if cause is not None:
        return cause
    if _handeye_fault(handeye_error_mm, handeye_error_deg, uncertainty or KinematicUncertainty()):
        return "hand_eye"
    if any(d is not None and d > WRONG_DETECTION_MM for d in detection_mm):
        return "wrong_detection"
    return "none_known"


def named_cause(stage: str, check: str) -> NamedCause:
    """The cause a refusal at ``stage`` with ``check`` names (:data:`NamedCause`)."""
    if check in _NAMED:
        return _NAMED[check]
    return "case_input" if stage == "preflight" else "unnamed"


def named_right(true: str, named: str, fault: Fault | None, stage: str, check: str) -> bool | None:
    """Whether the refusal named the known cause: a fault of the images or the case's inputs where
    its check names that fault (:func:`~fluoronav.simulation.navigation.faults.names_fault`), a
    hand-eye matrix or joint readings where it names the kinematics (the joint readings' own check
    too), a wrong detection where it names the detection; None where no cause is known."""
    if true == "none_known":
        return None
    if true in ("image", "case_input") and fault is not None:
        return names_fault(fault, stage, check)
    if true == "hand_eye":
        return named == "hand_eye_or_joints"
    if true == "joint_readings":
        return named in ("hand_eye_or_joints", "joint_readings")
    return named == true


def _detected(case_views: Sequence[Any], detect_diag: Mapping[str, Any]) -> list[np.ndarray | None]:
    """Per case view the landmarks the pipeline used: the case's, else the detector's (its stage's
    diagnostics); None where none was found."""
    out: list[np.ndarray | None] = []
    for v in case_views:
        if v.landmarks_px is not None:
            out.append(np.asarray(v.landmarks_px, np.float64))
            continue
        d = detect_diag.get("views", {}).get(v.name, {})
        out.append(np.asarray(d["landmarks_px"], np.float64) if "landmarks_px" in d else None)
    return out


def refusal_causes(
    stage: str,
    check: str,
    *,
    fault: Fault | None,
    handeye_error_mm: float,
    handeye_error_deg: float,
    case_views: Sequence[Any],
    images: Sequence[Any],
    detect_diagnostics: Mapping[str, Any],
) -> dict[str, Any]:
    """A refusal's ``true_cause``, ``named_cause`` and ``cause_named_right`` (None where no cause is
    known), with ``wrong_detection_views`` (view → mm) of the refused set of images: ``case_views``
    (the case's views of that set), ``images`` (the simulated ones, in the same order) and
    ``detect_diagnostics`` (its detect stage's)."""
    spacing = float(images[0].camera.pixel_spacing_mm or math.nan) if images else math.nan
    errors = detection_errors_mm(
        _detected(case_views, detect_diagnostics), [im.landmarks_px for im in images], spacing
    )
    true = true_cause(
        fault, handeye_error_mm=handeye_error_mm, handeye_error_deg=handeye_error_deg, detection_mm=errors
    )
    named = named_cause(stage, check)
    return {
        "true_cause": true,
        "named_cause": named,
        "cause_named_right": named_right(true, named, fault, stage, check),
        "wrong_detection_views": {
            v.name: e
            for v, e in zip(case_views, errors, strict=True)
            if e is not None and e > WRONG_DETECTION_MM
        },
    }


def refused_at(reason: str) -> tuple[str, str]:
    """(stage, check) of a refusal's reason (``stage X[, view V], check C: detail``); ("", "") else."""
    stage = re.match(r"stage ([^,]+),", reason)
    check = re.search(r", check (\w+):", reason)
    return (stage.group(1) if stage else "", check.group(1) if check else "")


def refused_view(reason: str) -> str:
    """The view a refusal's reason names (``stage X, view V, check C: …``), its set's tag
    (`` (verification)``) off; "" where none."""
    m = re.match(r"stage [^,]+, view (.+?), check ", reason or "")
    return "" if m is None else m.group(1).split(" (")[0]
