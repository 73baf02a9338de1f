"""Detection benchmark: ``detect_ms`` (two-stage pipeline on a 1536² CIOS-size image) against
``detect_ms_baseline`` (the coarse network applied once at the full input resolution), both measured
here in the same run on the same image, with the shipped weights when present (else the default
architecture with seeded random weights: the run time does not depend on the weight values).

The pipeline is timed stage by stage on a region of interest and a mask of a drawn CM-like arc, so the
figure covers the whole path (coarse, fine, mask mapping, centreline) whatever the weights detect.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import cv2
import numpy as np
import torch
from torch.nn import functional as tnf

from fluoronav.detection.centerline import extract_centerline
from fluoronav.detection.detector import Detector, shipped_model_path
from fluoronav.detection.model import DetectorConfig, DetectorNet
from fluoronav.detection.views import roi_view

logger = logging.getLogger(__name__)


def _bench_image(size: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A smooth noisy log image with a bright arc; its mask and the arc's end points (2, 2)."""
    small = cv2.GaussianBlur(rng.standard_normal((64, 64)).astype(np.float32), (0, 0), 6)
    image = cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC) * 20.0 + 2.0
    mask = np.zeros((size, size), np.uint8)
    c, r = (size // 2, size // 2 + size // 4), size // 4
    cv2.ellipse(mask, c, (r, r), 0, 225, 315, 1, thickness=max(size // 50, 3))
    image = image + 1.5 * mask + rng.normal(0, 0.05, (size, size)).astype(np.float32)
    ends = np.array(
        [[c[0] + r * np.cos(np.deg2rad(a)), c[1] + r * np.sin(np.deg2rad(a))] for a in (225, 315)]
    )
    return image.astype(np.float32), mask.astype(bool), ends


def _median_ms(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def run(quick: bool = False) -> dict[str, float]:
    """Median detection time (ms) of the two-stage pipeline and of the full-resolution baseline."""
    if shipped_model_path().is_file():
        det = Detector.load(device="cpu")
    else:
        torch.manual_seed(0)
        det = Detector(DetectorNet(DetectorConfig()), device="cpu", source="random weights")
    cfg = det.config
    image, mask, ends = _bench_image(1536, np.random.default_rng(0))
    vv, uu = np.nonzero(mask)
    roi = roi_view(
        np.array([[uu.min(), vv.min()], [uu.max(), vv.max()]], dtype=np.float64),
        cfg.roi_size,
        margin_frac=cfg.roi_margin_frac,
        min_side_px=cfg.roi_min_side_px,
    )

    def pipeline() -> None:
        det.coarse(image)
        logit, _, _ = det.fine(image, roi)
        det._mask_at_input(logit, roi, image.shape, 0.0)
        extract_centerline(mask, ends[0], ends[1])

    def baseline() -> None:
        from fluoronav.detection.views import normalize_intensity

        x = torch.from_numpy(normalize_intensity(image))[None, None]
        k = 2 ** (len(cfg.channels) - 1)
        pad = (-x.shape[-1]) % k
        with torch.no_grad():
            det.net.coarse(tnf.pad(x, (0, pad, 0, pad), mode="replicate"))

    repeats = 3 if quick else 10
    ms = _median_ms(pipeline, repeats)
    ms_baseline = _median_ms(baseline, 1 if quick else 3)
    return {"detect_ms": ms, "detect_ms_baseline": ms_baseline, "detect_ms_speedup": ms_baseline / ms}
