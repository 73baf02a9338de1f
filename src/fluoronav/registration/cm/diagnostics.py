"""How far a CM registration can be trusted, per view: what its result says about itself.

Two measures per view, both computable without the truth:

- ``landmark_residual_mm``: the larger detector distance between the registered CM's landmarks A and B,
  projected, and the detected ones: large if the registration slid along the CM or onto another structure.
- ``edge_ncc``: the gradient NCC between the view's ROI and the registered CM's DRR, over the pixels
  where the DRR has an edge (the CM's outline, dilated by 2 px): near 1 where the outline lies on
  the CM in the image, lower where it lies beside it.

The thresholds that decide are :class:`~fluoronav.registration.cm.checks.CMCheckConfig`'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fluoronav.registration.cm.result import CMRegistrationResult
from fluoronav.registration.similarity import edge_ncc as similarity_edge_ncc

__all__ = ["CMViewDiagnostics", "cm_view_diagnostics", "edge_ncc"]

#: the CIOS Fusion detector's pixel pitch, mm: the unit of landmark residuals when a view has none
FULL_PIXEL_SPACING_MM = 0.194


@dataclass(frozen=True)
class CMViewDiagnostics:
    """One view's agreement with a CM registration.

    Attributes:
        landmark_residual_mm: max over A, B of |registered − detected| at the detector (mm); None
            without a detection in that view.
        edge_ncc: gradient NCC (−1 … 1) of the ROI and the registered CM's DRR on the DRR's edges.
    """

    landmark_residual_mm: float | None
    edge_ncc: float

    def to_dict(self) -> dict[str, float | None]:
        return {"landmark_residual_mm": self.landmark_residual_mm, "edge_ncc": self.edge_ncc}


def edge_ncc(image: np.ndarray, drr: np.ndarray, *, dilate_px: int = 2, sigma_px: float = 1.0) -> float:
    """:func:`fluoronav.registration.similarity.edge_ncc` of the CM's DRR, in float64."""
    return similarity_edge_ncc(
        np.asarray(image, np.float64), np.asarray(drr, np.float64), dilate_px=dilate_px, sigma_px=sigma_px
    )


def cm_view_diagnostics(
    result: CMRegistrationResult,
    landmarks_px: Sequence[np.ndarray | None],
    pixel_spacing_mm: Sequence[float | None],
) -> list[CMViewDiagnostics]:
    """Per view of ``result``: landmark residual (mm at the detector) and edge NCC.

    Args:
        result: a CM registration (its views in the order of ``landmarks_px``).
        landmarks_px: per view the detected (2, 2) A, B in the view's image pixels, or None.
        pixel_spacing_mm: per view the image's pixel pitch at the detector (None: the CIOS Fusion
            pitch at full resolution).
    """
    out = []
    for k, (lm, ps) in enumerate(zip(landmarks_px, pixel_spacing_mm, strict=True)):
        res_mm = None
        if lm is not None:
            d_px = np.linalg.norm(np.asarray(result.landmarks_px[k]) - np.asarray(lm, np.float64), axis=1)
            res_mm = float(d_px.max() * (ps if ps is not None else FULL_PIXEL_SPACING_MM))
        out.append(CMViewDiagnostics(res_mm, edge_ncc(result.roi_images[k], result.roi_drrs[k])))
    return out
