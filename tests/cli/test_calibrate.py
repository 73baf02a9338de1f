"""``fluoronav calibrate``: case-file errors and (slow) a simulated example case end to end."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from fluoronav.cli.calibrate import load_calibration_case
from fluoronav.errors import InputError


def test_malformed_case_names_the_file(tmp_path) -> None:
    p = tmp_path / "case.json"
    p.write_text("{not json")
    with pytest.raises(InputError) as e:
        load_calibration_case(p)
    assert str(p) in str(e.value)
    p.write_text(json.dumps({"views": []}))
    with pytest.raises(InputError, match="camera"):
        load_calibration_case(p)


def test_cli_reports_a_bad_case_in_one_line(tmp_path, capsys) -> None:
    from fluoronav.cli.main import main

    p = tmp_path / "case.json"
    p.write_text("[]")
    with pytest.raises(SystemExit) as e:
        main(["calibrate", str(p), "--out", str(tmp_path / "out")])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert str(p) in err and len(err.splitlines()) == 1


@pytest.mark.slow
def test_calibrate_example_case_writes_handeye_json(tmp_path) -> None:
    from fluoronav.cli.calibrate import write_example_calibration_case
    from fluoronav.cli.main import app

    case = write_example_calibration_case(tmp_path / "case", seed=1, n_poses=4, image_size=384)
    r = CliRunner().invoke(app, ["calibrate", str(case), "--out", str(tmp_path / "out"), "--device", "cpu"])
    assert r.exit_code == 0, r.output
    d = json.loads((tmp_path / "out" / "handeye.json").read_text())
    assert d["ok"] and len(d["ee_from_cm"]) == 4
    assert set(d["landmark_residuals_px"]) == {f"pose{m}" for m in range(4)}
    assert "TSAI" in d["tracker_baselines"] and "eq9_vs_eq10_mm" in d["tracker_baselines"]["TSAI"]
    assert d["errors"]["handeye_rotation_deg"] < 3.0
    assert (tmp_path / "out" / "trace.json").is_file() and (tmp_path / "out" / "overlay_pose0.png").is_file()
