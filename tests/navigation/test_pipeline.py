"""The navigate pipeline's contract on small cases: refusals, exit statuses, outputs.

The whole pipeline on a simulated case (registration accuracy, the robot command, the Slicer files)
is tested end to end in test_demo.py (slow).
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import fluoronav.navigation.pipeline as pipeline
from fluoronav.errors import RegistrationRefused
from fluoronav.navigation.case import write_navigation_case
from fluoronav.navigation.pipeline import NavigationConfig, NavigationRefused, _band_mask, _refusals, navigate
from fluoronav.navigation.result import navigation_cm_config


def test_no_cm_in_the_views_refuses_at_detection_without_a_command(make_no_cm_case) -> None:
    events: list[tuple[str, str]] = []
    res = navigate(make_no_cm_case(), NavigationConfig(), on_stage=lambda n, e: events.append((n, e)))
    assert res.status == "refused"
    assert res.reason.startswith("stage detect, view view0, view1, view2, check views_with_cm:")
    assert res.joints_target_deg is None and res.rbase_from_ee_target is None
    assert res.stages["detect"].passed is False
    assert res.stages["detect"].diagnostics["views_detected"] == 0
    assert events == [("detect", "start"), ("detect", "done")]
    d = res.to_json()
    assert d["status"] == "refused" and "joints_target_deg" not in d and "rbase_from_ee_target" not in d


def test_given_landmarks_skip_the_detector_and_make_a_band_mask() -> None:
    mask = _band_mask((40, 60), np.array([[10.0, 20.0], [50.0, 20.0]]), 3.0)
    assert mask[20, 10] and mask[20, 50] and mask[23, 30] and not mask[24, 30] and not mask[20, 54]
    assert mask.sum() == pytest.approx(41 * 7 + np.pi * 9, rel=0.1)


def test_navigate_command_exits_3_on_a_refusal_and_writes_no_command(tmp_path: Path, make_no_cm_case) -> None:
    case = write_navigation_case(make_no_cm_case(), tmp_path / "case")
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "fluoronav", "navigate", str(case), "--out", str(out), "--device", "cpu"],
        capture_output=True,
        encoding="utf-8",
    )
    assert proc.returncode == 3, proc.stderr
    assert "refused: stage detect" in proc.stderr
    nav = json.loads((out / "navigation.json").read_text(encoding="utf-8"))
    assert nav["status"] == "refused" and "check views_with_cm" in nav["reason"]
    assert "joints_target_deg" not in nav and "rbase_from_ee_target" not in nav
    page = (out / "report.html").read_text(encoding="utf-8")
    assert "REFUSED" in page and "No robot command was given" in page


def test_navigate_command_bad_case_is_one_line_and_exit_2(tmp_path: Path, make_no_cm_case) -> None:
    case = write_navigation_case(make_no_cm_case(n_views=2, size=64), tmp_path / "case")
    d = json.loads(case.read_text(encoding="utf-8"))
    d["robot"]["joints_deg"] = d["robot"]["joints_deg"][:5]
    case.write_text(json.dumps(d), encoding="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "fluoronav", "navigate", str(case), "--out", str(tmp_path / "o")],
        capture_output=True,
        encoding="utf-8",
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(case) in lines[0] and "joints_deg" in lines[0]
    assert not (tmp_path / "o" / "navigation.json").exists()


def test_navigation_cm_settings_are_the_cmaes_levels() -> None:
    """The navigation keeps CMA-ES at both CM levels, first registration and verification alike:
    the verification's refusals rose with the faster multi-view settings (docstring)."""
    from fluoronav.registration.cm.config import default_cm_levels

    cfg = navigation_cm_config()
    assert cfg.levels == default_cm_levels()
    for workflow in ("single-view", "multi-view"):
        assert [lv.optimizer for lv in cfg.levels_for(workflow)] == ["cmaes", "cmaes"]


def test_a_registration_refusal_is_the_navigations_its_stage_named_as_the_pipelines() -> None:
    with pytest.raises(NavigationRefused) as err, _refusals("verify_"):
        raise RegistrationRefused("cm", "edge_ncc", "NCC 0.10 (at least 0.7)", view="AP (verify)")
    assert (
        err.value.stage == "verify_cm" and err.value.check == "edge_ncc" and err.value.view == "AP (verify)"
    )
    assert str(err.value) == "stage verify_cm, view AP (verify), check edge_ncc: NCC 0.10 (at least 0.7)"


def test_navigate_registers_the_detected_views_as_one_set(
    monkeypatch: pytest.MonkeyPatch, make_no_cm_case
) -> None:
    """The views with the case's landmarks go to ``register_view_set`` with the pipeline's settings
    (one device) and no prior; its stages are the pipeline's, and its refusal the navigation's."""
    case = make_no_cm_case(n_views=2, size=64)
    lm = np.array([[20.0, 30.0], [40.0, 34.0]])
    case = dataclasses.replace(case, views=tuple(dataclasses.replace(v, landmarks_px=lm) for v in case.views))
    seen: dict = {}

    def register(views, volume, **kw):
        seen.update(views=views, **kw)
        with kw["recorder"]("cm"):
            raise RegistrationRefused("cm", "edge_ncc", "NCC 0.10", view="view1")

    monkeypatch.setattr(pipeline, "register_view_set", register)
    events: list[tuple[str, str]] = []
    res = navigate(case, NavigationConfig(device="cpu", seed=3), on_stage=lambda n, e: events.append((n, e)))
    assert [v.name for v in seen["views"]] == ["view0", "view1"]
    assert all(v.detection is not None and v.detection.source == "case" for v in seen["views"])
    assert seen["settings"] == NavigationConfig(device="cpu", seed=3).view_set_settings(verification=False)
    assert seen.get("prior") is None and seen["side"] == case.side
    assert res.status == "refused" and res.reason == "stage cm, view view1, check edge_ncc: NCC 0.10"
    assert res.stages["cm"].passed is False and res.joints_target_deg is None
    assert events == [("detect", "start"), ("detect", "done"), ("cm", "start"), ("cm", "done")]
