"""The CM shaft's depth from its apparent width in one image: a cue that one view's centreline lacks.

One view's centreline alone does not tell the CM's depth from its tilt (equal-cost minima 175 mm
apart). The rigid shaft behind landmark A shows at a width that scales with ``focal / depth``; its
profile (:func:`~fluoronav.detection.tube_profile.fit_tube_profile`) gives that depth, used by the
centreline initialisation as a term ``½((z_pred − z_meas)/σ)²`` of the cost.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from fluoronav.detection.tube_profile import fit_tube_profile, shaft_axis_px
from fluoronav.geometry.camera import Camera, project_points
from fluoronav.manipulator import CMConfig

__all__ = [
    "SHAFT_DEPTH_SIGMA_FRACTION",
    "SHAFT_SEARCH_MARGIN_MM",
    "ShaftDepthCue",
    "measure_shaft_depth",
    "shaft_depth_residual",
]

#: σ of the measured shaft depth as a fraction of it: the spread of the measured depth on
#: physics-simulated images (docs/validation.md)
SHAFT_DEPTH_SIGMA_FRACTION = 0.02
#: the shaft's scale is searched for depths this far either side of the CM's depth range (the shaft
#: reaches behind A), mm
SHAFT_SEARCH_MARGIN_MM = 50.0
#: length of the shaft segment projected to find the local image scale (pixels per mm), mm
_SCALE_SEGMENT_MM = 10.0


@dataclass(frozen=True)
class ShaftDepthCue:
    """The CM shaft's distance from the source, measured from its apparent width
    (:func:`~fluoronav.detection.tube_profile.fit_tube_profile` along the centreline's continuation
    behind A, :func:`~fluoronav.detection.tube_profile.shaft_axis_px`).

    Attributes:
        depth_mm: measured camera-frame z of the sampled stretch of shaft (``focal / px_per_mm``).
        sigma_mm: its assumed error σ.
        distances_px: (Q,) image distances behind A of the profiles that were fitted.
        shaft_length_mm: length of the shaft behind A.
    """

    depth_mm: float
    sigma_mm: float
    distances_px: np.ndarray
    shaft_length_mm: float


def measure_shaft_depth(
    camera: Camera,
    image: np.ndarray,
    centerline_px: np.ndarray,
    *,
    config: CMConfig,
    shaft_length_mm: float,
    depth_range_mm: tuple[float, float],
    sigma_fraction: float = SHAFT_DEPTH_SIGMA_FRACTION,
    search_margin_mm: float = SHAFT_SEARCH_MARGIN_MM,
) -> ShaftDepthCue | None:
    """Measure :class:`ShaftDepthCue` in ``image`` (None when the shaft's profile does not fit).

    Args:
        camera: the view (its ``K``).
        image: (H, W) −log X-ray in this camera's pixels.
        centerline_px: (P, 2) the extracted centreline, ordered A → B, pixels.
        config: CM geometry (the shaft's outer and inner radii).
        shaft_length_mm: length of the rigid shaft behind A.
        depth_range_mm: (min, max) camera-frame depth of A being searched.
        sigma_fraction: σ of the cue as a fraction of the measured depth.
        search_margin_mm: the shaft's scale is searched for depths this far either side of
            ``depth_range_mm`` (clipped to start 1 mm past the source).
    """
    cl = np.asarray(centerline_px, dtype=np.float64)
    ax = shaft_axis_px(cl)
    f = float(camera.K[0, 0])
    lo, hi = max(depth_range_mm[0] - search_margin_mm, 1.0), depth_range_mm[1] + search_margin_mm
    fit = fit_tube_profile(
        image,
        ax,
        outer_radius_mm=config.outer_radius_mm,
        inner_radius_mm=config.inner_radius_mm,
        px_per_mm_range=(f / hi, f / lo),
    )
    if fit is None:
        return None
    z = fit.depth_mm(f)
    return ShaftDepthCue(
        depth_mm=z,
        sigma_mm=sigma_fraction * z,
        distances_px=np.linalg.norm(ax - cl[0], axis=1),
        shaft_length_mm=float(shaft_length_mm),
    )


def shaft_depth_residual(cue: ShaftDepthCue, K: torch.Tensor, camera_from_cm: torch.Tensor) -> torch.Tensor:
    """(N,) normalised residual ``(z_pred − z_meas)/σ`` of candidate poses (N, 4, 4): the predicted
    depth is the mean z of the shaft points (behind A along −z of the CM frame) whose images lie at the
    measured profiles' distances behind A."""
    A = camera_from_cm[:, :3, 3]
    axis = -camera_from_cm[:, :3, 2]
    eye = torch.eye(4, dtype=K.dtype, device=K.device).expand(A.shape[0], 4, 4)
    pts = torch.stack([A, A + _SCALE_SEGMENT_MM * axis], dim=1)  # (N, 2, 3)
    uv = project_points(K, eye, pts)
    px_per_mm = ((uv[:, 1] - uv[:, 0]).norm(dim=-1) / _SCALE_SEGMENT_MM).clamp_min(1e-6)
    d = torch.as_tensor(cue.distances_px, dtype=K.dtype, device=K.device)
    t = (d[None, :] / px_per_mm[:, None]).clamp(0.0, cue.shaft_length_mm)
    z = A[:, 2:3] + t * axis[:, 2:3]
    return (z.mean(dim=1) - cue.depth_mm) / cue.sigma_mm
