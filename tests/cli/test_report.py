"""``fluoronav report``: Table I from study summaries; bad directories give one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fluoronav.cli.main import main


def _summary(d: Path, workflow: str, tip: float) -> None:
    d.mkdir(parents=True)
    stats = {"mean": tip, "std": 0.1, "median": tip, "p95": tip + 0.2, "n": 20}
    (d / "summary.json").write_text(
        json.dumps(
            {
                "workflow": workflow,
                "trials": 20,
                "completed": 20,
                "failed": 0,
                "metrics": {"tip_mm": stats},
                "seconds_per_trial": {"median": 12.0, "p95": 20.0},
                "device": "cpu",
                "version": "0.1.0",
            }
        ),
        encoding="utf-8",
    )


def test_report_writes_table_with_paper_rows(tmp_path: Path) -> None:
    _summary(tmp_path / "sv", "single-view", 0.8)
    _summary(tmp_path / "mv", "multi-view", 0.3)
    main(["report", str(tmp_path / "sv"), str(tmp_path / "mv"), "--out", str(tmp_path / "r")])
    md = (tmp_path / "r" / "table_i.md").read_text(encoding="utf-8")
    assert "0.80 ± 0.10 (0.80)" in md
    assert "1.65 ± 1.13 (1.33)" in md  # the paper's single-view tip row
    assert "Gao et al. 2022" in md
    assert "<table>" in (tmp_path / "r" / "report.html").read_text(encoding="utf-8")


def test_report_rejects_non_study_dir(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["report", str(tmp_path), "--out", str(tmp_path / "r")])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "no summary.json" in err and len(err.splitlines()) == 1


def test_report_shows_refusals_and_unflagged_gross_failures(tmp_path: Path) -> None:
    _summary(tmp_path / "nav", "navigation", 0.5)
    s = json.loads((tmp_path / "nav" / "summary.json").read_text(encoding="utf-8"))
    s.update(
        refused=2,
        refusal_reasons={"stage verify_cm, check robot_motion: 9 mm": 2},
        unflagged_gross_failures=1,
    )
    (tmp_path / "nav" / "summary.json").write_text(json.dumps(s), encoding="utf-8")
    main(["report", str(tmp_path / "nav"), "--out", str(tmp_path / "r")])
    md = (tmp_path / "r" / "table_i.md").read_text(encoding="utf-8")
    assert "| navigation (nav) | 20 | 0 | 2 | 1 | 2× stage verify_cm, check robot_motion: 9 mm |" in md
    assert "2 refused" in (tmp_path / "r" / "report.html").read_text(encoding="utf-8")
