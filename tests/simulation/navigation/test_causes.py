"""A simulated refusal's cause as the simulation knows it, against the one its check names."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from fluoronav.simulation.navigation.causes import (
    WRONG_DETECTION_MM,
    detection_errors_mm,
    named_cause,
    named_right,
    refusal_causes,
    refused_at,
    true_cause,
)
from fluoronav.simulation.navigation.faults import FAULTS

#: the detector's pixel pitch of a 768² image of the 1536² detector, mm
SPACING_MM = 0.388
TRUE_PX = np.array([[100.0, 120.0], [160.0, 130.0]])


def _set(off_px: list[float], *, given: bool = True) -> tuple[list[SimpleNamespace], list[SimpleNamespace]]:
    """Case views and simulated images of one set: view k's landmarks ``off_px[k]`` pixels along u
    from the truth (given by the case, or left to the detector where not ``given``)."""
    views, images = [], []
    for k, off in enumerate(off_px):
        lm = TRUE_PX + np.array([off, 0.0])
        views.append(SimpleNamespace(name=f"view{k}", landmarks_px=lm if given else None))
        images.append(
            SimpleNamespace(landmarks_px=TRUE_PX, camera=SimpleNamespace(pixel_spacing_mm=SPACING_MM))
        )
    return views, images


def test_a_view_whose_landmarks_are_a_few_mm_off_is_a_wrong_detection() -> None:
    errors = detection_errors_mm(
        [TRUE_PX + 1.0, TRUE_PX + np.array([30.0, 0.0]), None], [TRUE_PX] * 3, SPACING_MM
    )
    assert errors[0] == pytest.approx(np.sqrt(2.0) * SPACING_MM) and errors[2] is None
    assert errors[1] == pytest.approx(30.0 * SPACING_MM) and errors[1] > WRONG_DETECTION_MM
    kw = dict(handeye_error_mm=0.5, handeye_error_deg=0.4)
    assert true_cause(None, detection_mm=errors, **kw) == "wrong_detection"
    assert true_cause(None, detection_mm=errors[:1], **kw) == "none_known"
    # an injected fault, or a hand-eye matrix beyond three of its stated σ, comes first
    assert true_cause(FAULTS["handeye_10mm"], detection_mm=errors, **kw) == "hand_eye"
    assert true_cause(None, detection_mm=errors, handeye_error_mm=10.0, handeye_error_deg=0.4) == "hand_eye"
    assert true_cause(FAULTS["verify_joints_3deg"], detection_mm=[], **kw) == "joint_readings"
    assert true_cause(FAULTS["mirror_one"], detection_mm=[], **kw) == "image"
    assert true_cause(FAULTS["verify_no_move"], detection_mm=[], **kw) == "image"
    assert true_cause(FAULTS["labels_swapped"], detection_mm=[], **kw) == "case_input"
    assert true_cause(FAULTS["none"], detection_mm=[], **kw) == "none_known"


@pytest.mark.parametrize(
    ("stage", "check", "named"),
    [
        ("verify_cm", "detection_disagrees", "wrong_detection"),
        ("verify_cm", "kinematics_disagree", "hand_eye_or_joints"),
        ("correct", "kinematics_disagree", "hand_eye_or_joints"),
        ("correct", "detection_or_kinematics", "cannot_tell"),
        ("verify_joints", "joint_readings", "joint_readings"),
        ("preflight", "mirrored_images", "image"),
        ("preflight", "target_in_femur", "case_input"),
        ("verify_cm", "edge_ncc", "unnamed"),
        ("correct", "correction_length", "unnamed"),
    ],
)
def test_each_check_names_its_cause(stage: str, check: str, named: str) -> None:
    assert named_cause(stage, check) == named


def test_named_right_matches_the_known_cause() -> None:
    assert named_right("wrong_detection", "wrong_detection", None, "verify_cm", "detection_disagrees")
    assert not named_right("wrong_detection", "hand_eye_or_joints", None, "verify_cm", "kinematics_disagree")
    assert named_right(
        "hand_eye", "hand_eye_or_joints", FAULTS["handeye_10mm"], "correct", "kinematics_disagree"
    )
    assert not named_right("hand_eye", "cannot_tell", None, "correct", "detection_or_kinematics")
    assert named_right("joint_readings", "joint_readings", None, "verify_joints", "joint_readings")
    # a fault of the images is named where its own checks name it
    assert named_right(
        "image", "hand_eye_or_joints", FAULTS["verify_no_move"], "correct", "kinematics_disagree"
    )
    assert not named_right("image", "unnamed", FAULTS["mirror_one"], "cm", "edge_ncc")
    assert named_right("none_known", "unnamed", None, "cm", "edge_ncc") is None


def test_a_refused_verification_with_a_detection_off_records_both_causes() -> None:
    views, images = _set([0.0, 40.0, 1.0])
    causes = refusal_causes(
        "verify_cm",
        "kinematics_disagree",
        fault=None,
        handeye_error_mm=0.5,
        handeye_error_deg=0.4,
        case_views=views,
        images=images,
        detect_diagnostics={},
    )
    assert causes["true_cause"] == "wrong_detection" and causes["named_cause"] == "hand_eye_or_joints"
    assert causes["cause_named_right"] is False
    assert causes["wrong_detection_views"] == {"view1": pytest.approx(40.0 * SPACING_MM)}


def test_the_detectors_landmarks_are_read_from_the_detect_stage() -> None:
    views, images = _set([0.0, 0.0], given=False)
    diag = {
        "views": {
            "view0": {"found": False},
            "view1": {"landmarks_px": (TRUE_PX + np.array([0.0, 25.0])).tolist()},
        }
    }
    causes = refusal_causes(
        "verify_cm",
        "detection_disagrees",
        fault=None,
        handeye_error_mm=0.5,
        handeye_error_deg=0.4,
        case_views=views,
        images=images,
        detect_diagnostics=diag,
    )
    assert causes["true_cause"] == "wrong_detection" and causes["cause_named_right"] is True
    assert list(causes["wrong_detection_views"]) == ["view1"]


def test_a_refusals_stage_and_check_are_read_from_its_reason() -> None:
    assert refused_at("stage verify_cm, view AP (verify), B (verify), check detection_disagrees: …") == (
        "verify_cm",
        "detection_disagrees",
    )
    assert refused_at("stage correct, check kinematics_disagree: the CM …") == (
        "correct",
        "kinematics_disagree",
    )
    assert refused_at("") == ("", "")


def test_the_refused_view_is_read_off_the_reason_without_its_sets_tag() -> None:
    from fluoronav.simulation.navigation.causes import refused_view

    assert refused_view("stage cm, view orbit +20, check odd_view: 3.1 mm") == "orbit +20"
    assert refused_view("stage cm, view AP (verification), check edge_ncc: NCC 0.4") == "AP"
    assert refused_view("stage cm, check fbg_reading: -3.4°") == ""
