"""A navigation without verification images says it is unverified (navigation.json and the report)."""

from __future__ import annotations

from fluoronav.navigation.config import NavigationConfig
from fluoronav.navigation.outputs.report import _banner
from fluoronav.navigation.pipeline import NavigationRefused
from fluoronav.navigation.result import NavigationResult


def test_a_result_without_verification_is_unverified_in_json_and_report() -> None:
    res = NavigationResult(config=NavigationConfig())
    assert res.status == "ok" and res.verified is False
    assert res.to_json()["verified"] is False
    assert "UNVERIFIED" in _banner(res) and "hand-eye" in _banner(res)


def test_a_passed_verification_is_verified_and_a_refusal_is_not() -> None:
    res = NavigationResult(config=NavigationConfig())
    res.verification = object()  # type: ignore[assignment]  # only its presence matters here
    assert res.verified is True and "UNVERIFIED" not in _banner(res)
    res.refuse(NavigationRefused("verify_cm", "edge_ncc", "NCC 0.10"))
    assert res.verified is False and "REFUSED" in _banner(res)


def test_a_warning_of_a_result_that_stands_is_shown_and_dropped_with_a_refusal() -> None:
    res = NavigationResult(config=NavigationConfig())
    res.warnings.append("the CM is 7.2 mm from where the robot's kinematics put it")
    assert res.to_json()["warnings"] == res.warnings
    res.verification = object()  # type: ignore[assignment]
    assert "Warning</b>: the CM is 7.2 mm" in _banner(res)
    res.refuse(NavigationRefused("correct", "correction_length", "12 mm"))
    assert "Warning" not in _banner(res)
