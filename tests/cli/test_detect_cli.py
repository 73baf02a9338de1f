"""``fluoronav detect`` writes the contract files; bad inputs end in one line with exit status 2."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch import nn

from fluoronav.cli.main import main
from fluoronav.detection.model import DetectorConfig, DetectorNet
from fluoronav.detection.training.train import save_model

_VIEW = {"network": {"channels": (4, 8, 16)}, "sampler": {"size": 32}}
TINY = DetectorConfig.model_validate({"coarse": _VIEW, "fine": _VIEW})


@pytest.fixture()
def empty_model(tmp_path: Path) -> Path:
    """A model file whose segmentation is always empty (zeroed last layer, seg bias −10)."""
    torch.manual_seed(0)
    net = DetectorNet(TINY)
    for stage in (net.coarse, net.fine):
        last = [m for m in stage.modules() if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d))][-1]
        with torch.no_grad():
            last.weight.zero_()
            last.bias.copy_(torch.tensor([-10.0, 0.0, 0.0]))
    path = tmp_path / "model.pt"
    save_model(path, net, extra={})
    return path


def test_detect_writes_contract_json_and_mask(tmp_path: Path, empty_model: Path) -> None:
    img = np.random.default_rng(0).normal(size=(48, 40)).astype(np.float32)
    np.savez(tmp_path / "frame1.npz", image=img)
    cv2.imwrite(str(tmp_path / "frame2.png"), (np.arange(30 * 50).reshape(30, 50) % 256).astype(np.uint8))
    out = tmp_path / "det"
    main(
        [
            "detect",
            str(tmp_path / "frame1.npz"),
            str(tmp_path / "frame2.png"),
            "--out",
            str(out),
            "--model",
            str(empty_model),
            "--device",
            "cpu",
        ]
    )
    for stem, shape in (("frame1", (48, 40)), ("frame2", (30, 50))):
        data = json.loads((out / f"{stem}.json").read_text())
        assert {"landmarks_px", "landmark_confidence", "centerline_px", "mask", "found"} <= set(data)
        assert data["found"] is False and data["landmarks_px"] is None and data["centerline_px"] is None
        assert len(data["landmark_confidence"]) == 2
        assert data["mask"] == f"{stem}_mask.png"
        mask = cv2.imread(str(out / data["mask"]), cv2.IMREAD_UNCHANGED)
        assert mask.shape == shape and not mask.any()


@pytest.mark.parametrize("problem", ["no_image_key", "corrupt_model", "missing_file"])
def test_detect_bad_input_one_line_exit_2(
    tmp_path: Path,
    empty_model: Path,
    capsys: pytest.CaptureFixture[str],
    problem: str,
) -> None:
    image = tmp_path / "img.npz"
    np.savez(image, image=np.zeros((16, 16), np.float32))
    model = empty_model
    if problem == "no_image_key":
        np.savez(image, picture=np.zeros((16, 16), np.float32))
    elif problem == "corrupt_model":
        model = tmp_path / "bad.pt"
        model.write_bytes(b"\x00garbage")
    else:
        image = tmp_path / "nothere.npz"
    with pytest.raises(SystemExit) as exc:
        main(["detect", str(image), "--out", str(tmp_path / "o"), "--model", str(model), "--device", "cpu"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and len(err.splitlines()) == 1
    assert (model.name if problem == "corrupt_model" else image.name) in err
