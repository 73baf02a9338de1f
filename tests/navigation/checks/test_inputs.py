"""The preflight's checks of the inputs every view shares: the FBG reading's range, the CT's spacing
and extent, the bone labels' size and HU.

The CT: the hip phantom at 2.5 mm (the preflight tests' spacing). A spacing fault rescales the grid
about the world origin (the phantom's centre) and leaves the landmarks where they were, as a CT
header with the wrong spacing does; each fault must be named by its own check, first among the
findings (the one a user sees), and the clean inputs must give none.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.robot import UR10
from fluoronav.navigation.case.model import NavigationCase
from fluoronav.navigation.case.view import CaseView
from fluoronav.navigation.checks.inputs import (
    check_bone_hu,
    check_bone_size,
    check_ct_geometry,
    check_fbg,
    fbg_limit_deg,
)
from fluoronav.navigation.checks.label_fit import label_depth_mm, sample_ct
from fluoronav.navigation.checks.preflight import (
    PreflightConfig,
    PreflightFinding,
    PreflightInputError,
    preflight,
    raise_for_input,
)
from fluoronav.navigation.planning import neck_entry_plan

CFG = PreflightConfig()


@pytest.fixture(scope="module")
def volume() -> Volume:
    return hip_phantom(seed=0, spacing_mm=2.5, texture=False)


def _case(volume: Volume, fbg: np.ndarray | None = None) -> NavigationCase:
    """A case without views: the shared inputs' checks need none."""
    lm = volume.landmarks_world
    camera = Camera(4, 4, np.array([[20.0, 0.0, 1.5], [0.0, 20.0, 1.5], [0.0, 0.0, 1.0]]), np.eye(4))
    image = CaseView("AP", np.zeros((4, 4), np.float32), camera)
    return NavigationCase(
        volume=volume,
        plan=neck_entry_plan(lm["entry_left"], lm["femoral_head_left"]),
        side="left",
        cm_config=CMConfig(),
        fbg_control_points_deg=fbg,
        robot=UR10,
        joints_deg=np.zeros(6),
        ee_from_cm=np.eye(4),
        views=(image,),
    )


def _first(findings: list[PreflightFinding]) -> PreflightFinding:
    bad = [f for f in findings if f.kind == "input"]
    assert bad, findings
    assert "\n" not in bad[0].reason and bad[0].reason.startswith(bad[0].subject)
    return bad[0]


def _rescaled(volume: Volume, factor: float) -> Volume:
    """The CT with its voxel spacing × ``factor`` (about the world origin); landmarks unchanged."""
    return volume.replace(
        spacing_mm=tuple(s * factor for s in volume.spacing_mm),
        origin_mm=tuple(o * factor for o in volume.origin_mm),
    )


def _shared(case: NavigationCase) -> list[PreflightFinding]:
    """The preflight's findings without its image checks (no DRR): the label and side checks."""
    return [f for f in preflight(case, CFG) if f.check not in ("inverted_image", "intrinsics")]


# ----- the FBG reading --------------------------------------------------------------------------
def test_an_fbg_reading_beyond_the_cms_bend_is_named_with_its_field() -> None:
    cm = CMConfig()
    limit = fbg_limit_deg(cm, None, CFG)
    assert limit == pytest.approx(cm.max_bend_deg + CFG.fbg_margin_deg)  # 8.84° + 0.5°
    findings = check_fbg([0.0, 12.0, 0.0, 0.0, 0.0], cm, None, CFG)
    f = _first(findings)
    assert f.check == "fbg_range" and f.subject == "fbg_control_points_deg[1]"
    assert "12°" in f.reason and "notches close" in f.reason
    with pytest.raises(PreflightInputError, match=r"case\.json: fbg_control_points_deg\[1\] = 12°"):
        raise_for_input(findings, "case.json")


def test_fbg_readings_within_the_bend_and_its_error_pass() -> None:
    cm = CMConfig()
    # the ideal world's readings: the CM's range ±7.9° with ±0.5° error
    assert check_fbg([8.4, -8.4, 7.9, -7.9, 0.0], cm, None, CFG) == []
    assert check_fbg(None, cm, None, CFG) == []
    # a stated σ of 0.5° allows 3 σ beyond the bend
    assert check_fbg([cm.max_bend_deg + 1.4, 0, 0, 0, 0], cm, 0.5, CFG) == []
    assert check_fbg([cm.max_bend_deg + 1.6, 0, 0, 0, 0], cm, 0.5, CFG) != []


# ----- the CT's spacing, extent and scale -------------------------------------------------------
def test_the_clean_ct_passes_its_geometry_checks(volume: Volume) -> None:
    assert check_ct_geometry(volume, CFG) == []
    s = sample_ct(volume, CFG.contrast_voxel_mm)
    depth = label_depth_mm(s, 2)
    assert depth is not None and 19.0 < depth < 24.0  # the femoral head, r = 23.5 mm
    assert check_bone_size(volume, depth, "femur_left", CFG) == []


@pytest.mark.parametrize(
    ("factor", "check", "words"),
    [
        (0.1, "ct_extent", "spacing looks like cm"),  # 0.25 mm, but the CT spans 34 mm
        (10.0, "ct_spacing", "spacing looks 10× too large"),
        (2.0, "ct_scale", "looks about 1.8× too large"),
    ],
)
def test_a_ct_spacing_off_by_a_factor_is_named_first(
    volume: Volume, factor: float, check: str, words: str
) -> None:
    f = _first(_shared(_case(_rescaled(volume, factor))))
    assert f.check == check and f.subject == "'ct'", f
    assert words in f.reason and "spacing" in f.reason


def test_a_spacing_in_cm_at_1_mm_is_named_by_the_spacing() -> None:
    vol = Volume(np.zeros((300, 250, 350), np.float32), (0.1, 0.1, 0.1), (0.0, 0.0, 0.0))
    (f,) = check_ct_geometry(vol, CFG)
    assert f.check == "ct_spacing" and "spacing looks like cm: give it in mm" in f.reason


def test_swapped_labels_leave_the_scale_check_quiet(volume: Volume) -> None:
    """The largest ball is the deeper of the pelvis's and the femur's: a swap changes nothing, and the
    landmark check names the swap."""
    assert volume.labels is not None
    labels = volume.labels.copy()
    labels[volume.labels == 1], labels[volume.labels == 2] = 2, 1
    findings = _shared(_case(volume.replace(labels=labels)))
    assert _first(findings).check == "landmark_in_femur" and "swapped" in _first(findings).reason
    assert "ct_scale" not in [f.check for f in findings]


# ----- the labels' HU ----------------------------------------------------------------------------
def test_labels_that_are_not_bone_are_named(volume: Volume) -> None:
    s = sample_ct(volume, CFG.contrast_voxel_mm)
    names = {"pelvis": 1, "femur_left": 2}
    assert check_bone_hu(s.hu, s.labels, names, CFG) == []
    # a CT in attenuation (1/mm), not HU
    findings = _shared(_case(volume.replace(data=(volume.data + 1000.0) * 2e-5)))
    f = _first(findings)
    assert f.check == "label_hu" and f.subject == "label 'pelvis'" and "not HU" in f.reason
    # labels on soft tissue: every bone voxel set to muscle
    assert volume.labels is not None
    muscle = np.where(volume.labels > 0, 40.0, volume.data).astype(np.float32)
    soft = dataclasses.replace(volume, data=muscle)
    assert _first(_shared(_case(soft))).check == "label_hu"
