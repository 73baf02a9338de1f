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
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import fluoronav.navigation.pipeline as pipeline
import fluoronav.navigation.verification as verification
from fluoronav.errors import RegistrationRefused
from fluoronav.geometry import se3
from fluoronav.navigation.case.model import VerificationViews, write_navigation_case
from fluoronav.navigation.checks.safety import SafetyConfig
from fluoronav.navigation.config import navigation_cm_config
from fluoronav.navigation.detect import band_mask
from fluoronav.navigation.pipeline import NavigationConfig, NavigationRefused, navigate
from fluoronav.navigation.planning import planned_femur_from_cm
from fluoronav.navigation.result import navigation_refusals


def test_no_cm_in_the_views_refuses_at_detection_without_a_command(make_no_cm_case) -> None:
    events: list[tuple[str, str]] = []
    res = navigate(make_no_cm_case(), NavigationConfig(), on_stage=lambda n, e: events.append((n, e)))
    assert res.status == "refused"
    assert res.reason.startswith("stage detect, view view0, view1, view2, check views_with_cm:")
    assert res.joints_target_deg is None and res.rbase_from_ee_target is None
    assert res.stages["detect"].passed is False
    assert res.stages["detect"].diagnostics["views_detected"] == 0
    assert events == [("preflight", "start"), ("preflight", "done"), ("detect", "start"), ("detect", "done")]
    d = res.to_json()
    assert d["status"] == "refused" and "joints_target_deg" not in d and "rbase_from_ee_target" not in d


def test_given_landmarks_skip_the_detector_and_make_a_band_mask() -> None:
    mask = band_mask((40, 60), np.array([[10.0, 20.0], [50.0, 20.0]]), 3.0)
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


def test_navigation_cm_settings_are_cmaes_twice_and_the_verifications_local_levels_linearised() -> None:
    """The CM from the images' own starts: CMA-ES at 4× and at 2× (the linearised 2× finish left the
    base's direction ~3× worse); from the kinematic prediction: the local CMA-ES level, then the
    linearised 2× level with several views and CMA-ES with one."""
    from fluoronav.registration.cm.config import local_cm_levels

    assert [lv.optimizer for lv in navigation_cm_config().levels_for("multi-view")] == ["cmaes", "cmaes"]
    assert [lv.name for lv in navigation_cm_config().levels_for("multi-view")] == ["cm-4x", "cm-2x"]
    assert [lv.optimizer for lv in local_cm_levels(3)] == ["cmaes", "linearized"]
    assert [lv.optimizer for lv in local_cm_levels(1)] == ["cmaes", "cmaes"]


def test_a_registration_refusal_is_the_navigations_its_stage_named_as_the_pipelines() -> None:
    with pytest.raises(NavigationRefused) as err, navigation_refusals("verify_"):
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

    monkeypatch.setattr(verification, "register_view_set", register)
    events: list[tuple[str, str]] = []
    res = navigate(case, NavigationConfig(device="cpu", seed=3), on_stage=lambda n, e: events.append((n, e)))
    assert [v.name for v in seen["views"]] == ["view0", "view1"]
    assert all(v.detection is not None and v.detection.source == "case" for v in seen["views"])
    assert seen["settings"] == NavigationConfig(device="cpu", seed=3).view_set_settings(verification=False)
    assert seen.get("prior") is None and seen["side"] == case.side
    assert res.status == "refused" and res.reason == "stage cm, view view1, check edge_ncc: NCC 0.10"
    assert res.stages["cm"].passed is False and res.joints_target_deg is None
    assert events == [
        ("preflight", "start"),
        ("preflight", "done"),
        ("detect", "start"),
        ("detect", "done"),
        ("cm", "start"),
        ("cm", "done"),
    ]


def _fake_registration(ct_from_cm: np.ndarray) -> SimpleNamespace:
    """What the plan, robot and correct stages read of a registration (femur = CT, view 0 = CT)."""
    return SimpleNamespace(
        views=(SimpleNamespace(name="view0"),),
        cameras_ct=(SimpleNamespace(camera_from_world=np.eye(4)),),
        ct_from_femur=np.eye(4),
        ct_from_cm=ct_from_cm,
        cm=SimpleNamespace(control_points_deg=np.zeros(5)),
        to_dict=lambda: {"ct_from_cm": ct_from_cm.tolist()},
        tip_ct_mm=np.zeros(3),
    )


def _robot_case(
    make_no_cm_case,
    monkeypatch: pytest.MonkeyPatch,
    *,
    roll_deg: float,
    plan=None,
    verify_offset_mm=None,
    tilt_deg: float = 0.0,
    verify_diagnostics=None,
):
    """The conftest case with given landmarks and a stand-in registration: the CM held 40 mm back along
    the plan's axis, rolled ``roll_deg`` from the plan's default roll. With ``verify_offset_mm``, a
    verification at the first command's joints whose CM lies that far (mm, CM x) from the plan (and so
    from where the kinematics put it), its CM stage recording ``verify_diagnostics`` (default: two
    views that passed, their landmarks 0.3 mm from the detected ones)."""
    case = make_no_cm_case(n_views=2, size=64)
    lm = np.array([[20.0, 30.0], [40.0, 34.0]])
    views = tuple(dataclasses.replace(v, landmarks_px=lm) for v in case.views)
    case = dataclasses.replace(case, views=views, plan=plan or case.plan)
    free = dataclasses.replace(case.plan, bending_direction_world=None, control_points_deg=np.zeros(5))
    held = planned_femur_from_cm(free, roll_deg=roll_deg)
    held[:3, 3] -= 40.0 * case.plan.direction_world
    held = held @ se3.make(Rotation.from_rotvec([np.radians(tilt_deg), 0.0, 0.0]).as_matrix(), np.zeros(3))
    first = _fake_registration(held)
    monkeypatch.setattr(pipeline, "register_view_set", lambda views, volume, **kw: first)
    monkeypatch.setattr(verification, "register_view_set", lambda views, volume, **kw: first)
    if verify_offset_mm is None:
        return case
    q_after = navigate(case, _CFG).joints_target_deg
    assert q_after is not None
    reached = np.array(navigate(case, _CFG).femur_from_cm_target)
    reached[:3, 3] += verify_offset_mm * reached[:3, 0]
    ver = _fake_registration(reached)
    ver.left_out = {}
    diag = {
        "views": {v.name: {"landmark_residual_mm": 0.3, "edge_ncc": 0.9} for v in views},
        "views_used": [v.name for v in views],
        "tries": 1,
        **(verify_diagnostics or {}),
        "motion_tip_mm": verify_offset_mm,  # the plan is where the kinematics put the CM
    }

    def register(views, volume, **kw):
        if kw.get("prior") is None:
            return first
        with kw["recorder"]("cm") as rec:
            rec.diagnostics.update(diag)
        return ver

    monkeypatch.setattr(pipeline, "register_view_set", register)

    monkeypatch.setattr(verification, "register_view_set", register)
    return dataclasses.replace(case, verification=VerificationViews(q_after, views))


_CFG = NavigationConfig(device="cpu", seed=0, preflight=None)


def test_a_free_roll_plan_gets_the_least_motion_roll_and_a_measured_command(
    make_no_cm_case, monkeypatch: pytest.MonkeyPatch
) -> None:
    case = _robot_case(make_no_cm_case, monkeypatch, roll_deg=120.0)
    assert case.plan.roll_free
    res = navigate(case, _CFG)
    assert res.status == "ok", res.reason
    plan_diag, robot_diag = res.stages["plan"].diagnostics, res.stages["robot"].diagnostics
    assert plan_diag["roll_free"] is True and plan_diag["roll_deg"] == pytest.approx(120.0, abs=0.5)
    assert res.plan is not None
    assert res.femur_from_cm_target is not None
    np.testing.assert_allclose(
        res.femur_from_cm_target, planned_femur_from_cm(res.plan, roll_deg=plan_diag["roll_deg"]), atol=1e-12
    )
    assert robot_diag["joint_motion_deg"] <= 30.0
    assert robot_diag["tip_move_mm"] == pytest.approx(40.0, abs=0.01)
    assert robot_diag["rotation_deg"] == pytest.approx(0.0, abs=0.5)
    assert robot_diag["swept_path_mm"] >= robot_diag["swept_straight_mm"] == pytest.approx(40.0, abs=0.01)
    d = res.to_json()
    assert len(d["joint_motion_deg"]) == 6 and max(d["joint_motion_deg"]) == robot_diag["joint_motion_deg"]
    assert d["stages"]["robot"]["swept_max_deviation_mm"] == robot_diag["swept_max_deviation_mm"]


def test_a_fixed_roll_plan_keeps_its_pose_and_a_far_turn_is_refused(
    make_no_cm_case, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The plan fixes the roll 60° from where the CM is held: today's pose exactly, and a command that
    turns the wrist 60° is refused naming the plan."""
    plan0 = make_no_cm_case().plan
    bend = planned_femur_from_cm(plan0)[:3, 1]  # the default roll, fixed
    plan = dataclasses.replace(plan0, bending_direction_world=bend)
    case = _robot_case(make_no_cm_case, monkeypatch, roll_deg=60.0, plan=plan)
    res = navigate(case, _CFG)
    assert res.plan is not None and not res.plan.roll_free
    assert res.femur_from_cm_target is not None
    assert np.array_equal(res.femur_from_cm_target, planned_femur_from_cm(res.plan))
    assert "roll_deg" not in res.stages["plan"].diagnostics
    assert res.status == "refused" and res.joints_target_deg is None
    assert "stage robot, check joint_motion: plan 'entry'" in res.reason
    assert res.stages["robot"].diagnostics["joint_motion_deg"] == pytest.approx(60.0, abs=1e-6)


@pytest.mark.parametrize(
    ("bound", "check"),
    [
        ({"max_move_mm": 30.0}, "move_length"),
        ({"max_move_deg": 5.0}, "move_rotation"),
        ({"max_joint_motion_deg": 1.0}, "joint_motion"),
    ],
)
def test_each_bound_of_the_first_move_refuses_the_navigation(
    make_no_cm_case, monkeypatch: pytest.MonkeyPatch, bound: dict, check: str
) -> None:
    # for the rotation's bound, the CM held 10° off the plan's axis
    tilt_deg = 10.0 if check == "move_rotation" else 0.0
    case = _robot_case(make_no_cm_case, monkeypatch, roll_deg=0.0, tilt_deg=tilt_deg)
    cfg = dataclasses.replace(_CFG, safety=dataclasses.replace(SafetyConfig(), **bound))
    assert navigate(case, _CFG).status == "ok"
    res = navigate(case, cfg)
    assert res.status == "refused" and res.joints_target_deg is None and not res.stages["robot"].passed
    assert f"stage robot, check {check}: plan 'entry'" in res.reason


@pytest.mark.parametrize(
    ("offset_mm", "safety", "check"),
    [
        (2.0, {}, None),  # the images agree with the kinematics: corrected
        (5.0, {}, "kinematics_disagree"),  # they disagree, and two views cannot overrule the kinematics
        (5.0, {"overrule_min_views": 2}, None),  # two views may: corrected, with a warning
        (5.0, {"overrule_min_views": 2, "overrule_max_landmark_residual_mm": 0.2}, "kinematics_disagree"),
        (12.0, {"overrule_min_views": 2}, "kinematics_disagree"),  # beyond any correction
        (2.5, {"max_correction_mm": 2.0}, "correction_length"),
    ],
)
def test_the_correction_is_judged_against_the_kinematics_and_bounded(
    make_no_cm_case, monkeypatch: pytest.MonkeyPatch, offset_mm: float, safety: dict, check: str | None
) -> None:
    case = _robot_case(make_no_cm_case, monkeypatch, roll_deg=60.0, verify_offset_mm=offset_mm)
    res = navigate(case, dataclasses.replace(_CFG, safety=dataclasses.replace(SafetyConfig(), **safety)))
    diag = res.stages["correct"].diagnostics
    assert diag["kinematics_disagreement_mm"] == offset_mm
    if check is None:
        assert res.status == "ok", res.reason
        assert diag["tip_move_mm"] == pytest.approx(offset_mm, abs=1e-6)
        assert diag["predicted_tip_error_mm"] == pytest.approx(0.0, abs=1e-6)
        assert res.joints_correction_deg is not None and diag["joint_motion_deg"] <= 30.0
        assert len(res.to_json()["verification"]["joint_motion_deg"]) == 6
        overruled = offset_mm > SafetyConfig().max_motion_tip_mm
        assert bool(res.warnings) == overruled == bool(diag.get("images_overrule"))
        if overruled:
            assert "check the hand-eye matrix and the joint readings" in res.warnings[0]
            assert res.to_json()["warnings"] == res.warnings
    else:
        assert res.status == "refused" and res.joints_correction_deg is None
        assert f"stage correct, check {check}" in res.reason
        if check == "kinematics_disagree":
            assert f"{offset_mm:.1f} mm from where the robot's kinematics put it" in res.reason
            assert "hand-eye matrix" in res.reason


def test_a_view_left_out_keeps_the_images_from_overruling_the_kinematics(
    make_no_cm_case, monkeypatch: pytest.MonkeyPatch
) -> None:
    left = {"left_out": {"view1": "edge_ncc: NCC 0.2"}}
    case = _robot_case(
        make_no_cm_case, monkeypatch, roll_deg=60.0, verify_offset_mm=5.0, verify_diagnostics=left
    )
    res = navigate(case, dataclasses.replace(_CFG, safety=SafetyConfig(overrule_min_views=1)))
    assert res.status == "refused" and "views left out (view1)" in res.reason


def test_joint_readings_that_differ_from_the_command_are_refused_before_any_registration(
    make_no_cm_case, monkeypatch: pytest.MonkeyPatch
) -> None:
    case = _robot_case(make_no_cm_case, monkeypatch, roll_deg=60.0, verify_offset_mm=1.0)
    assert case.verification is not None
    q = np.array(case.verification.joints_deg)
    q[1] += 3.0
    case = dataclasses.replace(case, verification=VerificationViews(q, case.verification.views))
    res = navigate(case, _CFG)
    assert res.status == "refused" and res.verification is None
    assert "stage verify_joints, check joint_readings" in res.reason and "joint 2" in res.reason
    assert "3.00°" in res.reason and "verify_detect" not in res.stages


def _local_config() -> NavigationConfig:
    from fluoronav.navigation.config import VerificationConfig

    return dataclasses.replace(_CFG, verification=VerificationConfig(local_bones=True))


_LOCAL = _local_config()


@pytest.mark.parametrize("local_bones", [True, False])
def test_the_verification_registers_the_bones_locally_by_default_or_with_the_whole_ladders(
    make_no_cm_case, monkeypatch: pytest.MonkeyPatch, local_bones: bool
) -> None:
    from fluoronav.navigation.config import VerificationConfig

    case = _robot_case(make_no_cm_case, monkeypatch, roll_deg=60.0, verify_offset_mm=1.0)
    slide = se3.make(np.eye(3), (-40.0, 15.0, 0.0))
    case = _with_relations(case, [("view0", slide), ("view0", slide)])
    seen = _spy_verification(monkeypatch)
    cfg = (
        _CFG if local_bones else dataclasses.replace(_CFG, verification=VerificationConfig(local_bones=False))
    )
    assert VerificationConfig().local_bones is True
    navigate(case, cfg)
    assert seen["settings"].local is local_bones and seen["known_bones"] is None
    assert seen["prior"].prediction_sigma_mm > 0.5


def _with_relations(case, relations):
    """The case's verification views, each related to a first view by ``relations[k]`` (a
    ``(name, carm_after_from_carm_before)`` pair, or None)."""
    views = tuple(
        v if r is None else dataclasses.replace(v, moved_from=r[0], carm_motion=r[1])
        for v, r in zip(case.verification.views, relations, strict=True)
    )
    return dataclasses.replace(case, verification=VerificationViews(case.verification.joints_deg, views))


def _spy_verification(monkeypatch: pytest.MonkeyPatch) -> dict:
    """Wraps the stand-in registration: what the verification's ``register_view_set`` was given."""
    seen: dict = {}
    inner = pipeline.register_view_set

    def register(views, volume, **kw):
        if kw.get("prior") is not None:
            seen.update(views=views, **kw)
        return inner(views, volume, **kw)

    monkeypatch.setattr(pipeline, "register_view_set", register)
    monkeypatch.setattr(verification, "register_view_set", register)
    return seen


def test_views_moved_from_registered_ones_start_there_and_register_their_bones_locally(
    make_no_cm_case, monkeypatch: pytest.MonkeyPatch
) -> None:
    case = _robot_case(make_no_cm_case, monkeypatch, roll_deg=60.0, verify_offset_mm=1.0)
    slide = se3.make(np.eye(3), (-40.0, 15.0, 0.0))
    case = _with_relations(case, [("view0", slide), ("view0", slide)])
    seen = _spy_verification(monkeypatch)
    res = navigate(case, _LOCAL)
    assert res.status == "ok", res.reason
    # the first registration put view0's camera at the identity: each starts at the slide
    for v in seen["views"]:
        np.testing.assert_array_equal(v.camera.camera_from_world, slide)
    assert seen["settings"].local is True and seen["known_bones"] is None
    assert res.stages["verify_detect"].diagnostics["cameras_from_carm_motion"] is True
    # the kinematic prediction's stated σ goes with the prior (> the registration's 0.5 mm alone)
    assert seen["prior"].prediction_sigma_mm > 0.5


def test_one_view_without_a_relation_keeps_every_camera_and_the_whole_ladders(
    make_no_cm_case, monkeypatch: pytest.MonkeyPatch
) -> None:
    case = _robot_case(make_no_cm_case, monkeypatch, roll_deg=60.0, verify_offset_mm=1.0)
    given = [v.camera.camera_from_world for v in case.verification.views]
    case = _with_relations(case, [("view0", se3.make(np.eye(3), (5.0, 0.0, 0.0))), None])
    seen = _spy_verification(monkeypatch)
    navigate(case, _LOCAL)
    assert seen["settings"].local is False
    np.testing.assert_array_equal(seen["views"][1].camera.camera_from_world, given[1])


def test_the_reference_verification_uses_neither_the_carm_motion_nor_the_kinematics(
    make_no_cm_case, monkeypatch: pytest.MonkeyPatch
) -> None:
    from fluoronav.navigation.config import VerificationConfig

    case = _robot_case(make_no_cm_case, monkeypatch, roll_deg=60.0, verify_offset_mm=1.0)
    case = _with_relations(case, [("view0", np.eye(4)), ("view0", np.eye(4))])
    seen = _spy_verification(monkeypatch)
    navigate(case, dataclasses.replace(_CFG, verification=VerificationConfig.reference()))
    assert seen["settings"].local is False and seen["known_bones"] is None
    assert seen["prior"].prediction_sigma_mm is None


@pytest.mark.parametrize("unmoved", [True, False], ids=["anatomy-still", "anatomy-moved"])
def test_unmoved_carm_positions_keep_the_first_bones_where_the_images_agree(
    make_no_cm_case, monkeypatch: pytest.MonkeyPatch, unmoved: bool
) -> None:
    case = _robot_case(make_no_cm_case, monkeypatch, roll_deg=60.0, verify_offset_mm=1.0)
    case = _with_relations(case, [("view0", np.eye(4)), ("view0", np.eye(4))])
    known = SimpleNamespace(name="the first bones")
    asked: list = []

    def unmoved_bones(views, first, same_as, *, min_ncc):
        asked.append((same_as, min_ncc))
        ncc = {v.name: 0.999 if unmoved else 0.95 for v in views}
        return (known if unmoved else None), ncc

    monkeypatch.setattr(verification, "unmoved_bones", unmoved_bones)
    seen = _spy_verification(monkeypatch)
    res = navigate(case, _LOCAL)
    assert asked == [([0, 0], 0.995)]
    assert seen["known_bones"] is (known if unmoved else None)
    diag = res.stages["verify_detect"].diagnostics
    assert diag["bones_from_first_registration"] is unmoved and set(diag["unmoved_ncc"]) == {"view0", "view1"}


@pytest.mark.parametrize(
    ("check", "retried"), [("edge_ncc", True), ("kinematics_disagree", False)], ids=["cm-check", "kinematics"]
)
def test_a_verification_with_local_bones_that_refuses_is_registered_again_with_the_whole_ladders(
    make_no_cm_case, monkeypatch: pytest.MonkeyPatch, check: str, retried: bool
) -> None:
    """The local levels' CM failing its checks: once more with the whole ladders (the first attempt
    kept as ``verify_local_*``); a refusal that names the kinematics is final."""
    from fluoronav.errors import RegistrationRefused

    case = _robot_case(make_no_cm_case, monkeypatch, roll_deg=60.0, verify_offset_mm=1.0)
    slide = se3.make(np.eye(3), (-40.0, 15.0, 0.0))
    case = _with_relations(case, [("view0", slide), ("view0", slide)])
    inner = verification.register_view_set
    local_calls: list[bool] = []

    def register(views, volume, **kw):
        local_calls.append(kw["settings"].local)
        if kw["settings"].local:
            with kw["recorder"]("cm") as rec:
                rec.diagnostics["tries"] = 2
                rec.passed = False
            raise RegistrationRefused("cm", check, "NCC 0.60 (at least 0.70)", view="view0")
        return inner(views, volume, **kw)

    monkeypatch.setattr(verification, "register_view_set", register)
    res = navigate(case, _LOCAL)
    diag = res.stages["verify_detect"].diagnostics
    if not retried:
        assert local_calls == [True] and res.status == "refused" and "kinematics_disagree" in res.reason
        assert "local_bones_refused" not in diag
        return
    assert local_calls == [True, False]
    assert res.status == "ok", res.reason
    assert (
        diag["local_bones_refused"] == "stage verify_cm, view view0, check edge_ncc: NCC 0.60 (at least 0.70)"
    )
    assert res.stages["verify_local_cm"].passed is False and res.stages["verify_cm"].passed is True


def test_a_verification_without_a_detection_is_registered_from_the_prediction(
    make_no_cm_case, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The detector finds the CM in no verification view (images without one, nothing given): the CM
    is registered from the kinematic prediction and goes on with a warning where that passes; where
    it refuses, or with ``register_undetected`` off, the refusal is ``views_with_cm``."""
    case = _robot_case(make_no_cm_case, monkeypatch, roll_deg=60.0, verify_offset_mm=1.0)
    assert case.verification is not None
    blind = tuple(dataclasses.replace(v, landmarks_px=None) for v in case.verification.views)
    case = dataclasses.replace(case, verification=dataclasses.replace(case.verification, views=blind))
    names = ", ".join(v.name for v in blind)
    register = verification.register_view_set
    seen: list[int] = []
    outcome = "passes"

    def blind_register(views, volume, **kw):
        if kw.get("prior") is not None:
            seen.append(sum(v.detection is not None for v in views))
            if outcome == "refuses":
                raise RegistrationRefused("cm", "edge_ncc", "the registered CM's outline matches NCC 0.31")
        return register(views, volume, **kw)

    monkeypatch.setattr(verification, "register_view_set", blind_register)
    res = navigate(case, _CFG)
    assert res.status == "ok", res.reason
    assert seen == [0] and res.joints_correction_deg is not None
    assert len(res.warnings) == 1 and res.warnings[0].startswith(
        f"views_with_cm: the CM was found in none of the verification views ({names})"
    )
    off = dataclasses.replace(_CFG.verification, register_undetected=False)
    for outcome, cfg in (("refuses", _CFG), ("off", dataclasses.replace(_CFG, verification=off))):
        seen.clear()
        res = navigate(case, cfg)
        assert res.status == "refused" and res.joints_correction_deg is None
        assert "stage verify_detect" in res.reason and "check views_with_cm" in res.reason
        assert f"the CM was found in 0 of {len(blind)} views" in res.reason
        if outcome == "refuses":
            assert seen == [0]
            assert (
                "registered from the kinematic prediction on the images alone it failed its checks"
                in res.reason
            )
            assert "check edge_ncc: the registered CM's outline matches NCC 0.31" in res.reason
        else:
            assert seen == [] and "1 needed" in res.reason
