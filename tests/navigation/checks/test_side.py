"""Which femur: the plan's (inferred from its path through the femur labels), the case's ``side`` and
the hip the views show.

The hip phantom at 2.5 mm; two views centred on the left femoral head (AP and an orbit of 20°), in
which the right femoral head (168 mm away) lies outside the image. A plan on the right femur with
``side`` "left" is named as such; with no ``side`` the right femur is inferred, recorded (a note)
and named as missing from the views; the clean case (the left plan) gives no finding.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.geometry.carm import carm_camera, orbit_camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.robot import UR10
from fluoronav.navigation.case.model import NavigationCase, load_navigation_case, write_navigation_case
from fluoronav.navigation.case.view import CaseView
from fluoronav.navigation.checks.preflight import (
    PreflightConfig,
    PreflightInputError,
    preflight,
    raise_for_input,
)
from fluoronav.navigation.checks.side import check_side, views_showing
from fluoronav.navigation.pipeline import navigate
from fluoronav.navigation.planning import Plan, neck_entry_plan, plan_side


@pytest.fixture(scope="module")
def volume() -> Volume:
    return hip_phantom(seed=0, spacing_mm=2.5, texture=False)


def _plan(volume: Volume, side: str) -> Plan:
    lm = volume.landmarks_world
    return neck_entry_plan(lm[f"entry_{side}"], lm[f"femoral_head_{side}"])


def _case(volume: Volume, plan_side_: str, side: str, inferred: str | None = None) -> NavigationCase:
    head = volume.landmarks_world["femoral_head_left"]
    ap = carm_camera(isocenter_world=head).downsample(12)
    cams = (ap, orbit_camera(ap, angle_deg=20.0, isocenter_world=head))
    rng = np.random.default_rng(0)  # images of noise: the side checks need only the cameras
    views = tuple(
        CaseView(name, rng.random((c.rows, c.cols), dtype=np.float32), c)
        for name, c in zip(("AP", "orbit"), cams, strict=True)
    )
    return NavigationCase(
        volume=volume,
        plan=_plan(volume, plan_side_),
        side=side,
        cm_config=CMConfig(),
        fbg_control_points_deg=None,
        robot=UR10,
        joints_deg=np.zeros(6),
        ee_from_cm=np.eye(4),
        views=views,
        side_inferred_from=inferred,
    )


def test_the_plans_side_is_told_by_its_path_through_the_femur_labels(volume: Volume) -> None:
    for side in ("left", "right"):
        found = plan_side(_plan(volume, side), volume)
        assert found.side == side and found.by_label and f"femur_{side} label" in found.how
    # without labels: the femoral head nearest the entry
    found = plan_side(_plan(volume, "right"), dataclasses.replace(volume, labels=None))
    assert found.side == "right" and not found.by_label and "femoral_head_right" in found.how


def test_the_views_show_the_left_hip_only(volume: Volume) -> None:
    case = _case(volume, "left", "left")
    lm = volume.landmarks_world
    assert views_showing(case.views, lm["femoral_head_left"]) == ["AP", "orbit"]
    assert views_showing(case.views, lm["femoral_head_right"]) == []


def test_the_clean_case_gives_no_side_finding(volume: Volume) -> None:
    assert check_side(_case(volume, "left", "left")) == []


def test_a_plan_on_the_other_femur_than_side_is_named(volume: Volume) -> None:
    case = _case(volume, "right", "left")
    (f,) = check_side(case)
    assert f.kind == "input" and f.check == "plan_side" and f.subject == "plan 'entry'"
    assert "is on the right femur" in f.reason and "'side' is 'left'" in f.reason
    findings = preflight(case, PreflightConfig())
    assert [g.check for g in findings if g.kind != "note"] == ["plan_side"]  # the plan is not checked
    with pytest.raises(PreflightInputError, match=r"case\.json: plan 'entry' is on the right femur"):
        raise_for_input(findings, "case.json")


def test_without_side_the_plans_femur_is_used_recorded_and_named_when_no_view_shows_it(
    volume: Volume,
) -> None:
    case = _case(volume, "right", "right", inferred="its path runs through the femur_right label")
    note, f = check_side(case)
    assert note.kind == "note" and note.check == "side_inferred" and "the right femur" in note.reason
    assert f.kind == "input" and f.check == "femur_in_views"
    assert "is on the right femur (inferred from the plan)" in f.reason
    assert "femoral_head_left landmark into view 'AP'" in f.reason
    # the plan on the femur the views show: the note only, which refuses nothing
    case = _case(volume, "left", "left", inferred="its path runs through the femur_left label")
    findings = preflight(case, PreflightConfig())
    assert [g.check for g in findings] == ["side_inferred"]
    raise_for_input(findings, "case.json")


def test_a_case_file_without_side_takes_the_plans_femur(tmp_path: Path, volume: Volume) -> None:
    path = write_navigation_case(_case(volume, "right", "right"), tmp_path)
    d = json.loads(path.read_text(encoding="utf-8"))
    del d["side"]
    path.write_text(json.dumps(d), encoding="utf-8")
    case = load_navigation_case(path)
    assert case.side == "right" and case.side_inferred_from == "its path runs through the femur_right label"
    assert [f.check for f in check_side(case)] == ["side_inferred", "femur_in_views"]


def test_navigate_records_the_inferred_side_with_the_preflight(make_no_cm_case) -> None:
    """The note is recorded in navigation.json's preflight stage and refuses nothing: the run goes on
    to the plan check, which refuses a target 300 mm inward."""
    case = make_no_cm_case(n_views=2, size=64)
    plan = case.plan
    far = dataclasses.replace(
        plan, entry_point_world_mm=plan.entry_point_world_mm + 300.0 * plan.direction_world
    )
    case = dataclasses.replace(
        case, plan=far, side_inferred_from="the femoral_head_left landmark is the nearest"
    )
    res = navigate(case)
    assert res.status == "refused" and "check target_in_femur" in res.reason
    found = res.to_json()["stages"]["preflight"]["findings"]
    assert [f["check"] for f in found][:2] == ["side_inferred", "target_in_femur"]
    assert found[0]["kind"] == "note" and "the left femur, inferred from the plan" in found[0]["reason"]
