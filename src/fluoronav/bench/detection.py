"""Detection benchmark: the detection pipeline on a 1536² image against a one-pass baseline.

``detect_ms`` times the whole pipeline stage by stage on the simulated CM's region and mask, so the
figure covers every stage whatever the weights detect; ``detect_ms_baseline`` is the coarse network
applied once at the full input resolution. Both run in the same process on one physics-simulated
detector image of the CM over the hip phantom (unbinned 0.194 mm pixels), with the shipped weights
when present (else seeded random weights: the time does not depend on them).
``detect_second_look_ms`` times the path with the second look forced (what an unsure detection
costs); on a CPU with native bfloat16, ``detect_bfloat16_ms`` with the model's ``bf16_stages`` in
bfloat16 (``--precision bfloat16``). The figures: docs/validation.md ("Speed").
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
import torch
from torch.nn import functional as tnf

from fluoronav.bench.timing import time_ms
from fluoronav.detection.centerline import extract_centerline
from fluoronav.detection.config import DetectorConfig
from fluoronav.detection.detector import Detector
from fluoronav.detection.evidence import end_continuation, mask_edge_ratio
from fluoronav.detection.localize import FineResult
from fluoronav.detection.model import DetectorNet, load_net, shipped_model_path
from fluoronav.detection.runtime import native_bf16
from fluoronav.detection.views import normalize_intensity

logger = logging.getLogger(__name__)


def _bench_image(size: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """A simulated (size, size) log image of the CM over the phantom, its mask, landmarks (2, 2) and
    pixel spacing (mm)."""
    from fluoronav.anatomy.phantom import hip_phantom
    from fluoronav.simulation.scene import SceneSampling, sample_scene
    from fluoronav.simulation.xray import SimulationConfig, XraySimulator

    sim = XraySimulator(hip_phantom(seed=seed), config=SimulationConfig(image_size=size), device="cpu")
    rng = np.random.default_rng(seed)
    while True:  # the paper's scene sampling keeps the CM in view; redraw in the rare case it is not
        image = sim.simulate(sample_scene(sim.volume, rng, sampling=SceneSampling()), seed=seed)
        if image.landmarks_px is not None and image.mask.any():
            spacing_mm = image.camera.pixel_spacing_mm
            assert spacing_mm is not None  # a simulated camera knows its detector
            return (
                image.image.astype(np.float32),
                image.mask.astype(bool),
                np.asarray(image.landmarks_px),
                float(spacing_mm),
            )


def run(quick: bool = False, device: str = "cpu") -> dict[str, float]:
    """Median detection time (ms) on ``device`` of the detection pipeline and of the full-resolution
    baseline (and of the pipeline in bfloat16 where the device is a CPU that runs it natively and the
    model names stages for it). The test image is simulated on the CPU either way."""
    if shipped_model_path().is_file():
        net, source = load_net(), str(shipped_model_path())
    else:
        torch.manual_seed(0)
        net, source = DetectorNet(DetectorConfig()), "random weights"
    det = Detector(net, device=device, source=source)
    cfg = det.config
    image, mask, ends, spacing_mm = _bench_image(1536)
    vv, uu = np.nonzero(mask)
    roi = det.fine.roi_around(np.array([[uu.min(), vv.min()], [uu.max(), vv.max()]], dtype=np.float64))

    def has_mask(r: FineResult) -> bool:
        return bool(r.mask.any())

    def pipeline(d: Detector = det) -> None:
        d.coarse(image, pixel_spacing_mm=spacing_mm)
        # every fine pass (the last at each of the configured ROI scales), the second look where the
        # detection is unsure enough, landmark refinement, the centreline, the mask's redrawing
        # along it and at its ends (the patch stages), the checks of A's end, of the shaft and of
        # the mask's edges, as ``Detector.detect`` runs them
        res = d.fine.second_look(image, d.fine(image, roi), pixel_spacing_mm=spacing_mm, accept=has_mask)
        if d.refine is not None:
            d.refine(image, res.landmarks_px, res.mask, pixel_spacing_mm=spacing_mm)
        line = extract_centerline(mask, ends[0], ends[1])
        final = mask
        if d.tube is not None:
            final = d.tube(image, line, final, pixel_spacing_mm=spacing_mm)
        if d.ends is not None:
            final = d.ends(image, ends, final, pixel_spacing_mm=spacing_mm)
        if d.free_end is not None:
            end_continuation(image, final, ends[0], pixel_spacing_mm=spacing_mm)
        if d.shaft is not None:
            d.shaft.start(image, mask, line, pixel_spacing_mm=spacing_mm)
        if d.edge is not None and d.edge.config.needed_ratio(float(res.confidence.min())) > 0.0:
            mask_edge_ratio(image, final, pixel_spacing_mm=spacing_mm)

    def baseline() -> None:
        x = torch.from_numpy(normalize_intensity(image))[None, None].to(det.device)
        k = cfg.coarse.network.divisor
        pad = (-x.shape[-1]) % k
        with torch.no_grad():
            det.net.coarse(tnf.pad(x, (0, pad, 0, pad), mode="replicate"))

    def _median_ms(fn: Callable[[], object], repeats: int) -> float:
        return time_ms(fn, repeats=repeats, device=device)

    repeats = 3 if quick else 10
    ms = _median_ms(pipeline, repeats)
    ms_baseline = _median_ms(baseline, 1 if quick else 3)
    out = {"detect_ms": ms, "detect_ms_baseline": ms_baseline, "detect_ms_speedup": ms_baseline / ms}
    if cfg.bf16_stages and det.device.type == "cpu" and native_bf16():
        # from the trained networks: a bfloat16 stage keeps its batch norms
        fast = Detector(net, device=device, precision="bfloat16", source=source)
        ms_fast = _median_ms(lambda: pipeline(fast), repeats)
        out |= {
            "detect_bfloat16_ms": ms_fast,
            "detect_bfloat16_ms_baseline": ms_baseline,
            "detect_bfloat16_ms_speedup": ms_baseline / ms_fast,
        }
    hyp = cfg.fine.hypotheses
    if hyp.wide_factors:
        # the same image with the second look forced (as for an unsure detection): its wider view
        # and, where that moves a landmark far enough, a second run of the fine stage
        forced = Detector(net, device=device, source=source)
        forced.fine.config = cfg.fine.model_copy(
            update={"hypotheses": hyp.model_copy(update={"wide_max_confidence": 1.0})}
        )
        ms_look = _median_ms(lambda: pipeline(forced), repeats)
        out |= {
            "detect_second_look_ms": ms_look,
            "detect_second_look_ms_baseline": ms_baseline,
            "detect_second_look_ms_speedup": ms_baseline / ms_look,
        }
    return out
