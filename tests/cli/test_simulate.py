"""``fluoronav simulate``: help, bad input, and a held-out run on an unlabelled CT file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from fluoronav.anatomy.io import load_ct, save_volume
from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.cli.main import main
from fluoronav.simulation.dataset_check import check_dataset
from fluoronav.simulation.scene import BONE_HU


def test_help_documents_every_option() -> None:
    from fluoronav.cli.main import app

    result = CliRunner().invoke(app, ["simulate", "--help"], terminal_width=200)
    assert result.exit_code == 0
    for opt in (
        "--n",
        "--out",
        "--ct",
        "--seed",
        "--scheduler",
        "--workers",
        "--no-cm",
        "--size",
        "--phantoms",
        "--max-projected-ab-mm",
        "--max-shaft-mm",
        "--max-shaft-angle-deg",
        "--shaft-length-mm",
        "--world",
        "--scenes",
        "--navigation-fraction",
        "--device",
    ):
        assert opt in result.output
    assert "binned" in result.output  # the storage resolution is explained


def test_bad_ct_is_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "broken.nii.gz"
    bad.write_bytes(b"not a nifti")
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--n", "1", "--out", str(tmp_path / "out"), "--ct", str(bad), "--workers", "0"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "broken.nii.gz" in err
    assert not (tmp_path / "out").exists()  # nothing written


@pytest.fixture(scope="module")
def real_ct(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An unlabelled CT file: a cropped phantom with rotated direction cosines, no sibling files."""
    ph = hip_phantom(seed=3, spacing_mm=2.0)
    data = np.ascontiguousarray(ph.data[10:-10, 5:-5, 20:-20])
    c, s = np.cos(np.deg2rad(25.0)), np.sin(np.deg2rad(25.0))
    direction = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # rotated about z
    vol = ph.replace(
        data=data,
        labels=None,
        label_names={},
        landmarks_world={},
        direction=direction,
        origin_mm=(12.0, -30.0, 100.0),
        name="held_out",
    )
    path = tmp_path_factory.mktemp("ct") / "held_out.nii.gz"
    written = save_volume(vol, path)
    assert written == [path]  # no labels, no landmarks
    return path


def test_held_out_ct_and_seed_pass_the_contract(real_ct: Path, tmp_path: Path) -> None:
    out = tmp_path / "ds"
    args = [
        "simulate",
        "--n",
        "3",
        "--out",
        str(out),
        "--ct",
        str(real_ct),
        "--seed",
        "90210",
        "--size",
        "64",
        "--workers",
        "0",
    ]
    main(args)  # returns normally on success
    assert check_dataset(out, n=3) == []
    ct = load_ct(real_ct)
    assert ct.labels is None and not ct.landmarks_world
    for line in (out / "manifest.jsonl").read_text().splitlines():
        row = json.loads(line)
        assert row["ct"] == "held_out.nii.gz" and row["femur_side"] == ""
        # the CM sits in the bone nearest the volume centre
        a = np.asarray(row["world_from_cm"])[:, 3]
        i, j, k = np.round((ct.index_from_world @ a)[:3]).astype(int)
        assert ct.data[k, j, i] > BONE_HU
    assert (out / "contact_sheet.png").exists()
