"""Hand-eye and navigation studies: scenario sampling, row columns, a whole (slow) trial."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
import torch

from fluoronav.geometry import se3
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.manipulator.robot import UR10
from fluoronav.simulation.robot_scene import sample_handeye_scenario
from fluoronav.studies.handeye_study import (
    HANDEYE_METRICS,
    NAVIGATION_METRICS,
    HandEyeStudyConfig,
    _columns,
)


@functools.lru_cache(maxsize=1)
def _volume():
    from fluoronav.anatomy.phantom import hip_phantom

    return hip_phantom(seed=0, spacing_mm=3.0)


def test_rows_carry_the_contract_metric_names() -> None:
    he = _columns(HandEyeStudyConfig(workflow="hand-eye", trials=1, seed=0, poses=(4, 8)))
    for name in (
        "handeye_translation_mm",
        "handeye_rotation_deg",
        "handeye_tip_mm",
        "tip_mm",
        "base_translation_mm",
        "base_rotation_deg",
        "notch_rotation_deg",
        "seconds",
        "handeye_tip_mm_m4",
        "handeye_tip_mm_m8",
        "baseline_tip_mm",
        "handeye_axis_deg",
        "handeye_roll_deg",
    ):
        assert name in he
    nav = _columns(HandEyeStudyConfig(workflow="navigation", trials=1, seed=0))
    assert "reposition_tip_mm" in nav and "entry_mm" in nav and "seconds" in nav
    assert {"verify_entry_mm", "verify_tip_mm", "verify_relative_mm", "reposition_axis_deg"} <= set(nav)
    assert set(HANDEYE_METRICS) <= set(he) and set(NAVIGATION_METRICS) <= set(nav)


def test_scenario_has_robot_errors_diverse_in_view_poses_and_a_plausible_mount() -> None:
    sc = sample_handeye_scenario(_volume(), np.random.default_rng(7), n_poses=8)
    assert sc.q_deg.shape == (8, 6) and sc.world_from_cm.shape == (8, 4, 4)
    # the calibration data are the nominal FK of the commanded joints; the truth differs by the errors
    np.testing.assert_allclose(sc.rbase_from_ee_reported, UR10.rbase_from_ee(sc.q_deg))
    true_ee = sc.true_robot.rbase_from_ee(sc.q_actual_deg)
    dev = np.linalg.norm(true_ee[:, :3, 3] - sc.rbase_from_ee_reported[:, :3, 3], axis=1)
    assert np.all(dev > 0.01) and np.all(dev < 3.0)
    np.testing.assert_allclose(sc.world_from_cm, sc.world_from_rbase @ true_ee @ sc.ee_from_cm, atol=1e-9)
    assert 150.0 <= sc.ee_from_cm[2, 3] <= 250.0
    # orientation spread of the CM poses (max pairwise angle) is at least 20°
    R = sc.world_from_cm[:, :3, :3]
    ang = [float(se3.rotation_angle_deg(R[i].T @ R[j])) for i in range(8) for j in range(i + 1, 8)]
    assert max(ang) >= 20.0
    # every landmark is inside the detector (100 px margin)
    lm = sc.landmarks_px
    assert np.all(lm >= 100) and np.all(lm <= sc.camera.cols - 101)


def test_calibration_bend_is_one_planar_c_bend_and_stays_in_view() -> None:
    """``bend_deg``: every control point ±(2.5 + U(−0.5, 0.5))° with one sign, the same shape for all
    poses, the tip ≥ 15 mm off the base axis (a 2°-per-point bend puts it 15.0 mm off), the
    landmarks still inside the 100 px margin; None keeps the protocol's working shape."""
    for seed in (7, 8):
        sc = sample_handeye_scenario(_volume(), np.random.default_rng(seed), n_poses=6, bend_deg=2.5)
        cp = sc.control_points_deg
        assert np.all(np.abs(cp) >= 2.0) and np.all(np.abs(cp) <= 3.0)
        assert np.all(np.sign(cp) == np.sign(cp[0]))
        tip = CMKinematics().tip_cm(torch.as_tensor(cp, dtype=torch.float64)).numpy()
        assert np.hypot(tip[0], tip[1]) >= 15.0
        assert np.all(sc.landmarks_px >= 100) and np.all(sc.landmarks_px <= sc.camera.cols - 101)
    working = sample_handeye_scenario(_volume(), np.random.default_rng(7), n_poses=0)
    np.testing.assert_array_equal(working.control_points_deg, working.trial.control_points_deg)


def test_unknown_workflow_is_an_input_error(tmp_path) -> None:
    from fluoronav.errors import InputError
    from fluoronav.studies.handeye_study import run_handeye_study

    with pytest.raises(InputError):
        run_handeye_study(HandEyeStudyConfig(workflow="hand-eyes", trials=1, seed=0), tmp_path)


@pytest.mark.slow
def test_handeye_study_writes_rows_summary_and_figures(tmp_path) -> None:
    from fluoronav.studies.handeye_study import run_handeye_or_navigation_study

    s = run_handeye_or_navigation_study(
        "hand-eye", trials=1, seed=0, out=tmp_path, workers=0, poses=(3, 4), image_size=384
    )
    assert s["completed"] == 1
    import csv

    rows = list(csv.DictReader((tmp_path / "trials.csv").open()))
    assert rows[0]["status"] == "ok", rows[0]["reason"]
    for k in ("handeye_tip_mm", "handeye_rotation_deg", "handeye_translation_mm", "handeye_tip_mm_m3"):
        assert float(rows[0][k]) >= 0.0
    assert (tmp_path / "figures" / "handeye_error_vs_poses.png").is_file()


def test_rotation_error_splits_into_axis_tilt_and_roll() -> None:
    from scipy.spatial.transform import Rotation

    from fluoronav.studies.handeye_trials import axis_and_roll_deg

    T = se3.make(Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix(), [1.0, 2.0, 200.0])
    for order, angles in (("zx", [7.0, 2.0]), ("xz", [2.0, 7.0])):
        E = se3.make(Rotation.from_euler(order, angles, degrees=True).as_matrix(), np.zeros(3))
        d = axis_and_roll_deg(T @ E, T)
        assert d["handeye_axis_deg"] == pytest.approx(2.0, abs=1e-9)
        assert d["handeye_roll_deg"] == pytest.approx(7.0, abs=1e-9)


def test_recentre_slides_the_c_arm_without_rotating_it() -> None:
    from fluoronav.geometry.carm import carm_camera, recentre

    cam = carm_camera(source_to_isocenter_mm=450.0, isocenter_world=(10.0, -20.0, 30.0))
    uv0 = np.array([(cam.cols - 1) / 2.0, (cam.rows - 1) / 2.0])
    target = np.array([40.0, -5.0, 60.0])
    from_world = cam.backproject(uv0, float(cam.to_camera(target)[2]))
    moved = recentre(cam, from_world, target)
    np.testing.assert_allclose(moved.camera_from_world[:3, :3], cam.camera_from_world[:3, :3])
    # the target is now where the old centre point was: image centre, same depth
    np.testing.assert_allclose(moved.project(target[None])[0], uv0, atol=1e-9)
    np.testing.assert_allclose(moved.to_camera(target), cam.to_camera(from_world), atol=1e-9)
    np.testing.assert_allclose(moved.source_world - cam.source_world, target - from_world, atol=1e-9)


def test_centre_on_puts_the_point_on_the_central_ray_at_its_depth() -> None:
    from fluoronav.geometry.carm import carm_camera, centre_on

    cam = carm_camera(source_to_isocenter_mm=450.0, isocenter_world=(10.0, -20.0, 30.0))
    uv0 = np.array([(cam.cols - 1) / 2.0, (cam.rows - 1) / 2.0])
    target = np.array([40.0, -5.0, 60.0])  # off the central ray: it projects away from the centre
    assert np.linalg.norm(cam.project(target[None])[0] - uv0) > 50.0
    moved = centre_on(cam, target)
    np.testing.assert_allclose(moved.camera_from_world[:3, :3], cam.camera_from_world[:3, :3])
    np.testing.assert_allclose(moved.project(target[None])[0], uv0, atol=1e-9)
    assert moved.to_camera(target)[2] == pytest.approx(cam.to_camera(target)[2], abs=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_navigation_views_see_the_cm_and_the_femoral_head(seed: int) -> None:
    """The demo's C-arm views (AP, orbits of +20° and −15° about the centred point): centred on
    :func:`working_view_centre` they see A, B and the tip of the working CM with the femoral head
    near the centre; slid to centre the femoral head and the planned CM they see the CM at the
    plan (one C-arm position for both leaves the planned CM outside the field in most scenarios)."""
    from fluoronav.geometry import orbit_camera
    from fluoronav.geometry.carm import centre_on
    from fluoronav.navigation.planning import neck_entry_plan, planned_femur_from_cm
    from fluoronav.simulation.robot_scene import in_view, verification_view_centre, working_view_centre

    sc = sample_handeye_scenario(_volume(), np.random.default_rng(seed), n_poses=0)
    tr = sc.trial
    kin = CMKinematics(sc.cm_config)
    cp = torch.as_tensor(sc.control_points_deg, dtype=torch.float64)
    pts = np.concatenate([kin.landmarks_cm(cp).numpy(), kin.tip_cm(cp).numpy()[None]])
    femur_from_cm = planned_femur_from_cm(
        neck_entry_plan(tr.entry_ct, tr.femoral_head_ct, sc.control_points_deg), kinematics=kin
    )
    planned = tr.world_from_femur @ femur_from_cm
    head = np.asarray(tr.femoral_head_world)
    verify_centre = (
        tr.world_from_femur @ np.append(verification_view_centre(femur_from_cm, tr.femoral_head_ct), 1.0)
    )[:3]

    def views(centre: np.ndarray) -> list:
        ap = centre_on(sc.camera, centre)
        return [ap] + [orbit_camera(ap, angle_deg=a, isocenter_world=centre) for a in (20.0, -15.0)]

    for cam in views(working_view_centre(tr)):
        assert in_view(cam, sc.true_world_from_cm(sc.q_work_deg), pts, 20.0)
        centre_px = np.array([(cam.cols - 1) / 2.0, (cam.rows - 1) / 2.0])
        assert np.linalg.norm(cam.project(head[None])[0] - centre_px) < 0.25 * cam.cols
    for cam in views(verify_centre):
        assert in_view(cam, planned, pts, 20.0)


def test_navigation_allows_open_loop_or_one_correction(tmp_path) -> None:
    from fluoronav.errors import InputError
    from fluoronav.studies.handeye_study import run_handeye_study

    with pytest.raises(InputError, match="corrections"):
        run_handeye_study(
            HandEyeStudyConfig(workflow="navigation", trials=1, seed=0, corrections=2), tmp_path
        )


@pytest.mark.slow
def test_navigation_trial_runs_the_shared_loop_and_corrects() -> None:
    """A whole navigation trial (768², oracle landmarks, ~3 min) through the shared simulated loop:
    the verification (C-arm slid to the plan, 3 views, bones and CM registered anew) sees how far the
    first move missed, within 1 mm, and the corrective move lands within 1.5 mm of the plan, closer
    than the first move (or as close, within 0.1 mm, when the first move already landed well)."""
    from fluoronav.studies.handeye_study import run_navigation_trial

    cfg = HandEyeStudyConfig(workflow="navigation", trials=1, seed=5305, oracle_landmarks=True)
    row = run_navigation_trial(0, 5563968429960866729, cfg=cfg)
    assert row["status"] == "ok", row.get("reason")
    assert abs(row["reposition_registered_mm"] - row["reposition_open_loop_mm"]) < 1.0
    assert row["reposition_tip_mm"] < min(1.5, row["reposition_open_loop_mm"] + 0.1)
    assert row["verify_relative_mm"] < 1.5


def test_summary_counts_refusals_apart_and_flags_unflagged_gross_failures() -> None:
    from fluoronav.studies.handeye_study import _navigation_outcomes
    from fluoronav.studies.summary import summarize

    rows = [
        {"trial": 0, "status": "ok", "reposition_tip_mm": 0.4, "seconds": 10.0},
        {"trial": 1, "status": "ok", "reposition_tip_mm": 2.6, "seconds": 10.0},  # said ok, was not
        {
            "trial": 2,
            "status": "refused",
            "reason": "stage verify_cm, check robot_motion: 9 mm",
            "seconds": 9.0,
        },
        {"trial": 3, "status": "failed", "reason": "ValueError: x", "seconds": 1.0},
        {"trial": 4, "status": "refused", "reposition_tip_mm": 8.0, "reason": "stage cm, check edge_ncc"},
    ]
    s = summarize(
        "navigation", rows, ["reposition_tip_mm"], trials=5, device="cpu", extra=_navigation_outcomes(rows)
    )
    assert s["failed"] == 1 and s["refused"] == 2
    assert s["refusal_reasons"] == {
        "stage verify_cm, check robot_motion: 9 mm": 1,
        "stage cm, check edge_ncc": 1,
    }
    assert s["metrics"]["reposition_tip_mm"]["n"] == 2  # over the rows with status ok only
    assert s["unflagged_gross_failures"] == 1 and s["unflagged_gross_failure_trials"] == [1]


def test_navigation_rows_take_the_final_tip_and_the_checks() -> None:
    from fluoronav.navigation.pipeline import NavigationConfig
    from fluoronav.navigation.result import NavigationResult, StageRecord
    from fluoronav.simulation.navigation.loop import SimulatedNavigation, SimulatedNavigationConfig
    from fluoronav.studies.handeye_study import navigation_row

    res = NavigationResult(config=NavigationConfig())
    res.stages["cm"] = StageRecord(
        seconds=3.0,
        diagnostics={
            "views": {
                "AP": {"landmark_residual_mm": 0.3, "edge_ncc": 0.96},
                "B": {"landmark_residual_mm": 0.7, "edge_ncc": 0.91},
            }
        },
    )
    res.stages["verify_cm"] = StageRecord(
        seconds=2.0,
        diagnostics={
            "views": {"AP": {"landmark_residual_mm": None, "edge_ncc": 0.8}},
            "views_used": ["AP"],
            "motion_tip_mm": 1.2,
            "from_prediction": True,
        },
    )
    res.stages["verify_detect"] = StageRecord(diagnostics={"local_bones_refused": "stage verify_cm, …"})
    res.stages["pelvis"] = StageRecord(
        seconds=5.0, diagnostics={"views": {"AP": {"cost": 0.5}, "B": {"cost": 0.6}}}
    )
    run = SimulatedNavigation(config=SimulatedNavigationConfig(), result=res)
    run.errors.update(reposition_tip_mm=1.5, corrected_tip_mm=0.3, corrected_axis_deg=0.2, cm_tip_mm=0.25)
    row = navigation_row(run, HandEyeStudyConfig(workflow="navigation", trials=1, seed=0))
    assert row["reposition_open_loop_mm"] == 1.5 and row["reposition_tip_mm"] == 0.3 and row["tip_mm"] == 0.25
    assert row["cm_landmark_residual_mm"] == 0.7 and row["cm_edge_ncc"] == 0.91
    assert row["verify_cm_edge_ncc"] == 0.8 and row["verify_motion_tip_mm"] == 1.2
    assert "verify_cm_landmark_residual_mm" not in row and row["pelvis_cost"] == 0.6
    assert row["seconds_registration"] == 3.0 and row["seconds_verification"] == 2.0
    # how the verification went: one view, from the prediction, not fused, after the whole ladders
    assert (row["verify_views_used"], row["verify_from_prediction"], row["verify_fused"]) == (1.0, 1.0, 0.0)
    assert row["verify_whole_ladders_retry"] == 1.0
    open_loop = navigation_row(
        run, HandEyeStudyConfig(workflow="navigation", trials=1, seed=0, corrections=0)
    )
    assert open_loop["reposition_tip_mm"] == 1.5


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--fault", "mirror_three"], "--fault: unknown fault 'mirror_three'; one of: none, mirror_one"),
        (["--fault", "none", "--world", "atlantis"], "atlantis: unknown world"),
    ],
)
def test_study_fault_options_are_checked_before_anything_runs(
    args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from fluoronav.cli.main import main

    out = tmp_path / "study"
    with pytest.raises(SystemExit) as exc:
        main(["study", "navigation", "--trials", "1", "--seed", "0", "--out", str(out), *args])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


@pytest.mark.parametrize(
    ("workflow", "args"),
    [
        ("multi-view", ["--handeye-error-mm", "2"]),
        ("multi-view", ["--fault", "mirror_one"]),
        ("hand-eye", ["--world", "realistic"]),
        ("multi-view", ["--verify-views", "2"]),
        ("navigation", ["--poses", "4"]),
        ("deepfluoro", ["--world", "realistic"]),
    ],
)
def test_a_study_refuses_another_studys_options(
    workflow: str, args: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from fluoronav.cli.main import main

    out = tmp_path / "study"
    with pytest.raises(SystemExit) as exc:
        main(["study", workflow, "--trials", "1", "--seed", "0", "--out", str(out), *args])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"No such option: {args[0]}" in err and "Traceback" not in err
    assert not out.exists()


def test_fault_handeye_errors_come_from_the_fault_unless_given(
    monkeypatch: pytest.MonkeyPatch, tmp_path
) -> None:
    import fluoronav.studies.handeye_study as hs

    seen: list[HandEyeStudyConfig] = []

    def record(cfg: HandEyeStudyConfig, out: Path, **kw: object) -> dict[str, object]:
        seen.append(cfg)
        return {}

    monkeypatch.setattr(hs, "run_handeye_study", record)
    hs.run_handeye_or_navigation_study("navigation", trials=1, seed=0, out=tmp_path, fault="handeye_10mm")
    hs.run_handeye_or_navigation_study(
        "navigation", trials=1, seed=0, out=tmp_path, fault="handeye_10mm", handeye_error_mm=3.0
    )
    hs.run_handeye_or_navigation_study("navigation", trials=1, seed=0, out=tmp_path, fault="mirror_one")
    assert [c.handeye_error_mm for c in seen] == [10.0, 3.0, 0.5]
    assert [c.handeye_error_deg for c in seen] == [0.4, 0.4, 0.4]
    assert seen[0].fault == "handeye_10mm"


def test_fault_rows_record_the_check_and_the_outcome() -> None:
    from fluoronav.navigation.pipeline import NavigationConfig
    from fluoronav.navigation.result import NavigationRefused, NavigationResult, StageRecord
    from fluoronav.simulation.navigation.loop import SimulatedNavigation, SimulatedNavigationConfig
    from fluoronav.studies.handeye_study import navigation_row

    cfg = HandEyeStudyConfig(workflow="navigation", trials=1, seed=0, fault="mirror_one")
    names = ["AP", "orbit +20", "orbit -15"]
    res = NavigationResult(config=NavigationConfig())
    res.stages["pelvis"] = StageRecord(diagnostics={"left_out": {"orbit +20": "mirrored: looks mirrored"}})
    run = SimulatedNavigation(config=SimulatedNavigationConfig(), result=res, artifacts={"names": names})
    run.errors.update(reposition_tip_mm=1.5, corrected_tip_mm=0.3, cm_tip_mm=0.4)
    run.errors.update(cm_base_rx_deg=3.0, cm_base_ry_deg=4.0, cm_base_rz_deg=20.0)
    row = navigation_row(run, cfg)
    assert row["fault_outcome"] == "landed" and row["fault_handled"] and row["left_out"] == ["orbit +20"]
    assert row["cm_axis_deg"] == pytest.approx(5.0, abs=0.1)  # the tilt of the axis, not the roll

    res.refuse(NavigationRefused("pelvis", "mirrored", "view orbit +20 looks mirrored", "orbit +20"))
    row = navigation_row(run, cfg)
    assert (
        row["status"] == "refused" and row["check"] == "mirrored" and row["fault_outcome"] == "refused_named"
    )

    inverted = HandEyeStudyConfig(workflow="navigation", trials=1, seed=0, fault="inverted")
    err = SimulatedNavigation(
        config=SimulatedNavigationConfig(),
        artifacts={
            "names": names,
            "input_error": {"reason": "case: view 'AP' inverted", "check": "inverted_image"},
        },
    )
    row = navigation_row(err, inverted)
    assert row["status"] == "input_error" and row["check"] == "inverted_image"
    assert row["fault_outcome"] == "refused_named" and row["reason"] == "case: view 'AP' inverted"


def test_summary_flags_first_moves_from_registrations_off_the_truth() -> None:
    from fluoronav.studies.handeye_study import _navigation_outcomes

    # femur frame: what the move acts on; C-arm frame: with what the bones and the CM share
    rows = [
        {
            "trial": 0,
            "status": "ok",
            "reposition_open_loop_mm": 1.0,
            "femur_tip_mm": 0.5,
            "femur_axis_deg": 1.0,
            "tip_mm": 2.5,
            "cm_axis_deg": 1.0,
        },
        {
            "trial": 1,
            "status": "refused",
            "reposition_open_loop_mm": 4.0,
            "femur_tip_mm": 2.5,
            "femur_axis_deg": 1.0,
            "tip_mm": 2.5,
            "cm_axis_deg": 1.0,
        },
        {
            "trial": 2,
            "status": "ok",
            "reposition_open_loop_mm": 1.0,
            "femur_tip_mm": 1.0,
            "femur_axis_deg": 6.0,
            "tip_mm": 1.0,
            "cm_axis_deg": 6.0,
        },
        {
            "trial": 3,
            "status": "refused",
            "reposition_open_loop_mm": "",
            "femur_tip_mm": 9.0,
            "femur_axis_deg": "",
            "tip_mm": 9.0,
            "cm_axis_deg": "",
        },
    ]
    out = _navigation_outcomes(rows)
    assert out["unflagged_first_move_failures"] == 2 and out["unflagged_first_move_failure_trials"] == [1, 2]
    assert out["unflagged_first_move_failures_carm_frame"] == 3
    assert out["unflagged_first_move_failure_trials_carm_frame"] == [0, 1, 2]


def _navigation_study_configs(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, field: str, options: list[str]
) -> tuple[list[object], Path]:
    """``study navigation`` (2 trials, in this process) with ``options``, its trials stand-ins that
    record their config's ``field`` → (the recorded values, the study's directory)."""
    import fluoronav.studies.handeye_study as hs
    import fluoronav.studies.handeye_trials as ht
    from fluoronav.cli.main import main

    seen: list[object] = []

    def trial(trial_id: int, seed: int, *, cfg: HandEyeStudyConfig) -> dict[str, object]:
        seen.append(getattr(cfg, field))
        row = ht.new_row(trial_id, seed, cfg.workflow)
        row.update(status="refused", reason="stage robot, check reachable: x")
        return ht.finish_row(row, 0.0)

    monkeypatch.setattr(hs, "run_navigation_trial", trial)
    monkeypatch.setattr(hs, "detector_or_none", lambda device: None)
    out = tmp_path / "study"
    args = ["study", "navigation", "--trials", "2", "--seed", "1", "--out", str(out), "--workers", "0"]
    main([*args, *options])
    return seen, out


def test_the_world_of_a_navigation_study_reaches_its_trials_and_its_records(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """``--world realistic``: the trials' simulations get the world, config.json and summary.json
    record it (name and every magnitude)."""
    import json

    from fluoronav.simulation.world import REALISTIC

    worlds, out = _navigation_study_configs(monkeypatch, tmp_path, "world", ["--world", "realistic"])
    assert worlds == [REALISTIC, REALISTIC]
    for name in ("config.json", "summary.json"):
        assert json.loads((out / name).read_text())["world"] == REALISTIC.to_dict()


def test_the_verification_views_of_a_navigation_study_reach_its_trials_and_its_summary(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    import json

    seen, out = _navigation_study_configs(monkeypatch, tmp_path, "verify_views", ["--verify-views", "1"])
    assert seen == [1, 1]
    for name in ("config.json", "summary.json"):
        assert json.loads((out / name).read_text())["verify_views"] == 1
