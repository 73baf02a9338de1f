"""Landmark files: FCSV (RAS/LPS, numeric coordinate system, columns header) and JSON."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from fluoronav.anatomy.landmarks import (
    read_fcsv,
    read_landmarks,
    read_landmarks_json,
    write_fcsv,
    write_landmarks,
    write_landmarks_json,
)
from fluoronav.errors import InputError

POINTS = {"femoral_head_left": np.array([84.0, -10.5, -30.25]), "entry_left": np.array([149.3, 5.4, -55.6])}

SLICER_RAS = """# Markups fiducial file version = 4.11
# CoordinateSystem = RAS
# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID
vtkMRMLMarkupsFiducialNode_0,-84,10.5,-30.25,0,0,0,1,1,1,0,femoral_head_left,,vtkMRMLScalarVolumeNode1
vtkMRMLMarkupsFiducialNode_1,-149.3,-5.4,-55.6,0,0,0,1,1,1,0,entry_left,,
"""


def _assert_points(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    assert list(got) == list(want)
    for k in want:
        np.testing.assert_allclose(got[k], want[k], rtol=0, atol=1e-12)


def test_fcsv_ras_is_converted_to_lps(tmp_path: Path) -> None:
    f = tmp_path / "m.fcsv"
    f.write_text(SLICER_RAS)
    _assert_points(read_fcsv(f), POINTS)


@pytest.mark.parametrize(("line", "flip"), [("1", False), ("0", True), ("LPS", False), ("ras", True)])
def test_fcsv_numeric_and_named_coordinate_systems(tmp_path: Path, line: str, flip: bool) -> None:
    f = tmp_path / "m.fcsv"
    f.write_text(
        f"# Markups fiducial file version = 4.4\n# CoordinateSystem = {line}\nF_1,1,2,3,0,0,0,1,1,1,0,a,,\n"
    )
    want = np.array([-1.0, -2.0, 3.0]) if flip else np.array([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(read_fcsv(f)["a"], want)


def test_fcsv_custom_columns_and_default_ras(tmp_path: Path) -> None:
    f = tmp_path / "m.fcsv"
    f.write_text("# columns = label,z,y,x\np,3,2,1\n")  # no coordinate-system line → RAS
    np.testing.assert_array_equal(read_fcsv(f)["p"], [-1.0, -2.0, 3.0])


@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_fcsv_round_trip(tmp_path: Path, system: str) -> None:
    f = write_fcsv(tmp_path / "m.fcsv", POINTS, coordinate_system=system)
    assert f"CoordinateSystem = {system}" in f.read_text()
    _assert_points(read_landmarks(f), POINTS)


@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_json_round_trip(tmp_path: Path, system: str) -> None:
    f = write_landmarks_json(tmp_path / "m.json", POINTS, coordinate_system=system)
    doc = json.loads(f.read_text())
    assert doc["coordinate_system"] == system
    if system == "RAS":
        assert doc["landmarks"]["femoral_head_left"][0] == -84.0
    _assert_points(read_landmarks_json(f), POINTS)
    _assert_points(read_landmarks(write_landmarks(tmp_path / "n.json", POINTS)), POINTS)


@pytest.mark.parametrize(
    ("name", "text", "fragment"),
    [
        ("empty.fcsv", "", "empty"),
        ("bad.fcsv", "# CoordinateSystem = LPS\nF_1,1,2\n", "line 2"),
        ("nan.fcsv", "# CoordinateSystem = LPS\nF_1,1,x,3,0,0,0,1,1,1,0,a,,\n", "line 2"),
        ("inf.fcsv", "# CoordinateSystem = LPS\nF_1,1,inf,3,0,0,0,1,1,1,0,a,,\n", "line 2"),
        ("cs.fcsv", "# CoordinateSystem = IJK\nF_1,1,2,3\n", "line 1"),
        (
            "dup.fcsv",
            "# CoordinateSystem = 1\nF_1,1,2,3,0,0,0,1,1,1,0,a,,\nF_2,1,2,3,0,0,0,1,1,1,0,a,,\n",
            "line 3",
        ),
        ("cols.fcsv", "# columns = id,a,b,c\nF,1,2,3\n", "line 1"),
        ("only_header.fcsv", "# CoordinateSystem = LPS\n", "no landmarks"),
        ("bad.json", '{"landmarks": {\n "a": [1, 2, 3],\n}', "line 3"),
        ("shape.json", '{"landmarks": {"a": [1, 2]}}', "'a'"),
        ("bool.json", '{"landmarks": {"a": [1, true, 3]}}', "'a'"),
        ("nolm.json", '{"points": {}}', "landmarks"),
        ("cs.json", '{"coordinate_system": "XYZ", "landmarks": {"a": [1, 2, 3]}}', "coordinate system"),
        ("ext.txt", "1,2,3", "unknown landmark file type"),
    ],
)
def test_malformed_landmark_files_name_the_file(tmp_path: Path, name: str, text: str, fragment: str) -> None:
    f = tmp_path / name
    f.write_text(text)
    with pytest.raises(InputError) as info:
        read_landmarks(f)
    assert info.value.source == str(f)
    assert fragment in info.value.problem
    assert "\n" not in str(info.value)


def test_missing_landmark_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        read_landmarks(tmp_path / "nope.fcsv")
