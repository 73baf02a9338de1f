"""The declared configuration: stages and their settings, and their validation."""

from __future__ import annotations

import json

import pytest

from fluoronav.detection.config import DetectorConfig, RefineConfig, ShaftConfig
from fluoronav.detection.model import DetectorNet


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


def test_the_flat_keys_of_format_1_are_refused() -> None:
    # model files of format 1 held one flat dictionary; tools/convert_flat_detector.py converts them
    with pytest.raises(ValueError, match="extra"):
        DetectorConfig(input_size=64, refine_channels=(8, 16))  # type: ignore[call-arg]
    with pytest.raises(ValueError, match="extra"):
        DetectorConfig.from_dict({"heatmap": "gaussian", "roi_size": 128})
    assert DetectorConfig.from_dict({}) == DetectorConfig()
