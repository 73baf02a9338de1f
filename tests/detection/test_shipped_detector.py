"""The shipped weights on freshly simulated images (an anatomy and scenes no model was trained on).

A regression guard for the weights file, the image pre-processing and the decoding together; the
accuracy figures of the model card come from ``fluoronav evaluate`` on 100 + 40 unseen images.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.detection.config import STAGE_ORDER, DetectorConfig
from fluoronav.detection.detector import Detector, shipped_model_path
from fluoronav.detection.model import MODEL_FORMAT_VERSION
from fluoronav.detection.training.evaluate import dice_score
from fluoronav.simulation.scene import SceneSampling, sample_scene
from fluoronav.simulation.xray import SimulationConfig, XraySimulator

pytestmark = pytest.mark.skipif(not shipped_model_path().is_file(), reason="no shipped weights")

N_POSITIVE = 6


def test_shipped_detector_on_unseen_simulated_images() -> None:
    # the data sets' 512² images of a phantom anatomy (seed 9) that no training set used
    sim = XraySimulator(hip_phantom(seed=9), config=SimulationConfig(image_size=512), device="cpu")
    det = Detector.load(device="cpu")
    assert det.precision == "float32"  # the default, whatever the CPU
    fast = Detector.load(device="cpu", precision="bfloat16")
    dices, errors_px, found = [], [], 0
    agree, moved_px, mask_dices = 0, [], []  # bfloat16 against float32
    for k in range(N_POSITIVE):
        rng = np.random.default_rng(5100 + k)
        image = sim.simulate(sample_scene(sim.volume, rng, sampling=SceneSampling()), seed=k)
        d = det.detect(image.image, pixel_spacing_mm=image.camera.pixel_spacing_mm)
        dices.append(dice_score(d.mask, image.mask) if d.found else 0.0)
        if d.found:
            found += 1
            errors_px.extend(np.linalg.norm(d.landmarks_px - image.landmarks_px, axis=1))
        b = fast.detect(image.image, pixel_spacing_mm=image.camera.pixel_spacing_mm)
        agree += int(b.found == d.found)
        if b.found and d.found:
            moved_px.extend(np.linalg.norm(b.landmarks_px - d.landmarks_px, axis=1))
            mask_dices.append(dice_score(b.mask, d.mask))
    assert found >= N_POSITIVE - 2  # the shipped model finds 5 of these 6 (96 % on its test set)
    assert np.median(dices) >= 0.9, dices
    assert np.median(errors_px) <= 1.5, errors_px
    # bfloat16 moves a typical landmark by ~0.01 px (0.8 px at most here, where it tips a decision)
    assert agree >= N_POSITIVE - 1
    assert np.median(moved_px) <= 0.1, moved_px
    assert np.median(mask_dices) >= 0.99, mask_dices
    for k in range(2):
        rng = np.random.default_rng(5200 + k)
        scene = sample_scene(sim.volume, rng, sampling=SceneSampling(), with_cm=False)
        assert not det.detect(sim.simulate(scene, seed=k).image).found


def test_shipped_model_file_holds_the_declared_configuration() -> None:
    # format 2: the declared stages and their settings, read as they are (no flat form)
    blob = torch.load(shipped_model_path(), map_location="cpu", weights_only=True)
    assert blob["format_version"] == MODEL_FORMAT_VERSION == 2
    cfg = DetectorConfig.model_validate(blob["config"])
    assert blob["config"] == cfg.to_dict()
    assert cfg.stages == STAGE_ORDER
    assert cfg.fine.passes.sure_tta == 4 and cfg.fine.sampler.scales == (0.85, 1.0, 1.2)
    assert cfg.fine.hypotheses.wide_factors == (2.2,) and cfg.fine.hypotheses.wide_unfound
    assert cfg.accept.min_mask_mm2 == 28.3 and cfg.coarse.decoder.weak_mask_px == 1
    assert cfg.tube is not None and cfg.tube.sampler.spacing_px == 32.0
    assert cfg.shaft is not None and cfg.shaft.cut_min_mm == 5.0
    assert cfg.shaft.network == cfg.tube.network and cfg.shaft.min_cm_logit == 2.0
    assert cfg.edge is not None and cfg.edge.needed_ratio(0.1) == 2.2 and cfg.edge.needed_ratio(0.5) == 1.4
    assert cfg.bf16_stages == ("fine",)
    # the loaded detector runs that configuration, every network with its weights
    assert Detector.load(device="cpu").config == cfg
    assert {k.split(".", 1)[0] for k in blob["state_dict"]} == set(cfg.network_stages)


def test_shipped_sidecar_describes_the_shipped_weights() -> None:
    # detector.json is the model file without its weights
    blob = torch.load(shipped_model_path(), map_location="cpu", weights_only=True)
    sidecar = json.loads(shipped_model_path().with_suffix(".json").read_text(encoding="utf-8"))
    assert set(sidecar) == set(blob) - {"state_dict"}
    for key in sidecar:
        assert sidecar[key] == json.loads(json.dumps(blob[key])), key


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_shipped_detector_on_cuda_matches_cpu() -> None:
    # the same weights and decoding on the GPU: convolutions there may run in TF32, so a landmark
    # may move by a small fraction of a pixel; a decision (found or not) must not change
    sim = XraySimulator(hip_phantom(seed=9), config=SimulationConfig(image_size=512), device="cpu")
    cpu, gpu = Detector.load(device="cpu"), Detector.load(device="cuda")
    assert gpu.device.type == "cuda"
    moved_px, mask_dices = [], []
    for k in range(3):
        rng = np.random.default_rng(5100 + k)
        image = sim.simulate(sample_scene(sim.volume, rng, sampling=SceneSampling()), seed=k)
        a = cpu.detect(image.image, pixel_spacing_mm=image.camera.pixel_spacing_mm)
        b = gpu.detect(image.image, pixel_spacing_mm=image.camera.pixel_spacing_mm)
        assert a.found == b.found
        if a.found:
            moved_px.extend(np.linalg.norm(b.landmarks_px - a.landmarks_px, axis=1))
            mask_dices.append(dice_score(b.mask, a.mask))
    assert moved_px and np.median(moved_px) <= 0.1, moved_px
    assert np.min(mask_dices) >= 0.98, mask_dices
