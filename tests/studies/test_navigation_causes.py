"""The navigation study's refusals: each row's true and named cause, and the fraction named right."""

from __future__ import annotations

from fluoronav.navigation.config import NavigationConfig
from fluoronav.navigation.result import NavigationResult
from fluoronav.simulation.navigation.loop import SimulatedNavigation, SimulatedNavigationConfig
from fluoronav.studies.handeye_study import HandEyeStudyConfig, _columns, refusals_named_right
from fluoronav.studies.handeye_trials import NAVIGATION_CAUSES, navigation_row


def test_a_refused_trials_row_carries_the_known_and_the_named_cause() -> None:
    res = NavigationResult(config=NavigationConfig())
    res.status, res.reason = "refused", "stage verify_cm, view AP (verify), check kinematics_disagree: …"
    run = SimulatedNavigation(config=SimulatedNavigationConfig(), result=res)
    run.causes = {
        "true_cause": "wrong_detection",
        "named_cause": "hand_eye_or_joints",
        "cause_named_right": False,
        "wrong_detection_views": {"AP after the move": 12.3},
    }
    cfg = HandEyeStudyConfig(workflow="navigation", trials=1, seed=0)
    row = navigation_row(run, cfg)
    assert (row["true_cause"], row["named_cause"], row["cause_named_right"]) == (
        "wrong_detection",
        "hand_eye_or_joints",
        False,
    )
    assert row["check"] == "kinematics_disagree"
    # the columns close the row: a study resumed from before them keeps its columns where they were
    assert _columns(cfg)[-len(NAVIGATION_CAUSES) :] == list(NAVIGATION_CAUSES)
    ok = SimulatedNavigation(
        config=SimulatedNavigationConfig(), result=NavigationResult(config=NavigationConfig())
    )
    assert not set(NAVIGATION_CAUSES) & set(navigation_row(ok, cfg))


def test_the_summary_gives_the_fraction_of_refusals_named_right() -> None:
    """Rows as ``trials.csv`` reads them back (strings, empty cells where the trial went on)."""

    def row(true: str, named: str, right: str, status: str = "refused") -> dict[str, str]:
        return {"status": status, "true_cause": true, "named_cause": named, "cause_named_right": right}

    rows = [
        row("", "", "", status="ok"),
        row("wrong_detection", "wrong_detection", "True"),
        row("wrong_detection", "hand_eye_or_joints", "False"),
        row("wrong_detection", "wrong_detection", "True"),
        row("hand_eye", "hand_eye_or_joints", "True"),
        row("none_known", "unnamed", ""),
    ]
    out = refusals_named_right(rows)
    assert out["fraction"] == 0.75
    assert (out["named_right"], out["known_cause"], out["refusals"]) == (3, 4, 5)
    assert out["named_by_true_cause"] == {
        "wrong_detection": {"wrong_detection": 2, "hand_eye_or_joints": 1},
        "hand_eye": {"hand_eye_or_joints": 1},
        "none_known": {"unnamed": 1},
    }
    assert refusals_named_right([row("", "", "", status="ok")])["fraction"] is None
