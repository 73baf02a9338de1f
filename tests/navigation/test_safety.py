"""The registration gates: thresholds, leaving a view out, recovery from a second start, refusal.

The registrations are stand-ins here (their diagnostics are given); that the diagnostics flag broken
registrations of physics-simulated images is tested in tests/registration/test_diagnostics.py.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

import fluoronav.navigation.checks as checks
from fluoronav.navigation.checks import register_cm_checked
from fluoronav.navigation.result import NavigationRefused, StageRecord
from fluoronav.navigation.safety import SafetyConfig, judge_cm_views, judge_motion
from fluoronav.registration.cm.diagnostics import CMViewDiagnostics

GOOD = {"landmark_residual_mm": 0.4, "edge_ncc": 0.9}


def test_thresholds_decide_each_view() -> None:
    cfg = SafetyConfig(max_landmark_residual_mm=2.0, min_edge_ncc=0.5)
    diags = [
        GOOD,
        {"landmark_residual_mm": 2.5, "edge_ncc": 0.9},
        {"landmark_residual_mm": None, "edge_ncc": 0.2},
    ]
    v = judge_cm_views(["a", "b", "c"], diags, cfg)
    assert [x.passed for x in v] == [True, False, False]
    assert v[1].check == "landmark_residual" and "2.50 mm" in v[1].detail
    assert v[2].check == "edge_ncc" and "0.20" in v[2].detail
    assert judge_motion({"motion_tip_mm": 2.9}, SafetyConfig(max_motion_tip_mm=3.0)) is None
    m = judge_motion({"motion_tip_mm": 12.0}, SafetyConfig(max_motion_tip_mm=3.0))
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


def _run(
    monkeypatch: pytest.MonkeyPatch,
    bad: dict[tuple[int, str], dict[str, Any]],
    *,
    tries: int = 1,
    motion: dict[int, float] | None = None,
) -> tuple[_Reg, StageRecord, list[list[str]]]:
    """``bad[(start, view)]``: the diagnostics of that view in registrations from that start."""
    calls: list[list[str]] = []
    views = [_View(n, _Camera()) for n in ("AP", "orbit +20", "orbit -15")]

    def multistart(vs: list[_View], starts: list[np.ndarray], **kw: Any) -> _Reg:
        calls.append([v.name for v in vs])
        return _Reg([v.name for v in vs], int(starts[0][0, 3]))

    def single(vs: list[_View], **kw: Any) -> _Reg:
        calls.append([v.name for v in vs])
        return _Reg([v.name for v in vs], int(kw["initial_world_from_cm"][0, 3]))

    def diagnostics(cm: _Reg, lms: list[Any], ps: list[Any]) -> list[CMViewDiagnostics]:
        return [CMViewDiagnostics(**bad.get((cm.start, n), GOOD)) for n in cm.views]

    monkeypatch.setattr(checks, "register_cm_multistart", multistart)
    monkeypatch.setattr(checks, "register_cm", single)
    monkeypatch.setattr(checks, "cm_view_diagnostics", diagnostics)
    starts = []
    for t in range(tries):
        s = np.eye(4)
        s[0, 3] = t
        starts.append([s])
    rec = StageRecord()
    check = None if motion is None else (lambda cm: {"motion_tip_mm": motion[cm.start]})
    cm = register_cm_checked(
        views,  # type: ignore[arg-type]
        [np.zeros((2, 2))] * 3,
        starts,
        rec,
        stage_name="verify_cm",
        initial_control_points_deg=np.zeros(5),
        cm_config=None,  # type: ignore[arg-type]
        safety=SafetyConfig(max_motion_tip_mm=3.0),
        seed=0,
        motion_check=check,
    )
    return cm, rec, calls  # type: ignore[return-value]


def test_every_view_agrees_nothing_is_left_out(monkeypatch: pytest.MonkeyPatch) -> None:
    cm, rec, calls = _run(monkeypatch, {})
    assert cm.views == ["AP", "orbit +20", "orbit -15"] and len(calls) == 1
    assert rec.passed and "left_out" not in rec.diagnostics and rec.diagnostics["tries"] == 1


def test_a_view_that_disagrees_is_left_out_and_the_cm_registered_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    cm, rec, calls = _run(monkeypatch, {(0, "orbit +20"): {"landmark_residual_mm": 0.3, "edge_ncc": 0.05}})
    assert calls == [["AP", "orbit +20", "orbit -15"], ["AP", "orbit -15"]]
    assert cm.views == ["AP", "orbit -15"]
    assert rec.diagnostics["left_out"]["orbit +20"].startswith("edge_ncc")
    assert rec.diagnostics["views_used"] == ["AP", "orbit -15"]


def test_too_few_views_left_refuses_naming_the_view_and_check(monkeypatch: pytest.MonkeyPatch) -> None:
    far = {"landmark_residual_mm": 9.0, "edge_ncc": 0.9}
    with pytest.raises(NavigationRefused) as err:
        _run(monkeypatch, {(0, "AP"): far, (0, "orbit -15"): far})
    assert err.value.stage == "verify_cm" and err.value.check == "landmark_residual"
    assert err.value.view == "AP"
    assert str(err.value).startswith(
        "stage verify_cm, view AP, check landmark_residual: registered landmarks 9.00 mm"
    )


def test_a_failed_motion_check_recovers_from_the_second_start(monkeypatch: pytest.MonkeyPatch) -> None:
    cm, rec, calls = _run(monkeypatch, {}, tries=2, motion={0: 14.0, 1: 0.8})
    assert cm.start == 1 and len(calls) == 2
    assert rec.diagnostics["tries"] == 2 and rec.diagnostics["motion_tip_mm"] == 0.8


def test_motion_that_disagrees_from_every_start_refuses(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(NavigationRefused) as err:
        _run(monkeypatch, {}, tries=2, motion={0: 14.0, 1: 9.5})
    assert err.value.check == "robot_motion" and "9.5 mm" in err.value.detail
