"""The CM registration's checks: thresholds, leaving a view out, recovery from a second start,
agreement with a predicted pose, refusal.

The registrations are stand-ins here (their diagnostics are given); that the diagnostics flag broken
registrations of physics-simulated images is tested in test_diagnostics.py.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

import fluoronav.registration.cm.checks as checks
from fluoronav.errors import RegistrationRefused
from fluoronav.geometry import se3
from fluoronav.manipulator.config import CMConfig
from fluoronav.registration.cm.checks import (
    CMCheckConfig,
    PredictedCMPose,
    judge_cm_views,
    judge_motion,
    judge_shape,
    motion_agreement,
    register_cm_checked,
    shape_departure_sigmas,
)
from fluoronav.registration.cm.diagnostics import CMViewDiagnostics

GOOD: dict[str, Any] = {"landmark_residual_mm": 0.4, "edge_ncc": 0.9}


def test_thresholds_decide_each_view() -> None:
    cfg = CMCheckConfig(max_landmark_residual_mm=2.0, min_edge_ncc=0.5)
    diags: list[dict[str, Any]] = [
        GOOD,
        {"landmark_residual_mm": 2.5, "edge_ncc": 0.9},
        {"landmark_residual_mm": None, "edge_ncc": 0.2},
    ]
    v = judge_cm_views(["a", "b", "c"], diags, cfg)
    assert [x.passed for x in v] == [True, False, False]
    assert v[1].check == "landmark_residual" and "2.50 mm" in v[1].detail
    assert v[2].check == "edge_ncc" and "0.20" in v[2].detail
    assert judge_motion({"motion_tip_mm": 2.9}, 3.0) is None
    m = judge_motion({"motion_tip_mm": 12.0}, 3.0)
    assert m is not None and m.check == "robot_motion" and "12.0 mm" in m.detail


@dataclass
class _Reg:
    """A stand-in CM registration: which views it used and which start it came from."""

    views: list[str]
    start: int
    world_from_cm: np.ndarray = field(default_factory=lambda: np.eye(4)[None])
    control_points_deg: np.ndarray = field(default_factory=lambda: np.zeros(5))
    cost: float = 1.0
    converged: bool = True
    reason: str = "converged"


@dataclass
class _View:
    name: str
    camera: Any = None


class _Camera:
    pixel_spacing_mm = 0.388


@dataclass
class _Config:
    cm_config: CMConfig = field(default_factory=CMConfig)
    control_point_sigma_deg: float | None = 0.1
    control_point_tolerance_deg: float = 0.0


def _run(
    monkeypatch: pytest.MonkeyPatch,
    bad: dict[tuple[int, str], dict[str, Any]],
    *,
    tries: int = 1,
    motion: dict[int, float] | None = None,
    shape: dict[int, np.ndarray] | None = None,
    priors: list[Any] | None = None,
) -> tuple[_Reg, dict[str, Any], list[list[str]]]:
    """``bad[(start, view)]``: the diagnostics of that view in registrations from that start;
    ``motion[start]``: the tip's distance from the predicted pose of registrations from that start;
    ``shape[start]``: the control points registered from that start (the FBG reading is 0, σ 0.1°,
    checked at 4 σ where given); ``priors`` collects the prior centre of continued registrations."""
    calls: list[list[str]] = []
    views = [_View(n, _Camera()) for n in ("AP", "orbit +20", "orbit -15")]

    def reg(vs: list[_View], start: int) -> _Reg:
        cp = np.zeros(5) if shape is None else shape[start]
        return _Reg([v.name for v in vs], start, control_points_deg=cp)

    def multistart(vs: list[_View], starts: list[np.ndarray], **kw: Any) -> _Reg:
        calls.append([v.name for v in vs])
        return reg(vs, int(starts[0][0, 3]))

    def single(vs: list[_View], **kw: Any) -> _Reg:
        calls.append([v.name for v in vs])
        if priors is not None:
            priors.append(kw["prior_control_points_deg"])
        return reg(vs, int(kw["initial_world_from_cm"][0, 3]))

    def diagnostics(cm: _Reg, lms: list[Any], ps: list[Any]) -> list[CMViewDiagnostics]:
        return [CMViewDiagnostics(**bad.get((cm.start, n), GOOD)) for n in cm.views]

    def agreement(predicted: PredictedCMPose, cm: _Reg, cm_config: CMConfig) -> dict[str, float]:
        assert motion is not None
        return {"motion_tip_mm": motion[cm.start], "motion_rotation_deg": 0.0}

    monkeypatch.setattr(checks, "register_cm_multistart", multistart)
    monkeypatch.setattr(checks, "register_cm", single)
    monkeypatch.setattr(checks, "cm_view_diagnostics", diagnostics)
    monkeypatch.setattr(checks, "motion_agreement", agreement)
    starts = []
    for t in range(tries):
        s = np.eye(4)
        s[0, 3] = t
        starts.append([s])
    diag: dict[str, Any] = {}
    cm = register_cm_checked(
        views,  # type: ignore[arg-type]
        [np.zeros((2, 2))] * 3,
        starts,
        diag,
        initial_control_points_deg=np.zeros(5),
        config=_Config(),  # type: ignore[arg-type]
        checks=CMCheckConfig(max_shape_departure_sigmas=None if shape is None else 4.0),
        seed=0,
        predicted=None if motion is None else PredictedCMPose(np.eye(4), np.eye(4), max_tip_mm=3.0),
    )
    return cm, diag, calls  # type: ignore[return-value]


def test_every_view_agrees_nothing_is_left_out(monkeypatch: pytest.MonkeyPatch) -> None:
    cm, diag, calls = _run(monkeypatch, {})
    assert cm.views == ["AP", "orbit +20", "orbit -15"] and len(calls) == 1
    assert "left_out" not in diag and diag["tries"] == 1 and "motion_tip_mm" not in diag


def test_a_view_that_disagrees_is_left_out_and_the_cm_registered_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    cm, diag, calls = _run(monkeypatch, {(0, "orbit +20"): {"landmark_residual_mm": 0.3, "edge_ncc": 0.05}})
    assert calls == [["AP", "orbit +20", "orbit -15"], ["AP", "orbit -15"]]
    assert cm.views == ["AP", "orbit -15"]
    assert diag["left_out"]["orbit +20"].startswith("edge_ncc")
    assert diag["views_used"] == ["AP", "orbit -15"]


def test_too_few_views_left_refuses_naming_the_view_and_check(monkeypatch: pytest.MonkeyPatch) -> None:
    far = {"landmark_residual_mm": 9.0, "edge_ncc": 0.9}
    with pytest.raises(RegistrationRefused) as err:
        _run(monkeypatch, {(0, "AP"): far, (0, "orbit -15"): far})
    assert err.value.stage == "cm" and err.value.check == "landmark_residual"
    assert err.value.view == "AP"
    assert str(err.value).startswith(
        "stage cm, view AP, check landmark_residual: registered landmarks 9.00 mm"
    )


def test_a_failed_motion_check_recovers_from_the_second_start(monkeypatch: pytest.MonkeyPatch) -> None:
    cm, diag, calls = _run(monkeypatch, {}, tries=2, motion={0: 14.0, 1: 0.8})
    assert cm.start == 1 and len(calls) == 2
    assert diag["tries"] == 2 and diag["motion_tip_mm"] == 0.8


def test_motion_that_disagrees_from_every_start_refuses(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(RegistrationRefused) as err:
        _run(monkeypatch, {}, tries=2, motion={0: 14.0, 1: 9.5})
    assert err.value.check == "robot_motion" and "9.5 mm" in err.value.detail


def test_motion_agreement_is_measured_in_the_reference_frame() -> None:
    """The registered pose relative to the reference against the predicted one: the tip's distance
    and the rotation between them, whatever the reference's own pose."""
    cfg = CMConfig()
    cp = np.full(cfg.n_control_points, 4.0)
    ct_from_femur = se3.make(
        np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), [10.0, -20.0, 30.0]
    )
    femur_from_cm = se3.make(np.eye(3), [1.0, 2.0, 3.0])
    shift = se3.make(np.eye(3), [0.0, 0.0, 2.5])  # 2.5 mm along the CM's own z

    @dataclass
    class _CM:
        world_from_cm: np.ndarray
        control_points_deg: np.ndarray

    same = _CM((ct_from_femur @ femur_from_cm)[None], cp)
    moved = _CM((ct_from_femur @ femur_from_cm @ shift)[None], cp)
    predicted = PredictedCMPose(ct_from_femur, femur_from_cm)
    a = motion_agreement(predicted, same, cfg)  # type: ignore[arg-type]
    assert a["motion_tip_mm"] == pytest.approx(0.0, abs=1e-9)
    assert a["motion_rotation_deg"] == pytest.approx(0.0, abs=1e-5)
    b = motion_agreement(predicted, moved, cfg)  # type: ignore[arg-type]
    assert b["motion_tip_mm"] == pytest.approx(2.5, abs=1e-9)
    assert judge_motion(b, 2.0) is not None and judge_motion(b, predicted.max_tip_mm) is None


def test_shape_departure_is_counted_beyond_the_tolerance_in_sigmas() -> None:
    reading = np.array([1.0, -2.0, 0.0, 0.5, 3.0])
    x = reading + np.array([0.3, -1.5, 0.2, 0.0, 0.9])
    # |Δ| − τ = (0.0, 1.2, 0, 0, 0.6) over σ 0.25
    assert shape_departure_sigmas(x, reading, sigma_deg=0.25, tolerance_deg=0.3) == pytest.approx(4.8)
    assert shape_departure_sigmas(reading, reading, sigma_deg=0.1, tolerance_deg=0.0) == 0.0


def test_a_shape_pulled_off_the_fbg_reading_fails_naming_the_fbg() -> None:
    cfg = _Config(control_point_sigma_deg=0.1)
    near = _Reg(["AP"], 0, control_points_deg=np.array([0.0, 0.3, -0.2, 0.0, 0.1]))
    dep, verdict = judge_shape(near, np.zeros(5), cfg, 4.0)  # type: ignore[arg-type]
    assert dep == pytest.approx(3.0) and verdict is None
    far = _Reg(["AP"], 0, control_points_deg=np.array([0.0, 0.3, -0.62, 0.0, 0.1]))
    dep, verdict = judge_shape(far, np.zeros(5), cfg, 4.0)  # type: ignore[arg-type]
    assert dep == pytest.approx(6.2) and verdict is not None and verdict.check == "fbg_shape"
    assert "-0.62° at control point 2" in verdict.detail and "FBG" in verdict.detail


def test_a_shape_check_failure_tries_the_next_start_then_refuses(monkeypatch: pytest.MonkeyPatch) -> None:
    off = np.array([0.0, 0.0, 1.0, 0.0, 0.0])  # 10 σ of a 0.1° reading
    cm, diag, _ = _run(monkeypatch, {}, tries=2, shape={0: off, 1: np.full(5, 0.05)})
    assert cm.start == 1 and diag["fbg_departure_sigmas"] == pytest.approx(0.5)
    with pytest.raises(RegistrationRefused) as err:
        _run(monkeypatch, {}, tries=2, shape={0: off, 1: off})
    assert err.value.stage == "cm" and err.value.check == "fbg_shape" and err.value.view == ""


def test_a_continued_registration_keeps_its_prior_on_the_reading(monkeypatch: pytest.MonkeyPatch) -> None:
    """After a view is left out the CM is registered again from its result: its shape starts there,
    but the prior stays centred on the reading, not on the shape it had settled at."""
    priors: list[Any] = []
    settled = np.full(5, 0.2)
    bad = {(0, "orbit +20"): {"landmark_residual_mm": 0.3, "edge_ncc": 0.05}}
    _run(monkeypatch, bad, shape={0: settled}, priors=priors)
    assert len(priors) == 1 and np.array_equal(priors[0], np.zeros(5))
