"""The table of training set-ups: every stage that trains has one, and each says how it trains."""

from __future__ import annotations

import dataclasses

import pytest

from fluoronav.detection.training.augment import AugmentConfig
from fluoronav.detection.training.config import TrainConfig
from fluoronav.detection.training.patches import EndJitter, RefineJitter
from fluoronav.detection.training.stages import STAGE_SETUPS, recorded_augmentation, stage_setup

PATCH_STAGES = ("refine", "ends", "tube", "shaft")


@pytest.mark.parametrize("stages", [("coarse", "fine"), ("fine", "coarse"), ("coarse",), ("fine",)])
def test_the_view_stages_share_one_setup_that_adds_nothing(stages: tuple[str, ...]) -> None:
    TrainConfig(stages=stages)  # a valid choice of stages
    setup = stage_setup(stages)
    assert setup is STAGE_SETUPS["coarse"] is STAGE_SETUPS["fine"]
    assert not setup.added and setup.copy_of is None and setup.jitter is None


def test_each_patch_stage_trains_alone_added_where_missing() -> None:
    setups = {name: stage_setup((name,)) for name in PATCH_STAGES}
    assert len({id(s) for s in setups.values()}) == len(PATCH_STAGES)
    assert all(s.added and s is not STAGE_SETUPS["coarse"] for s in setups.values())
    # a new shaft stage starts as the tube-mask stage; the others from their defaults
    assert [n for n, s in setups.items() if s.copy_of is not None] == ["shaft"]
    assert setups["shaft"].copy_of == "tube"


def test_a_model_file_records_the_patch_jitter_or_the_view_augmentation() -> None:
    aug = AugmentConfig(p_collimate=0.3)
    assert recorded_augmentation(stage_setup(("fine",)), aug) == dataclasses.asdict(aug)
    assert recorded_augmentation(stage_setup(("refine",)), aug) == dataclasses.asdict(RefineJitter())
    for name in ("ends", "tube", "shaft"):
        assert recorded_augmentation(stage_setup((name,)), aug) == dataclasses.asdict(EndJitter())
    assert recorded_augmentation(stage_setup(("refine",)), None) is None
