"""``tools/convert_flat_detector.py``: model files of format 1 (a flat configuration) to format 2."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import ModuleType

import pytest
import torch

from fluoronav.detection.config import DetectorConfig
from fluoronav.detection.detector import Detector
from fluoronav.detection.model import DetectorNet, load_net
from fluoronav.errors import InputError

TOOL = Path(__file__).resolve().parents[2] / "tools" / "convert_flat_detector.py"


@pytest.fixture(scope="module")
def tool() -> ModuleType:
    spec = importlib.util.spec_from_file_location("convert_flat_detector", TOOL)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def declared(tool: ModuleType, flat: dict) -> DetectorConfig:
    return DetectorConfig.model_validate(tool.declared_from_flat(flat))


def test_the_flat_settings_map_onto_the_stages(tool: ModuleType) -> None:
    cfg = declared(
        tool,
        {
            "heatmap": "softmax",
            "input_size": 64,
            "roi_size": 96,
            "channels": (4, 8, 16),
            "roi_channels": (8, 16, 32),
            "fine_tta": 2,
            "min_confidence": 0.2,
            "refine_channels": (4, 8),
            "ends_channels": (4, 8),
            "ends_shape": (40, 48),
            "free_end_max_continuation": 0.3,
        },
    )
    assert cfg.stages == ("coarse", "fine", "refine", "ends", "free_end")
    assert cfg.coarse.sampler.size == 64 and cfg.coarse.network.channels == (4, 8, 16)
    assert cfg.fine.sampler.size == 96 and cfg.fine.network.channels == (8, 16, 32)
    assert cfg.fine.passes.tta == 2 and cfg.accept.min_confidence == 0.2
    assert cfg.ends is not None and cfg.ends.sampler.shape == (40, 48)
    assert cfg.free_end is not None and cfg.free_end.max_continuation == 0.3
    # the defaults of the flat form are the declared defaults
    assert declared(tool, {**tool.FLAT_DEFAULTS}) == DetectorConfig()
    # a shaft network whose check is off is not listed; with the check on, it is
    assert declared(tool, {"heatmap": "softmax", "shaft_channels": [4, 8]}).shaft is None
    on = declared(tool, {"heatmap": "softmax", "shaft_channels": [4, 8], "shaft_cut_min_mm": 5.0})
    assert on.shaft is not None and on.shaft.network.channels == (4, 8)
    edge = declared(tool, {"heatmap": "softmax", "min_edge_ratio": 1.4})
    assert edge.edge is not None and edge.edge.min_ratio == 1.4
    with pytest.raises(ValueError, match="min_edge_ratio"):
        tool.declared_from_flat({"min_edge_ratio": -1.0})


def test_keys_of_stages_gone_are_left_out_and_old_defaults_kept(tool: ModuleType) -> None:
    old = declared(tool, {"heatmap": "softmax", "strip_channels": [4, 8], "apex_max_confidence": 0.5})
    assert old == DetectorConfig()
    # files without the heatmap key predate the softmax heatmaps
    assert declared(tool, {"roi_size": 128}).fine.decoder.heatmap == "gaussian"
    bf16 = declared(tool, {"heatmap": "softmax", "bf16_stages": ["fine", "strip"]}).bf16_stages
    assert bf16 == ("fine",)
    assert tool.is_flat({"roi_size": 128}) and not tool.is_flat(DetectorConfig().to_dict())


def test_a_model_file_converts_with_its_weights_unchanged(tool: ModuleType, tmp_path: Path) -> None:
    flat = {
        "input_size": 32,
        "roi_size": 32,
        "channels": [4, 8, 16],
        "roi_channels": [4, 8, 16],
        "min_confidence": 0.2,
        "strip_channels": [4, 8],  # a stage fluoronav no longer has: its weights are left out
    }
    torch.manual_seed(0)
    net = DetectorNet(declared(tool, flat))
    state = {**net.state_dict(), "strip.model.0.conv.weight": torch.zeros(4, 1, 3, 3)}
    old = {"format_version": 1, "config": flat, "normalization": {"low_pct": 1.0}, "state_dict": state}
    torch.save(old, tmp_path / "old.pt")
    with pytest.raises(InputError, match="convert_flat_detector"):
        Detector.load(tmp_path / "old.pt")

    config = tool.convert_model_file(tmp_path / "old.pt", tmp_path / "new.pt")
    assert config.fine.decoder.heatmap == "gaussian" and config.accept.min_confidence == 0.2
    new = torch.load(tmp_path / "new.pt", weights_only=True)
    assert new["format_version"] == 2 and new["config"] == config.to_dict()
    assert new["normalization"] == old["normalization"]
    assert list(new["state_dict"]) == list(net.state_dict())
    loaded = load_net(tmp_path / "new.pt")
    assert loaded.config == config
    for name, value in net.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], value), name
    sidecar = json.loads((tmp_path / "new.json").read_text(encoding="utf-8"))
    assert sidecar == json.loads(json.dumps({k: v for k, v in new.items() if k != "state_dict"}))
    # a file of format 2 is not converted again
    with pytest.raises(ValueError, match="not a model file of format 1"):
        tool.convert_model_file(tmp_path / "new.pt", tmp_path / "again.pt")
