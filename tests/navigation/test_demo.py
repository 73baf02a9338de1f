"""The demo pipeline: its report survives a failed run; the whole run (slow) meets its error bars."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fluoronav.navigation.demo import DemoConfig, DemoResult, run_demo, write_case, write_results
from fluoronav.navigation.demo_report import write_report


def test_a_failed_run_still_writes_results_and_a_report(tmp_path: Path) -> None:
    res = DemoResult(config=DemoConfig(seed=3), status="failed", reason="RegistrationFailure: no CM")
    res.timings_s.update(anatomy=1.0, scene=0.1)
    res.errors["landmark_px"] = 0.7
    write_results(res, tmp_path)
    assert write_case(res, tmp_path) is None
    page = write_report(res, tmp_path).read_text(encoding="utf-8")
    assert "FAILED: RegistrationFailure: no CM" in page and "<img" in page  # the timing chart
    data = json.loads((tmp_path / "results.json").read_text(encoding="utf-8"))
    assert data["status"] == "failed" and data["config"]["seed"] == 3 and data["errors"]["landmark_px"] == 0.7


def test_stage_callbacks_and_failure_capture(monkeypatch: pytest.MonkeyPatch) -> None:
    import fluoronav.navigation.demo as demo

    def boom(cfg: DemoConfig, res: DemoResult, stage: object) -> None:
        with stage("anatomy"):  # type: ignore[operator]
            pass
        raise ValueError("bad scene")

    monkeypatch.setattr(demo, "_run", boom)
    events: list[tuple[str, str]] = []
    res = run_demo(DemoConfig(), on_stage=lambda n, e: events.append((n, e)))
    assert res.status == "failed" and res.reason == "ValueError: bad scene"
    assert events == [("anatomy", "start"), ("anatomy", "done")] and "anatomy" in res.timings_s


@pytest.mark.slow
def test_demo_end_to_end(tmp_path: Path) -> None:
    res = run_demo(DemoConfig(seed=0, oracle_landmarks=True))
    assert res.status == "ok", res.reason
    write_results(res, tmp_path)
    case = write_case(res, tmp_path)
    assert case is not None and case.is_file()
    page = write_report(res, tmp_path).read_text(encoding="utf-8")
    assert page.count("<img") >= 6
    E = res.errors
    assert E["cm_tip_mm"] < 2.0 and E["femur_entry_mm"] < 2.0
    assert E["corrected_tip_mm"] < 3.0
