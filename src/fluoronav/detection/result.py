"""The detector's result for one image and its output files.

:class:`Detection` holds what the detector found in an image and says whether a registration may
start from it (:attr:`Detection.usable`); :func:`write_detection` writes it as the ``detect``
command's files: the contract JSON (:func:`detection_to_dict`) and the mask as a PNG.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from fluoronav.detection.config import ASSUMED_SPACING_MM
from fluoronav.detection.decoder import distances_to_mask, truncated_landmarks
from fluoronav.errors import InputError

__all__ = ["ASSUMED_SPACING_MM", "OFF_MASK_MM", "Detection", "detection_to_dict", "write_detection"]

#: a found landmark further than this (mm at the detector) from the mask is not on the CM: its
#: detection is not usable (the CM's tube is ~6 mm wide and A and B lie on it; no landmark of the
#: validation sets is more than 3 mm off its mask)
OFF_MASK_MM = 3.0


@dataclass(frozen=True)
class Detection:
    """Result of one image.

    Attributes:
        found: whether a CM was detected; if False there are no landmarks and no centreline.
        landmarks_px: (2, 2) [[uA, vA], [uB, vB]] in the input image's pixels, or None.
        landmark_confidence: (2,) heatmap peak values in [0, 1] (0 where nothing was found).
        mask: (rows, cols) bool segmentation at the input size.
        centerline_px: (P, 2) ordered A → B, or None.
        pixel_spacing_mm: detector pixel spacing of the input when known (passed through).
    """

    found: bool
    landmarks_px: np.ndarray | None
    landmark_confidence: np.ndarray
    mask: np.ndarray
    centerline_px: np.ndarray | None
    pixel_spacing_mm: float | None = None

    @property
    def landmark_truncated(self) -> np.ndarray:
        """(2,) bool, True for a landmark on the image border where the mask meets that border: the
        CM goes on outside the image and the point is where it leaves, not the landmark
        (:func:`~fluoronav.detection.decoder.truncated_landmarks`). All False when nothing was found."""
        if not self.found or self.landmarks_px is None:
            return np.zeros(2, dtype=bool)
        return truncated_landmarks(self.mask, self.landmarks_px)

    @property
    def landmark_off_mask(self) -> np.ndarray:
        """(2,) bool, True for a landmark more than :data:`OFF_MASK_MM` (mm at the detector; images
        without a pixel spacing are taken to have :data:`ASSUMED_SPACING_MM` pixels) from every pixel
        of the mask: A and B lie on the CM, so such a landmark is on something else (a shaft's far
        end). All False when nothing was found."""
        if not self.found or self.landmarks_px is None or not self.mask.any():
            return np.zeros(2, dtype=bool)
        dist_px = distances_to_mask(self.mask, np.asarray(self.landmarks_px))
        return dist_px * (self.pixel_spacing_mm or ASSUMED_SPACING_MM) > OFF_MASK_MM

    @property
    def usable(self) -> bool:
        """Found, with both landmarks inside the image and on the CM's mask: what a registration may
        start from."""
        return self.unusable_reason is None

    @property
    def unusable_reason(self) -> str | None:
        """Why the detection cannot give a registration its landmarks (None: it can)."""
        if not self.found or self.landmarks_px is None:
            return "no CM found"
        cut = [name for name, t in zip("AB", self.landmark_truncated, strict=True) if t]
        if cut:
            return f"the CM leaves the image at landmark {' and '.join(cut)}"
        off = [name for name, o in zip("AB", self.landmark_off_mask, strict=True) if o]
        if off:
            return f"landmark {' and '.join(off)} off the CM's mask"
        return None


def detection_to_dict(det: Detection, mask_file: str) -> dict[str, Any]:
    """The JSON of a detection written by ``fluoronav detect`` (``found``, ``landmarks_px``, …)."""
    return {
        "found": bool(det.found),
        "landmarks_px": None if det.landmarks_px is None else np.asarray(det.landmarks_px).tolist(),
        "landmark_confidence": [float(c) for c in det.landmark_confidence],
        "centerline_px": None if det.centerline_px is None else np.asarray(det.centerline_px).tolist(),
        "mask": mask_file,
        "rows": int(det.mask.shape[0]),
        "cols": int(det.mask.shape[1]),
        "pixel_spacing_mm": det.pixel_spacing_mm,
        "landmark_truncated": [bool(x) for x in det.landmark_truncated],
    }


def write_detection(det: Detection, out_dir: str | Path, stem: str) -> Path:
    """Write ``out_dir/<stem>.json`` and ``out_dir/<stem>_mask.png`` (0/255); returns the JSON path."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    mask_name = f"{stem}_mask.png"
    if not cv2.imwrite(str(out_dir / mask_name), det.mask.astype(np.uint8) * 255):
        raise InputError(out_dir / mask_name, "could not write the mask PNG")
    json_path = out_dir / f"{stem}.json"
    json_path.write_text(json.dumps(detection_to_dict(det, mask_name), indent=1) + "\n", encoding="utf-8")
    return json_path
