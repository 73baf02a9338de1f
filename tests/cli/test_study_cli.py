"""``fluoronav study``: one sub-command per workflow, each with its own options only."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from fluoronav.cli.main import app

WORKFLOWS = ("centerline", "single-view", "multi-view", "multi-cm", "hand-eye", "navigation", "deepfluoro")


def _help(*args: str) -> str:
    result = CliRunner().invoke(app, [*args, "--help"], terminal_width=200, env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    return result.output


def test_study_lists_every_workflow() -> None:
    text = _help("study")
    assert all(w in text for w in WORKFLOWS)


@pytest.mark.parametrize(
    ("workflow", "takes", "refuses"),
    [
        ("single-view", ("--trials", "--ct", "--init", "--phantoms", "--world"), ("--fault", "--poses")),
        ("hand-eye", ("--poses", "--calibration-bend-deg", "--image-size"), ("--world", "--fault", "--init")),
        (
            "navigation",
            ("--fault", "--verify-views", "--handeye-error-mm", "--corrections", "--world"),
            ("--poses", "--init", "--phantoms"),
        ),
        ("deepfluoro", ("--data", "--specimen", "--xreg-gt-correction"), ("--ct", "--world")),
    ],
)
def test_each_workflow_takes_its_own_options(
    workflow: str, takes: tuple[str, ...], refuses: tuple[str, ...]
) -> None:
    text = _help("study", workflow)
    assert all(o in text for o in takes)
    assert not any(o in text for o in refuses)
