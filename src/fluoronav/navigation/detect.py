"""The ``detect`` stage of the navigation: the CM found in each view of a case, by the shipped
detector or from the landmarks (and mask) the case gives (:func:`detect_views`)."""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from fluoronav.detection.centerline import extract_centerline
from fluoronav.navigation.case.view import CaseView
from fluoronav.navigation.config import NavigationConfig
from fluoronav.registration.view_set import ViewDetection

__all__ = ["band_mask", "detect_views", "shipped_detector"]

log = logging.getLogger(__name__)


@functools.lru_cache(maxsize=2)
def shipped_detector(device: str) -> Any:
    """The shipped CM detector on ``device`` (loaded once per process)."""
    from fluoronav.detection.detector import Detector

    return Detector.load(None, device=device)


def band_mask(shape: tuple[int, int], ab: np.ndarray, half_width_px: float) -> np.ndarray:
    """(rows, cols) bool: pixels within ``half_width_px`` of the segment A–B."""
    rows, cols = shape
    v, u = np.mgrid[0:rows, 0:cols]
    p = np.stack([u, v], axis=-1).astype(np.float64)
    a, b = np.asarray(ab[0], np.float64), np.asarray(ab[1], np.float64)
    d = b - a
    t = np.clip(((p - a) @ d) / max(float(d @ d), 1e-12), 0.0, 1.0)
    return np.asarray(np.linalg.norm(p - (a + t[..., None] * d), axis=-1) <= half_width_px)


def _as_bool(x: np.ndarray) -> np.ndarray:
    return np.asarray(x, dtype=bool)


def detect_views(
    views: Sequence[CaseView], *, config: NavigationConfig
) -> tuple[list[ViewDetection | None], dict[str, Any]]:
    """Per view: the CM found (detector, or the case's landmarks), None where none is usable; and the
    per-view diagnostics (found, why not, confidence)."""
    out: list[ViewDetection | None] = []
    diag: dict[str, Any] = {}
    for v in views:
        if v.landmarks_px is not None:
            lm = np.asarray(v.landmarks_px, np.float64)
            if v.mask is not None:
                mask = _as_bool(v.mask)
            else:
                ps = v.camera.pixel_spacing_mm or 0.194
                mask = band_mask(v.image.shape, lm, config.landmark_band_mm / ps)
            out.append(ViewDetection(lm, extract_centerline(mask, lm[0], lm[1]), mask, np.ones(2), "case"))
            diag[v.name] = {"found": True, "source": "case"}
            continue
        det = shipped_detector(config.device).detect(v.image, pixel_spacing_mm=v.camera.pixel_spacing_mm)
        if not det.usable or det.centerline_px is None:
            why = det.unusable_reason or "no centreline"
            log.warning("detector: %s in view %s; not used", why, v.name)
            out.append(None)
            diag[v.name] = {"found": False, "why": why}
            continue
        out.append(
            ViewDetection(
                np.asarray(det.landmarks_px, np.float64),
                np.asarray(det.centerline_px, np.float64),
                _as_bool(det.mask),
                np.asarray(det.landmark_confidence, np.float64),
                "detector",
            )
        )
        diag[v.name] = {
            "found": True,
            "source": "detector",
            "landmarks_px": np.asarray(det.landmarks_px).tolist(),
            "confidence": [float(c) for c in det.landmark_confidence],
        }
    return out, diag
