"""Property-based tests of the command line: malformed images, DICOMs, camera and case files.

Every command that reads a user file must end with one line on stderr naming the file, a non-zero
exit status and no traceback, whatever the bytes or JSON it is given.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fluoronav.cli.main import main

CLI = settings(suppress_health_check=[HealthCheck.function_scoped_fixture], max_examples=25)

json_values = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 2000) | st.floats(allow_nan=True) | st.text(max_size=6),
    lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=6), c, max_size=4),
    max_leaves=12,
)
IMAGE_SUFFIXES = (".png", ".tif", ".jpg", ".dcm", ".npz", ".npy")


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    with pytest.raises(SystemExit) as info:
        main(argv)
    code = info.value.code
    return (code if isinstance(code, int) else 1), capsys.readouterr().err


def _assert_clean_rejection(code: int, err: str, path: Path) -> None:
    assert code != 0
    assert "Traceback" not in err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert path.name in lines[0], err


@CLI
@given(content=st.binary(max_size=300), suffix=st.sampled_from(IMAGE_SUFFIXES))
def test_detect_rejects_malformed_images(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes, suffix: str
) -> None:
    path = tmp_path / f"frame{suffix}"
    path.write_bytes(content)
    code, err = _run(["detect", str(path), "--out", str(tmp_path / "out"), "--device", "cpu"], capsys)
    _assert_clean_rejection(code, err, path)


def _case_like() -> st.SearchStrategy[dict]:
    view = st.fixed_dictionaries(
        {},
        optional={
            "image": st.sampled_from(["img.png", "img.dcm", "missing.npz", "img.npz"]) | json_values,
            "camera": st.sampled_from(["cam.json", "dicom", "missing.json"]) | json_values,
            "landmarks_px": json_values,
            "binning": json_values,
        },
    )
    return st.fixed_dictionaries(
        {},
        optional={
            "workflow": st.sampled_from(["single-view", "multi-view", "multi-cm", "bogus"]) | json_values,
            "views": st.lists(view, max_size=3) | json_values,
            "initial_control_points_deg": json_values,
            "initial_world_from_cm": json_values,
            "camera": st.sampled_from(["cam.json", "missing.json"]) | json_values,
            "robot_poses": st.sampled_from(["poses.csv", "missing.csv"]) | json_values,
            "initial_ee_from_cm": json_values,
        },
    )


def _case_files(tmp_path: Path, garbage: bytes) -> None:
    """Files a fuzzed case may point at: a garbage image and DICOM, a broken camera and pose log."""
    for name in ("img.png", "img.dcm", "img.npz"):
        (tmp_path / name).write_bytes(garbage)
    (tmp_path / "cam.json").write_text('{"rows": 4, "cols": "x"}', encoding="utf-8")
    (tmp_path / "poses.csv").write_text("1,2,three\n", encoding="utf-8")


@CLI
@given(
    case=st.one_of(_case_like().map(json.dumps), st.text(max_size=80)),
    garbage=st.binary(max_size=64),
    command=st.sampled_from(["register", "calibrate"]),
)
def test_register_and_calibrate_reject_malformed_cases(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str, garbage: bytes, command: str
) -> None:
    _case_files(tmp_path, garbage)
    path = tmp_path / "case.json"
    path.write_text(case, encoding="utf-8")
    code, err = _run([command, str(path), "--out", str(tmp_path / "out"), "--device", "cpu"], capsys)
    assert code != 0 and "Traceback" not in err
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    # the line names the case file or the file inside it that is broken
    assert any(n in lines[0] for n in ("case.json", "img.", "cam.json", "poses.csv", "missing.")), err


@CLI
@given(content=st.one_of(st.binary(max_size=200), json_values.map(lambda v: json.dumps(v).encode())))
def test_render_rejects_malformed_cameras(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes
) -> None:
    path = tmp_path / "camera.json"
    path.write_bytes(content)
    code, err = _run(
        ["render", "--ct", "phantom", "--camera", str(path), "--out", str(tmp_path / "drr.npy")], capsys
    )
    _assert_clean_rejection(code, err, path)
