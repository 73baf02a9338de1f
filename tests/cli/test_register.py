"""``fluoronav register``: a simulated example case end to end, and one-line errors for bad cases."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from fluoronav.cli.register_case import load_case, write_example_case
from fluoronav.errors import InputError


@pytest.fixture(scope="module")
def example_case(tmp_path_factory):
    return write_example_case(tmp_path_factory.mktemp("case"), seed=2)


def test_example_case_round_trips(example_case) -> None:
    case = load_case(example_case)
    assert case.workflow == "single-view" and len(case.views) == 1
    assert case.views[0].image.shape == (384, 384) and case.views[0].image_binning == 4
    assert case.world_from_cm_true is not None and case.world_from_cm_true.shape == (1, 4, 4)


@pytest.mark.slow
def test_register_command_writes_result_trace_and_overlay(example_case, tmp_path) -> None:
    from fluoronav.cli.register import run_case

    d = run_case(example_case, tmp_path / "out", seed=0, device="cpu")
    out = tmp_path / "out"
    result = json.loads((out / "result.json").read_text())
    assert result == json.loads(json.dumps(d))
    assert set(result) >= {
        "world_from_cm",
        "control_points_deg",
        "tip_world_mm",
        "landmarks_px",
        "errors",
        "seconds",
        "converged",
        "reason",
    }
    assert result["errors"]["tip_error_mm"] < 2.0
    assert json.loads((out / "trace.json").read_text())["levels"]
    assert (out / "overlay_view0.png").stat().st_size > 0


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        ("{not json", "not valid JSON"),
        ('{"workflow": "tri-view", "views": []}', "'workflow' must be one of"),
        ('{"workflow": "single-view", "views": []}', "'views' must be a non-empty list"),
    ],
)
def test_malformed_case_raises_input_error(tmp_path, content, problem) -> None:
    path = tmp_path / "case.json"
    path.write_text(content)
    with pytest.raises(InputError, match=problem) as exc:
        load_case(path)
    assert str(path) in str(exc.value)


def test_missing_image_and_bad_landmarks(example_case, tmp_path) -> None:
    d = json.loads(example_case.read_text())
    d["views"][0]["landmarks_px"] = [[1.0, 2.0]]
    bad = example_case.parent / "bad_landmarks.json"
    bad.write_text(json.dumps(d))
    with pytest.raises(InputError, match="landmarks_px"):
        load_case(bad)
    d["views"][0]["image"] = "missing.npz"
    bad.write_text(json.dumps(d))
    with pytest.raises(InputError, match="file not found"):
        load_case(bad)


def test_cli_prints_one_line_error(tmp_path) -> None:
    path = tmp_path / "case.json"
    path.write_text("[]")
    proc = subprocess.run(
        [sys.executable, "-m", "fluoronav", "register", str(path), "--out", str(tmp_path / "o")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(path) in lines[0] and "JSON object" in lines[0]


def test_case_without_a_start_is_initialised_from_its_centreline(example_case, tmp_path) -> None:
    """No ``initial_world_from_cm``: the centreline initialisation (shaft-width depth cue, roll scan)
    of the first view starts the registration; here within 20 mm of the truth (centreline = the true
    CM's projection, landmarks as detected in the example)."""
    import numpy as np
    import torch

    from fluoronav.manipulator import CMKinematics

    case = load_case(example_case)
    d = json.loads(example_case.read_text())
    W = np.asarray(d["ground_truth"]["world_from_cm"], np.float64).reshape(-1, 4, 4)[0]
    cp = torch.as_tensor(d["ground_truth"]["control_points_deg"], dtype=torch.float64)
    cl_cm = CMKinematics().centerline_cm(cp, n_points=40).numpy()
    d["views"][0]["centerline_px"] = case.views[0].camera.project(cl_cm @ W[:3, :3].T + W[:3, 3]).tolist()
    d.pop("initial_world_from_cm")
    for v in d["views"]:  # paths relative to the new case file's folder
        for key in ("image", "camera", "background"):
            if isinstance(v.get(key), str) and v[key] != "dicom":
                v[key] = str(example_case.parent / v[key])
    path = tmp_path / "case.json"
    path.write_text(json.dumps(d))
    started = load_case(path)
    tip = CMKinematics().tip_cm(cp).numpy()
    err = np.linalg.norm(
        started.initial_world_from_cm[:3, :3] @ tip
        + started.initial_world_from_cm[:3, 3]
        - (W[:3, :3] @ tip + W[:3, 3])
    )
    assert err < 20.0, err
