"""The views of a view set: each C-arm image with its camera and the CM found in it, and the views
the bone registrations see (the CM and its shaft left out of the similarity).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fluoronav.detection.instrument import instrument_masks
from fluoronav.geometry.camera import Camera
from fluoronav.registration.bone import BoneView

__all__ = [
    "FluoroView",
    "ViewDetection",
    "bone_views",
]


@dataclass(frozen=True, eq=False)
class ViewDetection:
    """The CM found in one view.

    Attributes:
        landmarks_px: (2, 2) A, B (u, v) in the view's pixels.
        centerline_px: (P, 2) ordered A → B.
        mask: (rows, cols) bool CM region.
        confidence: (2,) the detector's confidence of A and B (1 for given landmarks).
        source: where it came from ("detector", "case", "oracle").
    """

    landmarks_px: np.ndarray
    centerline_px: np.ndarray
    mask: np.ndarray
    confidence: np.ndarray
    source: str


@dataclass(frozen=True, eq=False)
class FluoroView:
    """One C-arm image of a view set.

    Attributes:
        name: unique within its set; names the view in diagnostics and refusals.
        image: (rows, cols) float log image (bright = attenuating).
        camera: intrinsics and the initial ``camera_from_world`` (world = CT: an estimate the
            pelvis registration replaces).
        detection: the CM found in it, or None where none is usable.
    """

    name: str
    image: np.ndarray
    camera: Camera
    detection: ViewDetection | None = None


def bone_views(views: Sequence[FluoroView]) -> list[BoneView]:
    """The views for the bone registrations, the CM and its shaft (where detected) left out of the
    similarity (:func:`~fluoronav.detection.instrument.instrument_masks`)."""
    detections = [v.detection for v in views]
    instruments = instrument_masks(
        [None if d is None else d.mask for d in detections],
        [None if d is None else d.centerline_px for d in detections],
        [v.image for v in views],
    )
    return [
        BoneView(np.asarray(v.image, np.float32), v.camera, None if m is None else ~np.asarray(m, dtype=bool))
        for v, m in zip(views, instruments, strict=True)
    ]
