"""The demo: a simulated case written to files, the navigate pipeline on them, the truth beside it.

The slow end-to-end test runs ``fluoronav demo`` in one process and ``fluoronav navigate`` on the
written case in another (nothing shared but the files), and checks the second against the truth and
its Slicer transforms against its own ``navigation.json``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk  # noqa: N813

from fluoronav.navigation.pipeline import NavigationConfig, NavigationRefused, NavigationResult, StageRecord
from fluoronav.simulation.navigation.demo import results_json, write_demo_outputs
from fluoronav.simulation.navigation.loop import SimulatedNavigation, SimulatedNavigationConfig
from fluoronav.simulation.world import IDEAL


def test_results_of_a_refused_run_say_so_and_carry_no_move() -> None:
    res = NavigationResult(config=NavigationConfig())
    res.stages["detect"] = StageRecord(seconds=0.5)
    res.joints_target_deg = np.zeros(6)  # a command computed before the refusal is withdrawn
    res.refuse(NavigationRefused("detect", "views_with_cm", "the CM was found in 1 of 3 views", view="AP"))
    run = SimulatedNavigation(config=SimulatedNavigationConfig(seed=3), result=res)
    run.errors["landmark_px"] = 0.7
    d = results_json(run)
    assert d["status"] == "refused"
    assert d["reason"] == "stage detect, view AP, check views_with_cm: the CM was found in 1 of 3 views"
    assert d["errors"]["reposition_tip_mm"] is None and d["errors"]["corrected_tip_mm"] is None
    assert d["errors"]["landmark_px"] == 0.7 and d["config"]["seed"] == 3
    assert d["world"] == {**IDEAL.to_dict(), "name": "ideal"}
    json.dumps(d)  # the world's magnitudes are JSON
    assert res.joints_target_deg is None and res.stages["detect"].passed is False
    assert "joints_target_deg" not in res.to_json()


def test_a_run_without_a_pipeline_result_still_writes_results(tmp_path: Path) -> None:
    run = SimulatedNavigation(config=SimulatedNavigationConfig(seed=1))
    run.loop_stages["anatomy"] = StageRecord(seconds=1.0)
    written = write_demo_outputs(run, tmp_path)
    assert written == [tmp_path / "results.json"]
    assert json.loads(written[0].read_text(encoding="utf-8"))["status"] == "failed"


def _h(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return np.asarray(p) @ np.asarray(T)[:3, :3].T + np.asarray(T)[:3, 3]


@pytest.mark.slow
def test_demo_case_navigates_in_a_separate_process(tmp_path: Path) -> None:
    """``fluoronav demo`` (oracle landmarks, seed 11) writes case/navigation.json and truth.json;
    ``fluoronav navigate`` on that case in another process puts the CM tip within 1 mm of the truth,
    gives a command, and its slicer/*.h5 map points as its navigation.json's matrices."""
    demo_out, nav_out = tmp_path / "demo", tmp_path / "nav"
    cmd = [
        sys.executable,
        "-m",
        "fluoronav",
        "demo",
        "--out",
        str(demo_out),
        "--seed",
        "11",
        "--device",
        "cpu",
    ]
    subprocess.run([*cmd, "--oracle-landmarks"], check=True, capture_output=True)
    case = demo_out / "case" / "navigation.json"
    truth = json.loads((demo_out / "truth.json").read_text(encoding="utf-8"))
    results = json.loads((demo_out / "results.json").read_text(encoding="utf-8"))
    assert results["status"] == "ok", results["reason"]
    assert (demo_out / "report.html").read_text(encoding="utf-8").count("<img") >= 6

    proc = subprocess.run(
        [sys.executable, "-m", "fluoronav", "navigate", str(case), "--out", str(nav_out), "--device", "cpu"],
        capture_output=True,
        encoding="utf-8",
    )
    assert proc.returncode == 0, proc.stderr
    nav = json.loads((nav_out / "navigation.json").read_text(encoding="utf-8"))
    assert nav["status"] == "ok" and len(nav["joints_target_deg"]) == 6
    assert np.linalg.norm(np.subtract(nav["tip_ct_mm"], truth["tip_ct_mm"])) < 1.0
    v = nav["verification"]
    assert np.linalg.norm(np.subtract(v["tip_ct_mm"], truth["verification"]["tip_ct_mm"])) < 1.0
    assert len(v["joints_target_deg"]) == 6
    # the verification views' pelvis again with the femur left out (the views are centred on the hip)
    for view in nav["stages"]["verify_pelvis"]["views"].values():
        assert 0.05 < view["femur_left_out"] < 0.8 and view["reason_without_femur"]
    # the Slicer files: the file of ct_from_x maps CT points to x (ITK's resampling direction)
    rng = np.random.default_rng(0)
    p_ct = rng.uniform(-100.0, 100.0, (5, 3))
    for name, key in (("ct_from_cm.h5", "ct_from_cm"), ("ct_from_femur.h5", "ct_from_femur")):
        tx = sitk.ReadTransform(str(nav_out / "slicer" / name))
        expected = _h(np.linalg.inv(v[key]), p_ct)
        got = np.array([tx.TransformPoint(tuple(float(c) for c in p)) for p in p_ct])
        np.testing.assert_allclose(got, expected, atol=1e-6)


def test_a_refused_runs_results_carry_the_known_and_the_named_cause() -> None:
    """``results.json`` of a refused run: its ``causes`` (none where the run went on)."""
    from types import SimpleNamespace

    from fluoronav.simulation.navigation import loop

    res = NavigationResult(config=NavigationConfig())
    lm = np.array([[100.0, 120.0], [160.0, 130.0]])
    res.stages["verify_detect"] = StageRecord(
        diagnostics={"views": {"AP": {"landmarks_px": (lm + 20.0).tolist()}}}
    )
    res.refuse(
        NavigationRefused("verify_cm", "kinematics_disagree", "the CM's landmarks …", view="AP (verify)")
    )
    run = SimulatedNavigation(config=SimulatedNavigationConfig(seed=3), result=res)
    assert "causes" not in results_json(run)
    s = SimpleNamespace(config=run.config)
    views = [SimpleNamespace(name="AP", landmarks_px=None)]
    images = [SimpleNamespace(landmarks_px=lm, camera=SimpleNamespace(pixel_spacing_mm=0.388))]
    loop._causes(s, run, "verify_cm", "kinematics_disagree", views, images, "verify_detect")  # type: ignore[arg-type]
    d = results_json(run)["causes"]
    assert (d["true_cause"], d["named_cause"], d["cause_named_right"]) == (
        "wrong_detection",
        "hand_eye_or_joints",
        False,
    )
    assert d["wrong_detection_views"] == {"AP": pytest.approx(20.0 * np.sqrt(2.0) * 0.388)}
    json.dumps(d)
