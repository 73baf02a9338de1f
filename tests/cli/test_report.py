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
