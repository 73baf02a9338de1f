"""A registration study on a user's CT: one without the labels and landmarks its trials need is
refused in one line before any trial runs (not failed trial by trial)."""

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
    out = tmp_path / "study"
    args = ["study", "single-view", "--ct", str(ct), "--trials", "1", "--seed", "0", "--out", str(out)]
    with pytest.raises(SystemExit) as exc:
        main([*args, "--workers", "0", "--image-size", "128", "--oracle-landmarks", "--device", "cpu"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert str(ct) in err and "needs label 'femur_left'" in err and lacks in err
    assert not (out / "trials.csv").exists()
