"""The checks of a detection after its patch stages: where landmark A sits, and the mask's edges.

Landmark A is where the CM meets its mounting shaft. The fine stage can put it elsewhere along the
tube: at the far end of a short shaft stub that it took for part of the CM (a free end of a tube,
:class:`FreeEndCheck`), or on a plain stretch of shaft (:class:`ShaftCheck`, with a patch network
trained on the shaft). Each check reads A again and runs the detection's last steps (a
:data:`Finish`: refinement, centreline and the patch-mask stages) from there. :class:`EdgeCheck`
asks whether the image has an edge where the final mask has its boundary.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from fluoronav.detection.config import EdgeConfig, FreeEndConfig, ShaftConfig
from fluoronav.detection.decoder import (
    along_centerline,
    cm_start_index,
    component_at,
    core_logits,
    distances_to_mask,
    tube_paste,
)
from fluoronav.detection.evidence import end_continuation, local_tube_width_px, mask_edge_ratio
from fluoronav.detection.localize import FineResult, FineStage
from fluoronav.detection.patch_stages import patch_logits
from fluoronav.detection.patches import RefinePatch, tube_frames
from fluoronav.detection.runtime import Networks
from fluoronav.detection.views import scaled_view

logger = logging.getLogger(__name__)

__all__ = ["EdgeCheck", "Finish", "Finished", "FreeEndCheck", "ShaftCheck"]


class Finished(NamedTuple):
    """A detection's last steps from its fine landmarks: refined landmarks (2, 2) input px, the
    centreline (N, 2) and the final mask (rows, cols) bool."""

    landmarks_px: np.ndarray
    centerline_px: np.ndarray
    mask: np.ndarray


#: the last steps of a detection from fine landmarks (2, 2) input px
Finish = Callable[[np.ndarray], Finished]


class FreeEndCheck:
    """The free-end check of landmark A: its settings and the fine stage it reads A again with."""

    def __init__(self, config: FreeEndConfig, fine: FineStage) -> None:
        self.config = config
        self.fine = fine

    def __call__(
        self,
        image: np.ndarray,
        res: FineResult,
        final: Finished,
        finish: Finish,
        *,
        pixel_spacing_mm: float | None = None,
    ) -> Finished:
        """``final``, or the same with landmark A read again away from the free end of a tube.

        Where A's fine confidence is at least ``min_confidence`` and the image has less tube around
        the final A outside the final mask than ``max_continuation``
        (:func:`~fluoronav.detection.evidence.end_continuation`), A is on a free end, such as the far
        end of a short shaft stub that the fine stage took for part of the CM; the heatmap of A then
        has a second mode where the CM meets that stub. The last pass's views go through the fine
        network again with A's map excluded within one tube width of the fine A; ``finish`` runs
        from the new fine landmarks, and its result replaces ``final`` where the new A lies on the
        fine mask, a quarter of a tube width or more short of B along the line from the free end to
        B (the stub's end, A and B lie in this order; the CM's tip goes on beyond B, as a shaft does
        beyond A), and has more tube than that fraction around it. B's fine landmark, the fine mask
        and the confidences stay. ``pixel_spacing_mm`` (mm per input pixel, where known) lets finer
        images be binned for the measure.
        """
        cfg = self.config
        pts, mask = final.landmarks_px, final.mask
        if float(res.confidence[0]) < cfg.min_confidence:
            return final
        c = end_continuation(image, mask, pts[0], pixel_spacing_mm=pixel_spacing_mm)
        if c is None or c >= cfg.max_continuation:
            return final
        width_px = local_tube_width_px(mask, pts[0])
        assert width_px is not None  # end_continuation is None for an empty mask
        fine_a = res.landmarks_px[0]
        views = [scaled_view(res.view, f) for f in self.fine.config.sampler.scales]
        _, view_pts, _ = self.fine.views(image, views, exclude_disk=(0, fine_a, width_px))
        fine_pts = res.landmarks_px.copy()
        fine_pts[0] = np.median(view_pts[:, 0], axis=0)
        if distances_to_mask(res.mask, fine_pts[:1])[0] > 1.0:
            logger.debug("A on a free end (continuation %.2f); its next place is off the mask", c)
            return final
        # the stub's far end, A and B lie in this order along the tube: a place not a quarter of a
        # tube width short of B is at B's end (the CM's tip goes on beyond B as a shaft beyond A)
        axis = fine_pts[1] - fine_a
        if float((fine_pts[1] - fine_pts[0]) @ axis) < 0.25 * width_px * float(np.linalg.norm(axis)):
            logger.debug("A on a free end (continuation %.2f); its next place is not short of B", c)
            return final
        other = finish(fine_pts)
        c_new = end_continuation(image, other.mask, other.landmarks_px[0], pixel_spacing_mm=pixel_spacing_mm)
        if c_new is None or c_new <= cfg.max_continuation:
            logger.debug("A on a free end (continuation %.2f); no better place (%s)", c, c_new)
            return final
        moved = float(np.linalg.norm(other.landmarks_px[0] - pts[0]))
        logger.debug(
            "A on a free end (continuation %.2f): moved %.1f px (continuation %.2f)", c, moved, c_new
        )
        return other


class ShaftCheck:
    """The shaft check of landmark A: its settings, the model's networks (its ``shaft`` network), the
    fine stage it reads A again with and the pixel spacing taken for images without one."""

    def __init__(
        self, config: ShaftConfig, networks: Networks, fine: FineStage, *, assumed_spacing_mm: float
    ) -> None:
        self.config = config
        self.networks = networks
        self.fine = fine
        self.assumed_spacing_mm = assumed_spacing_mm

    def logits(self, image: np.ndarray, frames: list[RefinePatch]) -> np.ndarray:
        """(P, rows, cols) mask logits of the shaft network on ``frames``' patches."""
        return patch_logits(self.networks, "shaft", image, frames, tta=self.config.tta)

    def start(
        self,
        image: np.ndarray,
        mask: np.ndarray,
        centerline_px: np.ndarray,
        *,
        pixel_spacing_mm: float | None = None,
    ) -> tuple[int, np.ndarray] | None:
        """Where the shaft network says the CM begins along a centreline (N, 2) (u, v) px from A to B,
        where that is ``cut_min_mm`` or more beyond A: the centreline's index and the fine ``mask``
        (rows, cols) bool redrawn by the network along it; None where A is on the CM, or the network
        cannot judge.

        The network redraws the mask on patches along the centreline (as the tube-mask stage). It
        judges only where it sees the notched CM clearly in one patch at least (``min_cm_logit``,
        :func:`~fluoronav.detection.decoder.core_logits`); A is off the CM where most of the
        centreline's first ``cut_run_mm`` (mm at the detector) lies outside its mask, and the CM
        begins at the centreline's first stretch of that length wholly inside
        (:func:`~fluoronav.detection.decoder.cm_start_index`)."""
        cfg = self.config
        spacing_mm = pixel_spacing_mm or self.assumed_spacing_mm
        step = cfg.sampler.step_px(pixel_spacing_mm, self.assumed_spacing_mm)
        line = np.asarray(centerline_px, dtype=np.float64)
        frames = tube_frames(
            line, step_px=step, shape=cfg.sampler.shape, spacing_px=cfg.sampler.spacing_px * step
        )
        if not frames:
            return None
        logits = self.logits(image, frames)
        if core_logits(logits, band_px=cfg.band_px).max() < cfg.min_cm_logit:
            return None  # the network does not see the notched CM clearly anywhere: it cannot judge
        cm = tube_paste(mask, frames, logits, band_px=cfg.band_px)
        run_px = cfg.cut_run_mm / spacing_mm
        inside, arc = along_centerline(line, cm)
        if float(inside[arc < run_px].mean()) >= 0.5:  # the CM begins at A
            return None
        start = cm_start_index(line, cm, run_px=run_px)
        if start is None or arc[start] * spacing_mm < cfg.cut_min_mm:
            return None
        return start, cm

    def __call__(
        self,
        image: np.ndarray,
        res: FineResult,
        final: Finished,
        finish: Finish,
        *,
        pixel_spacing_mm: float | None = None,
    ) -> Finished:
        """``final``, or the same with landmark A read again where the shaft network's CM begins.

        Where :meth:`start` finds the CM beginning well beyond A along the final centreline, the fine
        stage took a plain stretch of shaft for part of the CM and put A on the shaft. The fine
        stage's last pass then runs again on a ROI fitted to the rest of the CM (the component of the
        fine mask, less what the shaft network left out, that holds B) and B; its A is taken where it
        lies on that rest, no more than 2 mm before the cut along the centreline, else the
        centreline's point where the CM begins. ``finish`` runs from there, B's fine landmark
        staying; the pixels of the fine mask that the shaft network left out stay out of the final
        mask, which keeps the components that hold the landmarks."""
        found = self.start(image, res.mask, final.centerline_px, pixel_spacing_mm=pixel_spacing_mm)
        if found is None:
            return final
        start, cm = found
        spacing_mm = pixel_spacing_mm or self.assumed_spacing_mm
        line = np.asarray(final.centerline_px, dtype=np.float64)
        _, arc = along_centerline(line, cm)
        fine_pts = res.landmarks_px.copy()
        fine_pts[0] = line[start]
        rest = component_at(res.mask & cm, fine_pts[1:])
        if rest.any():
            # the fine stage sees the CM without the shaft: it places A where the notches begin
            vv, uu = np.nonzero(rest)
            corners = np.array([[uu.min() - 0.5, vv.min() - 0.5], [uu.max() + 0.5, vv.max() + 0.5]])
            roi = self.fine.roi_around(np.concatenate([corners, fine_pts[1:]]))
            scales = self.fine.config.sampler.scales
            _, view_pts, _ = self.fine.views(image, [scaled_view(roi, f) for f in scales])
            a_new = np.median(view_pts[:, 0], axis=0)
            at = int(np.argmin(np.linalg.norm(line - a_new, axis=1)))
            if distances_to_mask(rest, a_new[None])[0] <= 2.0 and arc[at] >= arc[start] - 2.0 / spacing_mm:
                fine_pts[0] = a_new
        logger.debug("A on the shaft: %.1f mm of the centreline not CM", arc[start] * spacing_mm)
        other = finish(fine_pts)
        # the shaft's end beyond the old A, outside every band, is left apart from the CM: dropped
        kept = component_at(other.mask & ~(res.mask & ~cm), other.landmarks_px)
        return other._replace(mask=kept)


class EdgeCheck:
    """The edge check of a detection's mask."""

    def __init__(self, config: EdgeConfig) -> None:
        self.config = config

    def __call__(self, image: np.ndarray, mask: np.ndarray, *, confidence: float, spacing_mm: float) -> bool:
        """Whether a detection whose smaller landmark confidence is ``confidence`` has an edge
        along its mask's (rows, cols) boundary in ``image`` (pixels of ``spacing_mm``)."""
        need = self.config.needed_ratio(confidence)
        if need <= 0.0:
            return True
        ratio = mask_edge_ratio(image, mask, pixel_spacing_mm=spacing_mm)
        if ratio < need:
            logger.debug("no edge on the mask's boundary (ratio %.2f < %.2f): no CM", ratio, need)
            return False
        return True
