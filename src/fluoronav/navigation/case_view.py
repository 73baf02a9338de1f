"""One C-arm image of a navigation case (:class:`CaseView`), as the case reader gives it and the
pipeline reads it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluoronav.geometry.camera import Camera

__all__ = ["CaseView"]


@dataclass(frozen=True, eq=False)
class CaseView:
    """One C-arm image of a navigation case.

    Attributes:
        name: unique within its list of views (the case file's ``name``; default ``view<k>``, and
            ``verify<k>`` for verification views).
        image: (rows, cols) float32 log image (bright = attenuating), as
            :func:`fluoronav.detection.detector.load_image` reads it.
        camera: intrinsics and the initial ``camera_from_ct`` (``camera_from_world`` with world = CT).
        landmarks_px: (2, 2) landmarks A, B given with the case (u, v in this image's pixels); when
            present the detector is not run on this view.
        mask: (rows, cols) bool CM mask given with the case (with ``landmarks_px``); when absent with
            given landmarks, the CM region is taken as a band about the segment A-B.
    """

    name: str
    image: np.ndarray
    camera: Camera
    landmarks_px: np.ndarray | None = None
    mask: np.ndarray | None = None
