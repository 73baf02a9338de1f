"""``fluoronav simulate --world --scenes``: a world file's data set of navigation scenes, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from fluoronav.anatomy.io import save_volume
from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.cli.main import main
from fluoronav.simulation.dataset_check import check_dataset


def _one_line_exit_2(args: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    return err


def test_world_file_navigation_data_set(tmp_path: Path) -> None:
    world = tmp_path / "coarse_or.json"
    world.write_text(
        json.dumps(
            {
                "ct": {"patient_spacing_mm": 2.0},
                "carm": {"flex_detector_shift_mm": 1.0},
                "instrument": {"angle_scale_sd": 0.07, "notch_depth_sd_mm": 0.02},
            }
        )
    )
    out = tmp_path / "ds"
    common = ["simulate", "--n", "2", "--out", str(out), "--size", "64", "--workers", "0", "--seed", "12"]
    main([*common, "--world", str(world), "--scenes", "navigation"])
    assert check_dataset(out, n=2) == []
    rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    assert {r["world"] for r in rows} == {"coarse_or"} and {r["scene"] for r in rows} == {"navigation"}
    meta = json.loads((out / "dataset.json").read_text())
    assert meta["world"]["name"] == "coarse_or" and meta["world"]["ct"]["patient_spacing_mm"] == 2.0
    assert meta["spec"]["scenes"] == "navigation" and meta["seed"] == 12
    main([*common, "--world", str(world), "--scenes", "navigation"])  # rerun: nothing left to do
    assert len((out / "manifest.jsonl").read_text().splitlines()) == 2


def test_bad_world_and_scenes_are_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    common = ["simulate", "--n", "1", "--out", str(out), "--workers", "0"]
    assert "mars" in _one_line_exit_2([*common, "--world", "mars"], capsys)
    bad = tmp_path / "w.json"
    bad.write_text('{"carm": {"flex_mm": 1}}')
    assert "w.json" in _one_line_exit_2([*common, "--world", str(bad)], capsys)
    with pytest.raises(SystemExit) as exc:  # a usage error
        main([*common, "--scenes", "robot"])
    assert exc.value.code == 2 and "scenes must be one of" in capsys.readouterr().err
    assert not out.exists()  # nothing written


def test_navigation_scenes_need_a_labelled_ct(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    ph = hip_phantom(seed=2, spacing_mm=4.0)
    ct = tmp_path / "bare.nii.gz"
    save_volume(ph.replace(labels=None, label_names={}, landmarks_world={}), ct)
    out = tmp_path / "out"
    args = ["simulate", "--n", "1", "--out", str(out), "--ct", str(ct), "--workers", "0", "--scenes", "mixed"]
    err = _one_line_exit_2(args, capsys)
    assert "bare.nii.gz" in err and "femur_left" in err
    assert not out.exists()
