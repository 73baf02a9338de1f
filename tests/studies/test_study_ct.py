"""A study on a user's CT: one without the labels and landmarks its trials need is refused in one
line before any trial runs (not failed trial by trial)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fluoronav.anatomy.io import save_volume
from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.cli.main import main


@pytest.mark.parametrize(
    ("keep_labels", "lacks"),
    [
        (False, "lacks label 'femur_left', landmark 'femoral_head_left', landmark 'entry_left'"),
        (True, "lacks landmark 'femoral_head_left', landmark 'entry_left'"),
    ],
)
def test_a_ct_without_femur_labels_is_refused_before_any_trial(
    keep_labels: bool, lacks: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ct = _user_ct(tmp_path, keep_labels=keep_labels)
    args = ["study", "single-view", "--ct", str(ct), "--oracle-landmarks"]
    err = _refused(args, tmp_path / "study", capsys)
    assert str(ct) in err and "needs label 'femur_left'" in err and lacks in err


@pytest.mark.parametrize(
    ("workflow", "keep_labels", "needs", "lacks"),
    [
        ("hand-eye", False, "needs label 'femur_left', landmark", "lacks label 'femur_left', landmark"),
        ("hand-eye", True, "needs label 'femur_left', landmark", "lacks landmark 'femoral_head_left'"),
        ("navigation", False, "needs label 'pelvis', label 'femur_left'", "lacks label 'pelvis', label"),
        ("navigation", True, "needs label 'pelvis', label 'femur_left'", "lacks landmark 'femoral_head"),
    ],
)
def test_a_robot_study_on_a_ct_without_its_scene_is_refused_before_any_trial(
    workflow: str,
    keep_labels: bool,
    needs: str,
    lacks: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    ct = _user_ct(tmp_path, keep_labels=keep_labels)
    err = _refused(["study", workflow, "--ct", str(ct)], tmp_path / "study", capsys)
    assert str(ct) in err and needs in err and lacks in err and "entry_left" in err


def _user_ct(tmp_path: Path, *, keep_labels: bool) -> Path:
    """A user's CT file: a coarse phantom without landmarks, and without labels unless ``keep_labels``."""
    ph = hip_phantom(seed=3, spacing_mm=4.0)
    vol = ph.replace(
        data=np.ascontiguousarray(ph.data),
        labels=ph.labels if keep_labels else None,
        label_names=ph.label_names if keep_labels else {},
        landmarks_world={},
        name="user_ct",
    )
    ct = tmp_path / "ct" / "user_ct.nii.gz"
    ct.parent.mkdir()
    save_volume(vol, ct)
    return ct


def _refused(args: list[str], out: Path, capsys: pytest.CaptureFixture[str]) -> str:
    """Run a one-trial study that must stop with an input error (exit 2) before any trial → its
    one-line message."""
    common = ["--trials", "1", "--seed", "0", "--out", str(out), "--workers", "0"]
    with pytest.raises(SystemExit) as exc:
        main([*args, *common, "--image-size", "128", "--device", "cpu"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert not (out / "trials.csv").exists()
    return err
