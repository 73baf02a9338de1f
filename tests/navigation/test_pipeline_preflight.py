"""navigate runs the preflight checks before any registration: a nonsense plan is refused (exit 3),
inconsistent labels are bad input (exit 2), and nothing is registered or commanded."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from fluoronav.navigation.case.model import write_navigation_case
from fluoronav.navigation.pipeline import NavigationConfig, navigate


def _plan_300_mm_inward(case):  # type: ignore[no-untyped-def]
    plan = case.plan
    far = dataclasses.replace(
        plan, entry_point_world_mm=plan.entry_point_world_mm + 300.0 * plan.direction_world
    )
    return dataclasses.replace(case, plan=far)


def test_a_plan_outside_the_femur_is_refused_before_any_registration(make_no_cm_case) -> None:
    events: list[tuple[str, str]] = []
    res = navigate(_plan_300_mm_inward(make_no_cm_case()), on_stage=lambda n, e: events.append((n, e)))
    assert res.status == "refused"
    assert res.reason.startswith("stage preflight, check target_in_femur: plan 'entry'")
    assert "outside the femur_left label" in res.reason
    assert events == [("preflight", "start"), ("preflight", "done")]
    assert res.first is None and res.joints_target_deg is None
    assert res.to_json()["stages"]["preflight"]["findings"][0]["check"] == "target_in_femur"


def test_without_preflight_the_same_plan_goes_on_to_detection(make_no_cm_case) -> None:
    res = navigate(_plan_300_mm_inward(make_no_cm_case()), NavigationConfig(preflight=None))
    assert res.status == "refused" and res.reason.startswith("stage detect")
    assert "preflight" not in res.stages


def test_navigate_command_exits_3_for_the_plan_and_2_for_swapped_labels(
    tmp_path: Path, make_no_cm_case
) -> None:
    case = make_no_cm_case(n_views=2, size=64)
    far = write_navigation_case(_plan_300_mm_inward(case), tmp_path / "far")
    proc = subprocess.run(
        [sys.executable, "-m", "fluoronav", "navigate", str(far), "--out", str(tmp_path / "o1")],
        capture_output=True,
        encoding="utf-8",
    )
    assert proc.returncode == 3, proc.stderr
    nav = json.loads((tmp_path / "o1" / "navigation.json").read_text(encoding="utf-8"))
    assert nav["status"] == "refused" and "plan 'entry'" in nav["reason"]
    assert "joints_target_deg" not in nav

    labels = np.asarray(case.volume.labels).copy()
    swapped = np.where(labels == 1, 2, np.where(labels == 2, 1, labels)).astype(labels.dtype)
    bad = dataclasses.replace(case, volume=dataclasses.replace(case.volume, labels=swapped))
    path = write_navigation_case(bad, tmp_path / "swapped")
    proc = subprocess.run(
        [sys.executable, "-m", "fluoronav", "navigate", str(path), "--out", str(tmp_path / "o2")],
        capture_output=True,
        encoding="utf-8",
    )
    assert proc.returncode == 2, proc.stderr
    errors = [line for line in proc.stderr.strip().splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and str(path) in errors[0] and "swapped" in errors[0]
    assert not (tmp_path / "o2" / "navigation.json").exists()
