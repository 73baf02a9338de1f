"""The declared configuration: stages and their settings, validation, and the flat form of format 1."""

from __future__ import annotations

import json

import pytest
import torch

from fluoronav.detection.config import STAGE_ORDER, DetectorConfig, RefineConfig, ShaftConfig
from fluoronav.detection.flat_config import FLAT_DEFAULTS
from fluoronav.detection.model import DetectorNet, shipped_model_path


def test_a_listed_stage_gets_its_defaults_and_an_unlisted_one_has_none() -> None:
    cfg = DetectorConfig(stages=("coarse", "fine", "refine", "edge"))
    assert cfg.refine == RefineConfig() and cfg.edge is not None
    assert cfg.tube is cfg.ends is cfg.shaft is cfg.free_end is None
    assert cfg.network_stages == ("coarse", "fine", "refine")
    d = cfg.to_dict()
    assert set(d) == {
        "stages",
        "assumed_spacing_mm",
        "bf16_stages",
        "accept",
        "coarse",
        "fine",
        "refine",
        "edge",
    }
    assert DetectorConfig.from_dict(json.loads(json.dumps(d))) == cfg
    net = DetectorNet(cfg)
    assert net.refine is not None and net.tube is None and net.ends is None and net.shaft is None


@pytest.mark.parametrize(
    ("stages", "match"),
    [
        (("fine", "coarse"), "subsequence"),  # out of order
        (("coarse", "fine", "fine"), "subsequence"),
        (("coarse", "fine", "strip"), "subsequence"),  # not a stage of this version
        (("coarse", "refine"), "'coarse' and 'fine'"),
    ],
)
def test_stages_are_validated(stages: tuple[str, ...], match: str) -> None:
    with pytest.raises(ValueError, match=match):
        DetectorConfig(stages=stages)


def test_settings_of_a_stage_not_listed_are_refused() -> None:
    with pytest.raises(ValueError, match="shaft has settings but is not in stages"):
        DetectorConfig(shaft=ShaftConfig())
    with pytest.raises(ValueError, match="extra"):
        DetectorConfig.model_validate({"coarse": {"sampler": {"sise": 64}}})  # a misspelt setting


def test_the_flat_keywords_of_format_1_map_onto_the_stages() -> None:
    cfg = DetectorConfig(
        input_size=64,
        roi_size=96,
        channels=(4, 8, 16),
        roi_channels=(8, 16, 32),
        fine_tta=2,
        min_confidence=0.2,
        refine_channels=(4, 8),
        ends_channels=(4, 8),
        ends_shape=(40, 48),
        free_end_max_continuation=0.3,
    )
    assert cfg.stages == ("coarse", "fine", "refine", "ends", "free_end")
    assert cfg.coarse.sampler.size == 64 and cfg.coarse.network.channels == (4, 8, 16)
    assert cfg.fine.sampler.size == 96 and cfg.fine.network.channels == (8, 16, 32)
    assert cfg.fine.passes.tta == 2 and cfg.accept.min_confidence == 0.2
    assert cfg.ends is not None and cfg.ends.sampler.shape == (40, 48)
    assert cfg.free_end is not None and cfg.free_end.max_continuation == 0.3
    # keywords are checked: an unknown or retired one raises
    for bad in ({"input_size": 64, "roi_sise": 64}, {"strip_channels": (4, 8)}):
        with pytest.raises(ValueError, match="unknown detector settings"):
            DetectorConfig(**bad)
    with pytest.raises(ValueError, match="roi_sise"):
        DetectorConfig(roi_sise=64)
    # a model file's keys of stages this version does not have are left aside
    old = DetectorConfig.from_dict(
        {"heatmap": "softmax", "strip_channels": [4, 8], "apex_max_confidence": 0.5}
    )
    assert old == DetectorConfig()
    # files without the heatmap key predate the softmax heatmaps
    assert DetectorConfig.from_dict({"roi_size": 128}).fine.decoder.heatmap == "gaussian"
    # the defaults of the flat form are the declared defaults
    assert DetectorConfig.from_dict({**FLAT_DEFAULTS}) == DetectorConfig()


@pytest.mark.skipif(not shipped_model_path().is_file(), reason="no shipped weights")
def test_the_shipped_flat_configuration_declares_every_stage() -> None:
    blob = torch.load(shipped_model_path(), map_location="cpu", weights_only=True)
    flat = blob["config"]
    cfg = DetectorConfig.from_dict(flat)
    assert cfg.stages == STAGE_ORDER
    assert cfg.fine.passes.sure_tta == flat["fine_sure_tta"] and cfg.fine.sampler.scales == (0.85, 1.0, 1.2)
    assert cfg.fine.hypotheses.wide_factors == (2.2,) and cfg.fine.hypotheses.wide_unfound
    assert cfg.accept.min_mask_mm2 == flat["min_mask_mm2"] and cfg.coarse.decoder.weak_mask_px == 1
    assert cfg.tube is not None and cfg.tube.sampler.spacing_px == flat["tube_spacing_px"]
    assert cfg.shaft is not None and cfg.shaft.cut_min_mm == flat["shaft_cut_min_mm"]
    assert cfg.shaft.network == cfg.tube.network and cfg.shaft.min_cm_logit == flat["shaft_min_cm_logit"]
    assert cfg.edge is not None and cfg.edge.needed_ratio(0.1) == 2.2 and cfg.edge.needed_ratio(0.5) == 1.4
    assert cfg.bf16_stages == ("fine",)
