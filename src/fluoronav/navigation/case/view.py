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
        moved_from: a verification view only: the first view whose C-arm position this one was
            taken from (the case file's ``moved_from.view``, or ``same_camera_as``), or None.
        carm_motion: (4, 4) with ``moved_from``: the C-arm's nominal motion since that view,
            ``carm_after_from_carm_before`` (mm; the identity where the C-arm did not move). The
            verification then starts this view's camera from the first registration's camera of
            that view moved by it, and registers its bones locally.
    """

    name: str
    image: np.ndarray
    camera: Camera
    landmarks_px: np.ndarray | None = None
    mask: np.ndarray | None = None
    moved_from: str | None = None
    carm_motion: np.ndarray | None = None
