"""A tiny training run writes the model, checkpoint, sidecar and log, and resumes."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch
from det_synthetic import tiny_config, with_settings, write_dataset

from fluoronav.detection.config import DetectorConfig
from fluoronav.detection.detector import Detector
from fluoronav.detection.training.augment import AugmentConfig
from fluoronav.detection.training.train import TrainConfig, checkpoint_path, log_path, sidecar_path, train
from fluoronav.errors import InputError

TINY = tiny_config()


def test_two_step_training_writes_checkpoint_and_resumes(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "data", 10, size=64, seed=2, negative_every=5)
    out = tmp_path / "model.pt"
    cfg = TrainConfig(epochs=1, batch_size=2, max_steps_per_epoch=2, device="cpu", val_fraction=0.3, seed=3)
    m1 = train(data, out, config=cfg, model_config=TINY, progress=False)
    assert m1["epoch"] == 1 and m1["steps"] == 2
    for path in (out, checkpoint_path(out), sidecar_path(out), log_path(out)):
        assert path.is_file()
    side = json.loads(sidecar_path(out).read_text())
    assert side["format_version"] == 2 and side["config"]["stages"] == ["coarse", "fine"]
    assert side["config"]["coarse"]["network"]["channels"] == [4, 8, 16] and side["parameters"] > 0
    assert side["normalization"]["method"] == "percentile"
    w1 = torch.load(out, weights_only=True)["state_dict"]

    m2 = train(data, out, config=TrainConfig(**{**cfg.__dict__, "epochs": 2}), resume=True, progress=False)
    assert m2["epoch"] == 2
    lines = log_path(out).read_text().splitlines()
    assert [json.loads(x)["epoch"] for x in lines] == [1, 2]
    assert all(k in json.loads(lines[-1]) for k in ("train_loss", "val_dice", "val_landmark_px"))
    w2 = torch.load(out, weights_only=True)["state_dict"]
    assert any(not torch.equal(w1[k], w2[k]) for k in w1)  # the resumed epoch trained further
    assert Detector.load(out, device="cpu").config == TINY

    # same seed, same result: a fresh run of 1 epoch reproduces the first model
    out_b = tmp_path / "again.pt"
    train(data, out_b, config=cfg, model_config=TINY, progress=False)
    w1b = torch.load(out_b, weights_only=True)["state_dict"]
    assert all(torch.equal(w1[k], w1b[k]) for k in w1)


def test_resume_without_checkpoint_is_an_input_error(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "data", 3, size=32, seed=0)
    with pytest.raises(InputError, match="checkpoint"):
        train(
            data, tmp_path / "m.pt", config=TrainConfig(epochs=1, device="cpu"), resume=True, progress=False
        )


def _first_model(
    tmp_path: Path, *, seed: int, steps: int
) -> tuple[Path, TrainConfig, Path, dict[str, torch.Tensor]]:
    """A small data set, its training settings, a TINY model trained on it and that model's weights."""
    data = write_dataset(tmp_path / "data", 6, size=64, seed=seed, negative_every=3)
    cfg = TrainConfig(
        epochs=1, batch_size=2, max_steps_per_epoch=steps, device="cpu", val_fraction=0.3, seed=seed + 1
    )
    first = tmp_path / "first.pt"
    train(data, first, config=cfg, model_config=TINY, progress=False)
    return data, cfg, first, torch.load(first, weights_only=True)["state_dict"]


def test_init_starts_from_a_model_files_weights(tmp_path: Path) -> None:
    data, cfg, first, w0 = _first_model(tmp_path, seed=4, steps=1)
    # lr 0: the fine-tuned model keeps the initial weights exactly (BatchNorm statistics aside)
    tuned = tmp_path / "tuned.pt"
    zero_lr = TrainConfig(**{**cfg.__dict__, "lr": 0.0})
    train(data, tuned, config=zero_lr, init=first, progress=False)
    w1 = torch.load(tuned, weights_only=True)["state_dict"]
    learned = [k for k in w0 if not k.endswith(("running_mean", "running_var", "num_batches_tracked"))]
    assert learned and all(torch.equal(w0[k], w1[k]) for k in learned)
    assert json.loads(sidecar_path(tuned).read_text())["train"]["init"] == str(first)
    assert Detector.load(tuned, device="cpu").config.coarse.network == TINY.coarse.network  # the init's
    # without init the same run starts from other (random) weights
    fresh = tmp_path / "fresh.pt"
    train(
        data, fresh, config=TrainConfig(**{**zero_lr.__dict__, "seed": 6}), model_config=TINY, progress=False
    )
    w2 = torch.load(fresh, weights_only=True)["state_dict"]
    assert any(not torch.equal(w0[k], w2[k]) for k in learned)
    (tmp_path / "bad.pt").write_bytes(b"not a model")
    with pytest.raises(InputError, match=r"bad\.pt"):
        train(data, tmp_path / "x.pt", config=cfg, init=tmp_path / "bad.pt", progress=False)


def test_init_keeps_the_init_files_decoding_settings_only_when_asked(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "data", 4, size=64, seed=9, negative_every=3)
    cfg = TrainConfig(epochs=1, batch_size=2, max_steps_per_epoch=1, device="cpu", val_fraction=0.3, seed=9)
    tuned_cfg = with_settings(
        TINY,
        fine={"decoder": {"join_frac": 0.2}, "sampler": {"scales": (0.9, 1.0)}},
        coarse={"decoder": {"min_mask_px": 12}},
    )
    first = tmp_path / "first.pt"
    train(data, first, config=cfg, model_config=tuned_cfg, progress=False)
    kept, reset = tmp_path / "kept.pt", tmp_path / "reset.pt"
    train(data, kept, config=cfg, init=first, keep_decoding=True, progress=False)
    train(data, reset, config=cfg, init=first, progress=False)
    assert Detector.load(kept, device="cpu").config == tuned_cfg
    assert json.loads(sidecar_path(kept).read_text())["train"]["keep_decoding"] is True
    # by default the networks are the init's and the decoding settings this version's
    assert Detector.load(reset, device="cpu").config == TINY
    assert (
        with_settings(
            DetectorConfig(),
            coarse={"network": TINY.coarse.network.model_dump(), "sampler": {"size": 32}},
            fine={"network": TINY.fine.network.model_dump(), "sampler": {"size": 32}},
        )
        == TINY
    )


def test_coarse_size_retrains_the_coarse_stage_at_another_scale(tmp_path: Path) -> None:
    data, cfg, first, w0 = _first_model(tmp_path, seed=11, steps=1)
    coarse_cfg = dataclasses.replace(cfg, stages=("coarse",), lr=0.0)
    wider = tmp_path / "wider.pt"
    train(data, wider, config=coarse_cfg, init=first, keep_decoding=True, coarse_size=64, progress=False)
    det = Detector.load(wider, device="cpu")
    assert det.config == with_settings(
        TINY, coarse={"sampler": {"size": 64}}
    )  # only the coarse scale changed
    w1 = torch.load(wider, weights_only=True)["state_dict"]
    learned = [k for k in w0 if not k.endswith(("running_mean", "running_var", "num_batches_tracked"))]
    assert all(torch.equal(w0[k], w1[k]) for k in learned)  # lr 0: the init's weights, now at 64²
    assert det.net.coarse(torch.zeros(1, 1, 64, 64)).shape == (1, 3, 64, 64)
    assert det.detect(torch.rand(96, 80).numpy()).mask.shape == (96, 80)
    with pytest.raises(ValueError, match="multiple of 16"):
        train(data, wider, config=coarse_cfg, init=first, coarse_size=40, progress=False)
    with pytest.raises(ValueError, match="coarse stage"):
        train(data, wider, config=dataclasses.replace(cfg, stages=("fine",)), coarse_size=64)


def test_training_one_stage_leaves_the_other_untouched(tmp_path: Path) -> None:
    data, cfg, first, w0 = _first_model(tmp_path, seed=7, steps=2)
    tuned = tmp_path / "fine_only.pt"
    fine_cfg = dataclasses.replace(
        cfg, stages=("fine",), collimate_prob=0.5, partial_roi_prob=0.5, edge_negative_prob=0.5
    )
    train(data, tuned, config=fine_cfg, init=first, progress=False)
    w1 = torch.load(tuned, weights_only=True)["state_dict"]
    # the coarse stage is not run at all: weights and batch-norm statistics stay bit-identical
    assert all(torch.equal(w0[k], w1[k]) for k in w0 if k.startswith("coarse."))
    assert any(not torch.equal(w0[k], w1[k]) for k in w0 if k.startswith("fine."))
    meta = json.loads(sidecar_path(tuned).read_text())
    first_meta = json.loads(sidecar_path(first).read_text())
    assert meta["parameters"] == first_meta["parameters"]  # the whole model, not the stage trained
    side = meta["train"]
    assert side["stages"] == ["fine"]
    assert side["augmentation"]["p_collimate"] == 0.5 and side["collimate_prob"] == 0.5
    assert side["augmentation"]["p_partial_roi"] == 0.5 and side["partial_roi_prob"] == 0.5
    assert side["augmentation"]["p_edge_negative_roi"] == 0.5 and side["edge_negative_prob"] == 0.5
    assert AugmentConfig().p_collimate == 0.0  # off unless asked for (--collimate-prob)
    assert AugmentConfig().p_partial_roi == 0.0  # off unless asked for (--partial-roi-prob)
    with pytest.raises(ValueError, match="collimate_prob"):
        TrainConfig(collimate_prob=1.5)
    with pytest.raises(ValueError, match="edge_negative_prob"):
        TrainConfig(edge_negative_prob=-0.1)
    with pytest.raises(ValueError, match="partial_roi_prob"):
        TrainConfig(partial_roi_prob=-0.1)
    with pytest.raises(ValueError, match="stages"):
        TrainConfig(stages=("middle",))
