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
from fluoronav.detection.config import DetectorConfig
from fluoronav.detection.detector import Detector, shipped_model_path
from fluoronav.detection.evaluate import dice_score
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


def test_shipped_sidecar_describes_the_shipped_weights() -> None:
    # detector.json is the model file without its weights, its configuration in the declared form:
    # the stages the shipped model runs (the weights file holds the flat configuration of format 1)
    blob = torch.load(shipped_model_path(), map_location="cpu", weights_only=True)
    sidecar = json.loads(shipped_model_path().with_suffix(".json").read_text(encoding="utf-8"))
    declared = DetectorConfig.from_dict(blob["config"])
    assert sidecar["config"] == declared.to_dict()
    assert DetectorConfig.from_dict(sidecar["config"]) == declared
    assert sidecar["config"]["stages"] == [
        "coarse",
        "fine",
        "refine",
        "tube",
        "ends",
        "free_end",
        "shaft",
        "edge",
    ]
    assert sidecar["train"] == json.loads(json.dumps(blob["train"]))
    for key in ("fluoronav_version", "normalization", "parameters", "metrics"):
        assert sidecar[key] == json.loads(json.dumps(blob[key]))
    # every network of the declared stages has its weights, and there are no others
    assert {k.split(".", 1)[0] for k in blob["state_dict"]} == set(declared.network_stages)


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
