"""Property-based tests: every file reader rejects malformed input with a one-line InputError.

Any other exception type (KeyError, ValueError, IndexError, …) escaping a reader would become a
traceback for the user; these tests fail on it.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fluoronav.anatomy.io import load_ct
from fluoronav.anatomy.landmarks import read_fcsv, read_landmarks_json
from fluoronav.errors import InputError
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.config import load_cm_config
from fluoronav.navigation.planning import load_plan

# examples and determinism come from the profile in tests/conftest.py
SETTINGS = settings(suppress_health_check=[HealthCheck.function_scoped_fixture])

json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(10**6), 10**6)
    | st.floats(allow_nan=True)
    | st.text(max_size=8),
    lambda children: (
        st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=8), children, max_size=5)
    ),
    max_leaves=20,
)


def _camera_like() -> st.SearchStrategy[dict]:
    num = st.one_of(
        st.floats(allow_nan=True, allow_infinity=True), st.integers(-5, 5000), st.text(max_size=3)
    )
    mat = st.lists(st.lists(num, min_size=0, max_size=5), min_size=0, max_size=5)
    return st.fixed_dictionaries(
        {},
        optional={"rows": num, "cols": num, "K": mat, "camera_from_world": mat, "pixel_spacing_mm": num},
    )


def _check_one_line(exc: InputError, path: Path) -> None:
    msg = str(exc)
    assert str(path) in msg
    assert "\n" not in msg


@SETTINGS
@given(
    content=st.one_of(
        st.binary(max_size=200),
        json_values.map(lambda v: json.dumps(v).encode()),
        _camera_like().map(lambda v: json.dumps(v).encode()),
    )
)
def test_camera_reader(tmp_path: Path, content: bytes) -> None:
    f = tmp_path / "camera.json"
    f.write_bytes(content)
    try:
        Camera.load(f)
    except InputError as exc:
        _check_one_line(exc, f)


@SETTINGS
@given(content=st.one_of(st.binary(max_size=200), json_values.map(lambda v: json.dumps(v).encode())))
def test_cm_config_reader(tmp_path: Path, content: bytes) -> None:
    for name in ("cm.json", "cm.toml"):
        f = tmp_path / name
        f.write_bytes(content)
        try:
            load_cm_config(f)
        except InputError as exc:
            _check_one_line(exc, f)


@SETTINGS
@given(content=st.one_of(st.binary(max_size=200), json_values.map(lambda v: json.dumps(v).encode())))
def test_landmark_and_plan_readers(tmp_path: Path, content: bytes) -> None:
    for name, reader in (("lm.json", read_landmarks_json), ("plan.json", load_plan)):
        f = tmp_path / name
        f.write_bytes(content)
        try:
            reader(f)
        except InputError as exc:
            _check_one_line(exc, f)


@SETTINGS
@given(lines=st.lists(st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=40), max_size=6))
def test_fcsv_reader(tmp_path: Path, lines: list[str]) -> None:
    f = tmp_path / "lm.fcsv"
    f.write_text("\n".join(lines), encoding="utf-8")
    try:
        read_fcsv(f)
    except InputError as exc:
        _check_one_line(exc, f)


@SETTINGS
@given(content=st.binary(min_size=0, max_size=400))
def test_ct_reader_on_garbage(tmp_path: Path, content: bytes) -> None:
    for name in ("ct.nii", "ct.nrrd", "ct.mha"):
        f = tmp_path / name
        f.write_bytes(content)
        with pytest.raises(InputError) as info:
            load_ct(f)
        _check_one_line(info.value, f)
