"""Slicer markups JSON (.mrk.json): reading (LPS/RAS, labels, skipped points), writing, schema
structure, the landmark-reader dispatch and InputErrors naming the file."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fluoronav.anatomy.landmarks import read_landmarks, write_landmarks
from fluoronav.anatomy.markups import (
    MARKUPS_SCHEMA_ID,
    read_markup_nodes,
    read_markups,
    write_markups,
)
from fluoronav.errors import InputError

POINTS = {
    "femoral_head_left": np.array([84.0, -10.5, -30.25]),
    "entry_left": np.array([149.3, 5.4, -55.6]),
    "trochanter": np.array([-1.5, 2.0e-3, 7.0]),
}

# A point list as Slicer 5 writes it (no "name": the node is named after the file), in RAS, with an
# unlabelled point and a point whose position is not set.
SLICER_RAS = """{
    "@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/Schema/markups-schema-v1.0.3.json#",
    "markups": [
        {
            "type": "Fiducial",
            "coordinateSystem": "RAS",
            "coordinateUnits": "mm",
            "locked": false,
            "fixedNumberOfControlPoints": false,
            "labelFormat": "%N-%d",
            "lastUsedControlPointNumber": 3,
            "controlPoints": [
                {
                    "id": "1", "label": "femoral_head_left", "description": "", "associatedNodeID": "",
                    "position": [-84.0, 10.5, -30.25],
                    "orientation": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                    "selected": true, "locked": false, "visibility": true, "positionStatus": "defined"
                },
                {
                    "id": "2", "label": "", "description": "", "associatedNodeID": "vtkMRMLScalarVolumeNode1",
                    "position": [-149.3, -5.4, -55.6],
                    "orientation": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                    "selected": true, "locked": false, "visibility": true, "positionStatus": "defined"
                },
                {
                    "id": "3", "label": "not_placed", "description": "", "associatedNodeID": "",
                    "position": "",
                    "orientation": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                    "selected": true, "locked": false, "visibility": true, "positionStatus": "undefined"
                }
            ],
            "measurements": [],
            "display": {"visibility": true, "opacity": 1.0, "color": [0.4, 1.0, 1.0]}
        }
    ]
}
"""


def _assert_points(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    assert list(got) == list(want)
    for k in want:
        np.testing.assert_allclose(got[k], want[k], rtol=0, atol=1e-12)


def test_slicer_ras_file_reads_as_lps_with_generated_label(tmp_path: Path) -> None:
    f = tmp_path / "F.mrk.json"
    f.write_text(SLICER_RAS)
    got = read_markups(f)
    # RAS (-84, 10.5, -30.25) is LPS (84, -10.5, -30.25); the unlabelled 2nd point of node "F" is
    # "F-2"; the undefined 3rd point is skipped
    _assert_points(
        got,
        {"femoral_head_left": np.array([84.0, -10.5, -30.25]), "F-2": np.array([149.3, 5.4, -55.6])},
    )


def test_absent_coordinate_system_is_lps_and_name_labels_points(tmp_path: Path) -> None:
    f = tmp_path / "x.mrk.json"
    doc = {
        "@schema": MARKUPS_SCHEMA_ID,
        "markups": [
            {"type": "Fiducial", "name": "heads", "controlPoints": [{"position": [1, 2, 3]}]},
            {
                "type": "Line",
                "coordinateSystem": "RAS",
                "controlPoints": [{"label": "a", "position": [1, 2, 3]}, {"position": [4, 5, 6]}],
            },
        ],
    }
    f.write_text(json.dumps(doc))
    _assert_points(
        read_markups(f),
        {
            "heads-1": np.array([1.0, 2.0, 3.0]),  # no coordinateSystem → LPS, unchanged
            "a": np.array([-1.0, -2.0, 3.0]),
            "x-2": np.array([-4.0, -5.0, 6.0]),  # unnamed markup → file name without .mrk.json
        },
    )
    nodes = read_markup_nodes(f)
    assert [(n.type, n.name, n.labels) for n in nodes] == [
        ("Fiducial", "heads", ("heads-1",)),
        ("Line", "x", ("a", "x-2")),
    ]


@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_round_trip(tmp_path: Path, system: str) -> None:
    f = write_markups(tmp_path / "m.mrk.json", POINTS, name="lm", coordinate_system=system)  # type: ignore[arg-type]
    raw = json.loads(f.read_text())["markups"][0]
    assert raw["coordinateSystem"] == system
    stored = np.array([cp["position"] for cp in raw["controlPoints"]])
    want = np.array(list(POINTS.values()))
    if system == "RAS":
        want = want * np.array([-1.0, -1.0, 1.0])
    np.testing.assert_array_equal(stored, want)
    _assert_points(read_markups(f), POINTS)


def test_line_and_curve_kinds(tmp_path: Path) -> None:
    two = dict(list(POINTS.items())[:2])
    line = write_markups(tmp_path / "l.mrk.json", two, name="plan", kind="Line")
    (node,) = read_markup_nodes(line)
    assert (node.type, node.name, node.labels) == ("Line", "plan", tuple(two))
    curve = write_markups(tmp_path / "c.mrk.json", POINTS, name="c", kind="Curve")
    assert read_markup_nodes(curve)[0].type == "Curve"
    with pytest.raises(ValueError, match="exactly two"):
        write_markups(tmp_path / "bad.mrk.json", POINTS, name="p", kind="Line")
    with pytest.raises(ValueError, match="kind"):
        write_markups(tmp_path / "bad.mrk.json", POINTS, name="p", kind="ROI")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="finite"):
        write_markups(tmp_path / "bad.mrk.json", {"a": np.array([1.0, np.nan, 2.0])}, name="p")


def test_read_and_write_landmarks_dispatch_mrk_json(tmp_path: Path) -> None:
    f = tmp_path / "ct_landmarks.MRK.JSON"
    f.write_text(SLICER_RAS)
    got = read_landmarks(f)
    np.testing.assert_array_equal(got["femoral_head_left"], [84.0, -10.5, -30.25])
    out = write_landmarks(tmp_path / "lm.mrk.json", POINTS)
    assert json.loads(out.read_text())["@schema"] == MARKUPS_SCHEMA_ID
    _assert_points(read_landmarks(out), POINTS)


# ---------------------------------------------------------------------------------------------
# the written file against the schema (markups-schema-v1.0.3.json): required keys, enums, types

_NUMBER = (int, float)


def _numbers(value: object, n: int) -> bool:
    return (
        isinstance(value, list)
        and len(value) == n
        and all(isinstance(v, _NUMBER) and not isinstance(v, bool) for v in value)
    )


def _check_schema_structure(doc: dict) -> None:
    # top level: required ["@schema", "markups"]; Slicer accepts markups-schema-v1.x.y ids
    assert {"@schema", "markups"} <= set(doc)
    assert re.search(r"markups-schema-v1\.[0-9]+\.[0-9]+\.json#*$", doc["@schema"].lower())
    assert isinstance(doc["markups"], list) and doc["markups"]
    for m in doc["markups"]:
        assert "type" in m  # the only required key of a markup
        assert m["type"] in ("Fiducial", "Line", "Angle", "Curve", "ClosedCurve", "Plane", "ROI")
        assert isinstance(m.get("name", ""), str)
        assert m.get("coordinateSystem", "LPS") in ("LPS", "RAS")
        assert m.get("coordinateUnits", "mm") in ("mm", "um")
        for key in ("locked", "fixedNumberOfControlPoints"):
            assert isinstance(m.get(key, False), bool)
        assert isinstance(m.get("labelFormat", ""), str)
        for cp in m["controlPoints"]:
            for key in ("id", "label", "description", "associatedNodeID"):
                assert isinstance(cp.get(key, ""), str)
            assert _numbers(cp["position"], 3)
            assert _numbers(cp.get("orientation", [0.0] * 9), 9)
            for key in ("selected", "locked", "visibility"):
                assert isinstance(cp.get(key, True), bool)
            assert cp.get("positionStatus", "defined") in ("undefined", "preview", "defined")
        display = m.get("display", {})
        assert isinstance(display, dict)
        assert isinstance(display.get("visibility", True), bool)
        assert 0.0 <= display.get("opacity", 1.0) <= 1.0
        for key in ("color", "selectedColor", "activeColor"):
            if key in display:
                assert _numbers(display[key], 3) and all(0.0 <= c <= 1.0 for c in display[key])
        assert display.get("glyphType", "Sphere3D") in (
            *("Vertex2D", "Dash2D", "Cross2D", "ThickCross2D", "Triangle2D", "Square2D", "Circle2D"),
            *("Diamond2D", "Arrow2D", "ThickArrow2D", "HookedArrow2D", "StarBurst2D"),
            *("Sphere3D", "Diamond3D"),
        )


@pytest.mark.parametrize(("kind", "n"), [("Fiducial", 3), ("Line", 2), ("Curve", 3)])
def test_written_file_follows_schema(tmp_path: Path, kind: str, n: int) -> None:
    pts = dict(list(POINTS.items())[:n])
    f = write_markups(tmp_path / "m.mrk.json", pts, name="m", kind=kind, color=(0.2, 0.3, 1.0))  # type: ignore[arg-type]
    doc = json.loads(f.read_text())
    _check_schema_structure(doc)
    (m,) = doc["markups"]
    assert (m["type"], m["name"], m["coordinateSystem"], m["coordinateUnits"]) == (kind, "m", "LPS", "mm")
    assert [cp["label"] for cp in m["controlPoints"]] == list(pts)
    assert [cp["id"] for cp in m["controlPoints"]] == [str(i) for i in range(1, n + 1)]
    # the identity orientation of Slicer's RAS scene, written in LPS as Slicer writes it
    assert m["controlPoints"][0]["orientation"] == [-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0]
    assert m["display"]["color"] == [0.2, 0.3, 1.0]


def test_slicer_example_passes_the_structural_check() -> None:
    # guards the check itself: a file Slicer wrote passes, a broken one fails
    _check_schema_structure(json.loads(SLICER_RAS.replace('"position": "",', '"position": [0, 0, 0],')))
    broken = json.loads(SLICER_RAS)
    del broken["markups"][0]["type"]
    with pytest.raises(AssertionError):
        _check_schema_structure(broken)


# ---------------------------------------------------------------------------------------------
# malformed files


def _markup(**changes: object) -> dict:
    m: dict = {
        "type": "Fiducial",
        "coordinateSystem": "LPS",
        "controlPoints": [{"label": "a", "position": [1, 2, 3]}],
    }
    m.update(changes)
    return m


def _cp(**cp: object) -> dict:
    return _markup(controlPoints=[cp])


BAD = {
    "empty": "",
    "not_json": "{markups: [",
    "nan_token": '{"markups": [{"type": "Fiducial", "controlPoints": [{"position": [1, NaN, 3]}]}]}',
    "top_list": [],
    "no_markups": {"@schema": MARKUPS_SCHEMA_ID},
    "markups_not_list": {"markups": {"type": "Fiducial"}},
    "foreign_schema": {"@schema": "https://example.org/other-schema.json#", "markups": [_markup()]},
    "markup_not_object": {"markups": [3]},
    "no_type": {"markups": [{"controlPoints": [{"position": [1, 2, 3]}]}]},
    "name_not_string": {"markups": [_markup(name=5)]},
    "unknown_system": {"markups": [_markup(coordinateSystem="XYZ")]},
    "units_cm": {"markups": [_markup(coordinateUnits="cm")]},
    "control_points_not_list": {"markups": [_markup(controlPoints={"a": [1, 2, 3]})]},
    "control_point_not_object": {"markups": [_markup(controlPoints=[[1, 2, 3]])]},
    "no_position": {"markups": [_cp(label="a")]},
    "two_numbers": {"markups": [_cp(label="a", position=[1, 2])]},
    "string_number": {"markups": [_cp(label="a", position=[1, "2", 3])]},
    "bool_number": {"markups": [_cp(label="a", position=[1, True, 3])]},
    "huge_integer": {"markups": [_cp(label="a", position=[1, 10**400, 3])]},
    "empty_position_defined": {"markups": [_cp(label="a", position="")]},
    "label_not_string": {"markups": [_cp(label=7, position=[1, 2, 3])]},
    "unknown_status": {"markups": [_cp(label="a", position=[1, 2, 3], positionStatus="maybe")]},
    "duplicate_labels": {
        "markups": [_markup(), _markup(type="Line", controlPoints=[{"label": "a", "position": [4, 5, 6]}])]
    },
    "no_points": {"markups": [_markup(controlPoints=[])]},
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_malformed_file_raises_input_error_naming_it(tmp_path: Path, case: str) -> None:
    f = tmp_path / f"bad_{case}.mrk.json"
    content = BAD[case]
    f.write_text(content if isinstance(content, str) else json.dumps(content))
    with pytest.raises(InputError) as err:
        read_markups(f)
    assert f.name in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(InputError):  # the landmark reader hands it on
        read_landmarks(f)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"nowhere\.mrk\.json.*not found"):
        read_markups(tmp_path / "nowhere.mrk.json")


json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**6), 10**6)
    | st.floats(allow_nan=True)
    | st.text(max_size=8),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=16,
)
control_point = st.fixed_dictionaries(
    {},
    optional={"label": json_values, "position": json_values, "positionStatus": json_values},
)
markup = st.fixed_dictionaries(
    {},
    optional={
        "type": st.sampled_from(["Fiducial", "Line", ""]) | json_values,
        "name": json_values,
        "coordinateSystem": st.sampled_from(["LPS", "RAS", "ras"]) | json_values,
        "coordinateUnits": json_values,
        "controlPoints": st.lists(control_point, max_size=3) | json_values,
    },
)


@settings(suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(doc=st.fixed_dictionaries({"markups": st.lists(markup, max_size=3)}) | json_values)
def test_reader_raises_only_input_error(tmp_path: Path, doc: object) -> None:
    f = tmp_path / "fuzz.mrk.json"
    f.write_text(json.dumps(doc))
    try:
        got = read_markups(f)
    except InputError as exc:
        assert str(f) in str(exc) and "\n" not in str(exc)
    else:
        assert got and all(p.shape == (3,) and np.all(np.isfinite(p)) for p in got.values())
