"""Patch-mask stages (mask ends, tube mask, shaft): training patches and their labels, pasting a patch
mask back, detector use, training."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from det_synthetic import first_tiny_model, tiny_config, with_settings
from torch import nn

from fluoronav.detection.config import DetectorConfig
from fluoronav.detection.decoder import cm_start_index, end_zone_paste, tube_paste
from fluoronav.detection.detector import Detector
from fluoronav.detection.model import DetectorNet
from fluoronav.detection.patches import RefinePatch, patch_grid_px, sample_patches, tube_frames
from fluoronav.detection.training.dataset import EndsDataset
from fluoronav.detection.training.patches import EndJitter, training_end_patch, training_tube_patch
from fluoronav.detection.training.train import TrainConfig, sidecar_path, train

NO_JITTER = EndJitter(along_sigma_px=0.0, across_sigma_px=0.0, angle_sigma_deg=0.0, p_mirror=0.0)


def _tube(a: tuple[float, float] = (40.3, 40.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A horizontal tube mask from A to u = 149, 12 px wide, its end at A a half-ellipse 5 px deep;
    the image is the mask."""
    vv, uu = np.mgrid[0:80, 0:160].astype(np.float64)
    s, n = uu - a[0], vv - a[1]
    a = np.array(a)
    mask = (np.abs(n) <= 6.0) & ((s >= 0) | ((s / 5.0) ** 2 + (n / 6.0) ** 2 <= 1.0)) & (uu < 150)
    return mask, mask.astype(np.float32), a


def test_training_patch_labels_each_patch_pixel_with_its_input_pixel() -> None:
    mask, image, a = _tube()
    rng = np.random.default_rng(0)
    patch, target = training_end_patch(
        image, mask, a, rng, step_px=0.5, shape=(32, 48), jitter=NO_JITTER, photometric=False
    )
    assert patch.shape == target.shape == (32, 48) and patch.dtype == target.dtype == np.float32
    frame = RefinePatch(a, np.array([1.0, 0.0]), 0.5, (32, 48))  # the tube runs along +u from A
    uv = patch_grid_px(frame)
    expect = mask[np.rint(uv[..., 1]).astype(int), np.rint(uv[..., 0]).astype(int)]
    np.testing.assert_array_equal(target > 0.5, expect)
    # the CM lies towards +cols (into the tube) and its end bulges beyond the centre by ≤ 5 px
    assert target[16, 47] == 1 and target[16, 0] == 0
    assert target[16, 23 - 9] == 1 and target[16, 23 - 11] == 0  # 4.5 / 5.5 input px beyond A
    # the mirror is exact about the tube's axis: image rows and labels flip together
    mirrored = EndJitter(along_sigma_px=0.0, across_sigma_px=0.0, angle_sigma_deg=0.0, p_mirror=1.0)
    p2, t2 = training_end_patch(
        image,
        mask,
        a,
        np.random.default_rng(0),
        step_px=0.5,
        shape=(32, 48),
        jitter=mirrored,
        photometric=False,
    )
    np.testing.assert_array_equal(t2, target[::-1])
    np.testing.assert_allclose(p2, patch[::-1], atol=1e-6)
    # no direction (an empty mask around the landmark): no patch
    assert (
        training_end_patch(
            image,
            np.zeros_like(mask),
            a,
            rng,
            step_px=0.5,
            shape=(32, 48),
            jitter=NO_JITTER,
            photometric=False,
        )
        is None
    )


def test_paste_replaces_the_outer_part_of_the_patch_only() -> None:
    mask = np.zeros((60, 100), bool)
    mask[:, 70:] = True  # outside the patch: kept
    frame = RefinePatch(np.array([50.0, 30.0]), np.array([1.0, 0.0]), 0.5, (16, 32))
    # patch cols 0..31 → u = 50 + 0.5·(k − 15.5): 42.25..57.75; rows → v = 30 + 0.5·(j − 7.5): 26.25..33.75
    out = end_zone_paste(mask, frame, np.ones((16, 32), np.float32), inner_px=4.0)
    zone = np.zeros_like(mask)
    zone[27:34, 43:53] = True  # inner_px 4 patch px = 2 input px inside the landmark: u ≤ 52
    np.testing.assert_array_equal(out, mask | zone)
    # negative logits clear the zone and nothing else
    full = np.ones_like(mask)
    cleared = end_zone_paste(full, frame, -np.ones((16, 32), np.float32), inner_px=4.0)
    np.testing.assert_array_equal(cleared, ~zone)
    # a patch outside the image changes nothing
    away = RefinePatch(np.array([500.0, 300.0]), np.array([1.0, 0.0]), 0.5, (16, 32))
    np.testing.assert_array_equal(end_zone_paste(mask, away, np.ones((16, 32)), inner_px=4.0), mask)


class _ShapeOracle(nn.Module):
    """Logits of the true tube end drawn in each patch: the patch image is the mask itself (0/1
    normalised), so > its mean is the CM."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x - x.mean(dim=(-2, -1), keepdim=True) + 1e-3


_VIEW = {"network": {"channels": (4, 8)}, "sampler": {"size": 32}}
ENDS_CFG = with_settings(
    DetectorConfig(),
    add=("ends",),
    coarse=_VIEW,
    fine=_VIEW,
    ends={"network": {"channels": (4, 8)}, "sampler": {"shape": (40, 48)}, "inner_px": 6.0},
)


def test_detector_redraws_the_mask_ends_from_the_patches() -> None:
    # landmarks on half-integers and 1 input px per patch px: the patch pixels are input pixels
    mask, image, a = _tube((40.5, 40.5))
    # the fine stage's mask: its end cut flat 3 px inside A and the tube running on 4 px beyond the end
    rough = mask.copy()
    rough[:, :44] = False
    rough[35:47, 140:154] = True
    b = np.array([149.5, 40.5])
    net = DetectorNet(ENDS_CFG)
    net.ends = _ShapeOracle()
    det = Detector(net, device="cpu")
    assert det.ends is not None
    out = det.ends(image, np.stack([a, b]), rough, pixel_spacing_mm=0.291)  # 1 input px per patch px
    # the zone at A: u ≤ 40.5 + 6; at B: u ≥ 149.5 − 6 (ends_inner_px 6 inside each landmark)
    np.testing.assert_array_equal(out[:, :47], mask[:, :47])  # A's end is the true one again
    np.testing.assert_array_equal(out[:, 144:], mask[:, 144:])  # the tube ends at u = 149 again
    np.testing.assert_array_equal(out[:, 47:144], rough[:, 47:144])  # between the zones: the fine mask
    assert (out[:, :47] != rough[:, :47]).any() and (out[:, 144:] != rough[:, 144:]).any()
    # a model without the stage: no such network, and its last steps leave the fine mask's ends
    plain = Detector(DetectorNet(tiny_config()), device="cpu")
    assert plain.net.ends is None and plain.ends is None
    assert plain.finish(image, rough, np.stack([a, b])).mask is rough


def test_ends_settings_are_validated_and_round_trip() -> None:
    cfg = with_settings(ENDS_CFG, ends={"sampler": {"shape": (40, 48)}, "inner_px": 2.5})
    assert DetectorConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    with pytest.raises(ValueError, match="shape"):
        with_settings(ENDS_CFG, ends={"sampler": {"shape": (41, 48)}})
    with pytest.raises(ValueError, match="inner_px"):
        with_settings(ENDS_CFG, ends={"inner_px": 30.0})


TINY = tiny_config()


def test_training_the_ends_stage_adds_it_and_leaves_the_others(tmp_path: Path) -> None:
    data, cfg, first, w0 = first_tiny_model(tmp_path, TINY)
    out = tmp_path / "ends.pt"
    m = train(
        data,
        out,
        config=dataclasses.replace(cfg, stages=("ends",), refine_repeats=2),
        init=first,
        progress=False,
    )
    assert 0.0 <= m["val_end_error"] <= 1.0 and np.isfinite(m["val_loss"])
    det = Detector.load(out, device="cpu")
    assert det.net.ends is not None and det.config.ends is not None
    assert det.config.ends.network.channels == (16, 32, 64, 128) and det.config.stages == (
        "coarse",
        "fine",
        "ends",
    )
    w1 = torch.load(out, weights_only=True)["state_dict"]
    assert all(torch.equal(w0[k], w1[k]) for k in w0)  # coarse and fine untouched
    assert any(k.startswith("ends.") for k in w1)
    assert json.loads(sidecar_path(out).read_text())["train"]["augmentation"]["along_sigma_px"] == 1.0
    # items: both landmarks' patches with their masks; none on negatives
    ds = EndsDataset(data, config=det.config, split="all", repeats=2, seed=0, stage="ends")
    assert len(ds) == 2 * 8
    valid = np.stack([ds[i]["ends_valid"].numpy() for i in range(len(ds))])
    assert (valid == 1).any() and (valid == 0).all(axis=1).any()
    item = ds[int(np.flatnonzero(valid.all(axis=1))[0])]
    assert item["ends_image"].shape == item["ends_mask"].shape == (2, 1, 80, 64)
    assert 0.0 < float(item["ends_mask"].mean()) < 1.0
    with pytest.raises(ValueError, match="ends"):
        TrainConfig(stages=("ends", "fine"))

    # the tube-mask stage on top: added, everything else (the mask-end stage too) untouched
    tube = tmp_path / "tube.pt"
    m = train(
        data,
        tube,
        config=dataclasses.replace(cfg, stages=("tube",), refine_repeats=1),
        init=out,
        progress=False,
    )
    assert 0.0 <= m["val_end_error"] <= 1.0
    det = Detector.load(tube, device="cpu")
    assert det.net.tube is not None and det.net.ends is not None and det.config.tube is not None
    assert det.config.tube.network.channels == (8, 16, 32, 64)
    assert det.config.stages == ("coarse", "fine", "tube", "ends")
    w2 = torch.load(tube, weights_only=True)["state_dict"]
    assert all(torch.equal(w1[k], w2[k]) for k in w1) and any(k.startswith("tube.") for k in w2)
    # fine-tuning another stage of a model that has the patch-mask stages trains that stage only
    fine = tmp_path / "fine.pt"
    train(data, fine, config=dataclasses.replace(cfg, stages=("fine",)), init=tube, progress=False)
    w3 = torch.load(fine, weights_only=True)["state_dict"]
    assert all(torch.equal(w2[k], w3[k]) for k in w2 if not k.startswith("fine."))
    assert any(not torch.equal(w2[k], w3[k]) for k in w2 if k.startswith("fine."))
    items = EndsDataset(data, config=det.config, split="all", repeats=1, seed=0, stage="tube")
    item = next(items[i] for i in range(len(items)) if bool(items[i]["ends_valid"].all()))
    # a patch centred on the tube's axis: CM along its middle row, background at its edges
    assert (
        float(item["ends_mask"][0, 0, 40, 32]) == 1.0
        and float(item["ends_mask"][0, 0, [0, -1], :].max()) == 0.0
    )

    # the shaft stage: added as a copy of the tube-mask stage, which stays as it was, and trained alone
    shaft = tmp_path / "shaft.pt"
    m = train(
        data,
        shaft,
        config=dataclasses.replace(cfg, stages=("shaft",), refine_repeats=1, tube_shaft_prob=0.5, lr=0.0),
        init=tube,
        progress=False,
    )
    det = Detector.load(shaft, device="cpu")
    assert det.net.shaft is not None and det.config.shaft is not None and det.config.tube is not None
    assert det.config.shaft.network == det.config.tube.network and det.shaft is not None
    w4 = torch.load(shaft, weights_only=True)["state_dict"]
    assert all(torch.equal(w2[k], w4[k]) for k in w2)
    # lr 0: the copy is exact (BatchNorm's running statistics aside, which a training pass updates)
    assert all(
        torch.equal(w4["shaft." + k[len("tube.") :]], w2[k])
        for k in w2
        if k.startswith("tube.") and not k.endswith(("running_mean", "running_var", "num_batches_tracked"))
    )
    assert json.loads(sidecar_path(shaft).read_text())["train"]["tube_shaft_prob"] == 0.5
    with pytest.raises(ValueError, match="tube_shaft_prob"):
        TrainConfig(stages=("shaft",))
    with pytest.raises(ValueError, match="tube_shaft_prob"):
        TrainConfig(stages=("fine",), tube_shaft_prob=0.3)


def test_tube_frames_follow_the_centreline_at_even_spacing() -> None:
    line = np.stack([np.linspace(10.0, 70.0, 61), np.full(61, 20.0)], axis=1)  # 60 px along +u
    frames = tube_frames(line, step_px=0.5, shape=(16, 32), spacing_px=16.0)
    np.testing.assert_allclose([f.center_px[0] for f in frames], np.linspace(10.0, 70.0, 5), atol=1e-9)
    assert all(np.allclose(f.tangent, [1.0, 0.0]) and f.step_px == 0.5 for f in frames)
    # a bend of radius 40 px: the tangent turns with the polyline (at the ends the chord is one-sided,
    # 4 px long: 0.05 rad behind the true tangent)
    arc = np.deg2rad(np.linspace(0.0, 90.0, 91))
    bent = np.stack([50.0 + 40.0 * np.sin(arc), 50.0 - 40.0 * np.cos(arc)], axis=1)
    fr = tube_frames(bent, step_px=0.5, shape=(16, 32), spacing_px=20.0)
    assert np.allclose(fr[0].tangent, [1.0, 0.0], atol=0.06) and np.allclose(
        fr[-1].tangent, [0.0, 1.0], atol=0.06
    )
    assert tube_frames(np.zeros((5, 2)), step_px=0.5, shape=(16, 32), spacing_px=8.0) == []


def test_tube_paste_averages_overlapping_bands_and_keeps_the_rest() -> None:
    mask = np.zeros((40, 100), bool)
    mask[0, :] = True  # outside every patch: kept
    f1 = RefinePatch(np.array([40.0, 20.0]), np.array([1.0, 0.0]), 0.5, (16, 32))
    f2 = RefinePatch(np.array([46.0, 20.0]), np.array([1.0, 0.0]), 0.5, (16, 32))
    # bands of 8 patch px = 4 input px: u 36..44 and 42..50; they overlap on u 42..44
    logits = np.stack([np.full((16, 32), 1.0), np.full((16, 32), -3.0)]).astype(np.float32)
    out = tube_paste(mask, [f1, f2], logits, band_px=8.0)
    rows = slice(17, 24)  # v within 20 ± 3.75
    assert out[rows, 36:42].all()  # f1 alone: +1
    assert not out[rows, 42:51].any()  # the overlap's mean is −1, then f2 alone
    assert not out[rows, 35].any() and not out[rows, 51].any()  # outside both bands: the mask's (False)
    np.testing.assert_array_equal(out[0], mask[0])
    np.testing.assert_array_equal(tube_paste(mask, [], np.zeros((0, 16, 32)), band_px=8.0), mask)


def test_patches_sampled_together_equal_those_sampled_one_by_one() -> None:
    # a smooth image (features ~10 px): cv2's 1/32-px fixed-point weights move a value by at most
    # |gradient| / 64 ≈ 0.005 of the image's range, ~0.01 after the normalisation
    vv, uu = np.mgrid[0:60, 0:70].astype(np.float64)
    image = (np.sin(uu / 5.0) + np.cos(vv / 7.0 + uu / 11.0)).astype(np.float32)
    frames = [
        RefinePatch(np.array([30.0, 25.0]), np.array([0.6, 0.8]), 0.5, (16, 32)),
        RefinePatch(np.array([12.3, 50.1]), np.array([-1.0, 0.0]), 0.7, (16, 32)),
    ]
    got = sample_patches(image, frames)
    assert got.shape == (2, 16, 32) and got.dtype == np.float32
    np.testing.assert_allclose(got, np.stack([f.sample(image) for f in frames]), atol=0.02)


def test_shaft_patches_lie_on_the_shaft_inside_the_image_and_label_it_not_cm() -> None:
    # the CM runs along +u from A = (40.3, 40); its shaft goes from A along −u, out of the image at u = 0
    mask, image, _ = _tube()
    image = image + ((np.abs(np.mgrid[0:80, 0:160][0] - 40.0) <= 6.0) & (np.mgrid[0:80, 0:160][1] < 40))
    line = np.stack([np.linspace(40.3, 149.0, 50), np.full(50, 40.0)], axis=1)
    shaft = np.array([[40.3, 40.0], [-60.0, 40.0]])
    centres = []
    for seed in range(40):
        got = training_tube_patch(
            image,
            mask,
            line,
            np.random.default_rng(seed),
            step_px=0.5,
            shape=(40, 24),  # 20 px across: the 12 px tube and background either side
            jitter=NO_JITTER,
            photometric=False,
            shaft_px=shaft,
            shaft_prob=1.0,
        )
        assert got is not None
        patch, target = got
        # the patch is centred on the shaft's axis (the tube runs along its middle rows) ...
        across = patch.mean(axis=1)
        assert across[14:26].min() > max(across[0], across[-1]) + 0.5
        # ... and its label is the CM's mask only: 0 except where the patch reaches beyond A
        centres.append(target.mean())
    # (a patch is 12 px long, the shaft's part inside the image 40 px: most patches lie wholly on it)
    assert np.mean(np.array(centres) == 0.0) > 0.6 and max(centres) < 0.6
    # shaft_prob 0 draws on the CM's centreline only, with the draws of a call without a shaft
    draws = []
    for shaft_px in (shaft, None):
        got = training_tube_patch(
            image,
            mask,
            line,
            np.random.default_rng(3),
            step_px=0.5,
            shape=(16, 24),
            jitter=NO_JITTER,
            photometric=False,
            shaft_px=shaft_px,
        )
        assert got is not None
        draws.append(got)
    np.testing.assert_array_equal(draws[0][0], draws[1][0])
    np.testing.assert_array_equal(draws[0][1], draws[1][1])
    assert draws[0][1].mean() > 0.9


def test_cm_start_index_skips_a_stretch_outside_the_mask() -> None:
    line = np.stack([np.linspace(0.0, 99.0, 100), np.full(100, 5.0)], axis=1)
    mask = np.zeros((10, 100), bool)
    mask[:, 30:] = True
    mask[:, 10:13] = True  # a short stretch inside: shorter than the run asked for
    assert cm_start_index(line, mask, run_px=5.0) == 30
    assert cm_start_index(line, mask, run_px=2.0) == 10
    assert cm_start_index(line, np.zeros_like(mask), run_px=5.0) is None
    # points outside the image count as outside the mask
    assert cm_start_index(line - [40.0, 0.0], mask, run_px=5.0) == 70
