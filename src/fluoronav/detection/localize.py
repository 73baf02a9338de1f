"""The view stages: the coarse stage finds the CM in the whole image, the fine stage reads its
landmarks and mask from regions of interest around it.

The coarse stage (:class:`CoarseStage`) runs its network once on the whole image at its working resolution
(:class:`~fluoronav.detection.config.WholeViewSampler`). The fine stage (:class:`FineStage`) runs on a square
region of interest around the coarse mask and landmarks, resampled from the *input* image, so its precision is
set by the ROI's pixel size (≈ the CM's extent / 128 × 1.5), not by the coarse grid: each pass but the last
refits the ROI to its result, the last runs on the ROI at several scales; its heatmaps are decoded with a
sub-pixel fit and its mask mapped back to the input grid (:mod:`fluoronav.detection.decoder`). It also weighs
other hypotheses: other parts of the coarse mask (:meth:`FineStage.hypotheses`) and a wider view of an unsure
result (:meth:`FineStage.second_look`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
import torch

from fluoronav.detection.config import CoarseConfig, FineConfig
from fluoronav.detection.decoder import component_at, decode_views, mask_at_input, reaches_edge
from fluoronav.detection.runtime import Networks
from fluoronav.detection.views import View, full_view, roi_view, scaled_view, view_input

logger = logging.getLogger(__name__)

__all__ = ["CoarseResult", "CoarseStage", "FineResult", "FineStage"]


class CoarseResult(NamedTuple):
    """The coarse stage's view, seg logit (S, S), landmarks (2, 2) in input px and confidences (2,)."""

    view: View
    logit: np.ndarray
    landmarks_px: np.ndarray
    confidence: np.ndarray


@dataclass(frozen=True)
class FineResult:
    """One fine-stage hypothesis: landmarks (2, 2) input px, confidences (2,), mask (rows, cols) bool
    and the last pass's ROI at scale 1."""

    landmarks_px: np.ndarray
    confidence: np.ndarray
    mask: np.ndarray
    view: View


#: whether a fine result counts as a detection
Accept = Callable[[FineResult], bool]


class CoarseStage:
    """The coarse stage of a model: its settings and the model's networks."""

    def __init__(self, config: CoarseConfig, networks: Networks) -> None:
        self.config = config
        self.networks = networks

    def view(self, shape: tuple[int, int], pixel_spacing_mm: float | None = None) -> View:
        """The view of a (rows, cols) image: the whole image, widened to ``min_field_mm`` where the
        pixel spacing (mm) is known and the image is smaller."""
        sampler = self.config.sampler
        field_mm = sampler.min_field_mm
        min_side = field_mm / pixel_spacing_mm if field_mm > 0 and pixel_spacing_mm else 0.0
        return full_view(shape, sampler.size, min_side_px=min_side)

    def __call__(self, image: np.ndarray, *, pixel_spacing_mm: float | None = None) -> CoarseResult:
        """The coarse stage on a (rows, cols) image."""
        cfg = self.config
        cv = self.view(image.shape, pixel_spacing_mm)
        x = view_input(image, cv, low_pct=cfg.sampler.low_pct, high_pct=cfg.sampler.high_pct)[None]
        logit, pts, conf = decode_views(
            self.networks.views("coarse", x),
            heatmap=cfg.decoder.heatmap,
            sigma_px=cfg.decoder.sigma_px,
            threshold_logit=cfg.decoder.threshold_logit,
        )
        return CoarseResult(cv, logit[0], cv.to_input(pts[0]), conf[0])


class FineStage:
    """The fine stage of a model: its settings, the model's networks, the confidence from which a
    landmark places a ROI (``min_confidence``) and the pixel spacing taken for images without one."""

    def __init__(
        self, config: FineConfig, networks: Networks, *, min_confidence: float, assumed_spacing_mm: float
    ) -> None:
        self.config = config
        self.networks = networks
        self.min_confidence = min_confidence
        self.assumed_spacing_mm = assumed_spacing_mm

    def views(
        self,
        image: np.ndarray,
        views: list[View],
        *,
        tta: int | None = None,
        exclude_disk: tuple[int, np.ndarray, float] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The fine network on several ROIs in one batch: seg logits (N, R, R), landmarks (N, 2, 2) in
        input px, confidences (N, 2). ``tta``: dihedral transforms per view (None: ``passes.tta``).
        ``exclude_disk``: (landmark index, centre (2,) input px, radius input px), a disk where that
        landmark may not be taken."""
        cfg = self.config
        sampler, dec = cfg.sampler, cfg.decoder
        stack = np.stack(
            [view_input(image, v, low_pct=sampler.low_pct, high_pct=sampler.high_pct) for v in views]
        )
        tta = cfg.passes.tta if tta is None else tta
        exclude = None
        if exclude_disk is not None:
            k, centre, radius = exclude_disk
            size = stack.shape[-1]
            exclude = torch.zeros((len(views), 2, size, size), dtype=torch.bool)
            grid = np.arange(size, dtype=np.float64)
            for i, v in enumerate(views):
                cu, cv_ = v.from_input(np.asarray(centre, dtype=np.float64))
                disk = np.hypot(grid[None, :] - cu, grid[:, None] - cv_) <= radius / v.scale
                exclude[i, k] = torch.from_numpy(disk)
        logits, pts, conf = decode_views(
            self.networks.views("fine", stack, tta=tta),
            heatmap=dec.heatmap,
            sigma_px=dec.sigma_px,
            threshold_logit=dec.threshold_logit,
            min_separation_px=dec.min_separation_px,
            support_px=dec.support_px,
            exclude=exclude,
        )
        return logits, np.stack([v.to_input(p) for v, p in zip(views, pts, strict=True)]), conf

    def __call__(self, image: np.ndarray, view: View) -> FineResult:
        """:meth:`run`."""
        return self.run(image, view)

    def run(self, image: np.ndarray, view: View) -> FineResult:
        """All fine passes from a first ROI: landmarks (2, 2) in input px, confidences (2,), the mask
        (rows, cols) bool at the input size and the last pass's ROI (at scale 1).

        Each pass but the last refits the ROI to its result; the last runs on the ROI scaled by each
        of ``sampler.scales`` in one batch (median landmarks and confidences, mean logits), with
        ``passes.sure_tta`` transforms where the pass before it was sure of both landmarks. While a
        pass's mask reaches the edge of its ROI inside the image (the CM goes on beyond it: the
        coarse stage found only part of it), passes are added, up to ``passes.max_passes`` in all,
        each on a ROI refitted to the larger mask.
        """
        cfg = self.config
        p = cfg.passes
        first_tta = p.tta if p.first_tta is None else p.first_tta
        spare = max(p.max_passes - max(p.passes, 1), 0)
        remaining = max(p.passes, 1) - 1  # single passes before the last
        sure = False  # whether the pass before the last was sure of both landmarks
        while remaining > 0:
            logits, pts, confs = self.views(image, [view], tta=first_tta)
            f_logit, f_pts, f_conf = logits[0], pts[0], confs[0]
            sure = bool(np.all(f_conf >= p.sure_confidence))
            refit = self.refit(image, view, f_logit, f_pts, f_conf)
            if refit is None:
                break
            view, reached = refit
            remaining -= 1
            if reached and spare > 0:
                spare, remaining = spare - 1, remaining + 1
        while True:
            views = [scaled_view(view, f) for f in cfg.sampler.scales]
            tta = p.sure_tta if sure else None  # None: passes.tta
            logits, pts, confs = self.views(image, views, tta=tta)
            f_pts, f_conf = np.median(pts, axis=0), np.median(confs, axis=0)
            if spare > 0:
                # the view of the scale nearest 1 decides whether the CM goes on beyond the ROI
                k = int(np.argmin([abs(f - 1.0) for f in cfg.sampler.scales]))
                refit = self.refit(image, views[k], logits[k], pts[k], confs[k])
                if refit is not None and refit[1]:
                    spare -= 1
                    view = refit[0]
                    sure = bool(np.all(f_conf >= p.sure_confidence))
                    continue
            mask = mask_at_input(
                logits,
                views,
                image.shape,
                cfg.decoder.threshold_logit,
                f_pts,
                join_frac=cfg.decoder.join_frac,
            )
            return FineResult(f_pts, f_conf, mask, view)

    def refit(
        self, image: np.ndarray, view: View, logit: np.ndarray, pts: np.ndarray, conf: np.ndarray
    ) -> tuple[View, bool] | None:
        """The ROI fitted to one pass's result (seg logit (R, R), landmarks (2, 2) input px,
        confidences (2,)) and whether its mask reached the old ROI's edge; None if the mask is empty."""
        roi_mask = logit > self.config.decoder.threshold_logit
        if not roi_mask.any():
            return None
        sure = pts[conf >= self.min_confidence]
        component = component_at(roi_mask, view.from_input(sure))
        # again on a ROI fitted to this pass's result: its scale matches training more closely
        return self.roi(view, component, sure), reaches_edge(component, view, image.shape)

    def roi(self, view: View, view_mask: np.ndarray, landmarks_input: np.ndarray) -> View:
        """The ROI around a mask in ``view`` pixels and landmarks (N, 2) in input pixels."""
        vv, uu = np.nonzero(view_mask)
        corners = view.to_input(
            np.array([[uu.min() - 0.5, vv.min() - 0.5], [uu.max() + 0.5, vv.max() + 0.5]])
        )
        return self.roi_around(np.concatenate([corners, np.asarray(landmarks_input).reshape(-1, 2)]))

    def roi_around(self, points_px: np.ndarray) -> View:
        """The ROI around points (N, 2) (u, v) input px (:func:`~fluoronav.detection.views.roi_view`
        with the sampler's margin and smallest side)."""
        sampler = self.config.sampler
        return roi_view(
            points_px, sampler.size, margin_frac=sampler.margin_frac, min_side_px=sampler.min_side_px
        )

    def hypotheses(
        self,
        image: np.ndarray,
        cv: View,
        c_mask: np.ndarray,
        c_pts: np.ndarray,
        first: FineResult,
        *,
        accept: Accept,
        first_mask: np.ndarray | None = None,
        both: bool = True,
    ) -> FineResult:
        """``first``, or a hypothesis from another part of the coarse mask (view px) that is surer by
        ``hypotheses.min_gain``: with ``coarse_split``, where the two landmarks (2, 2) input px
        (``both`` confident) lie on different components, the fine stage from each one's component
        alone with its landmark; with ``coarse_other_min_px``, from each component of that many
        pixels or more outside ``first_mask`` (the components ``first`` started from) alone."""
        hyp = self.config.hypotheses
        starts: list[View] = []
        if hyp.coarse_split and both:
            seeds = cv.from_input(c_pts)
            # a seed on no component gets the largest one, a mask of one component itself: both overlap
            parts = [component_at(c_mask, seeds[k : k + 1]) for k in range(2)]
            if not bool((parts[0] & parts[1]).any()):
                starts += [self.roi(cv, parts[k], c_pts[k : k + 1]) for k in range(2)]
        if hyp.coarse_other_min_px > 0 and first_mask is not None:
            n, labels, stats, _ = cv2.connectedComponentsWithStats(c_mask.astype(np.uint8), connectivity=8)
            for j in range(1, n):
                part = labels == j
                if stats[j, cv2.CC_STAT_AREA] >= hyp.coarse_other_min_px and not (part & first_mask).any():
                    starts.append(self.roi(cv, part, np.zeros((0, 2))))
        return self.surest(image, first, starts, accept=accept, what="another part of the coarse mask")

    def surest(
        self, image: np.ndarray, first: FineResult, starts: list[View], *, accept: Accept, what: str
    ) -> FineResult:
        """``first``, or of the fine stage's results from ``starts`` (first ROIs) those that
        ``accept`` takes, the one of the highest mean landmark confidence where that mean is
        ``hypotheses.min_gain`` or more above ``first``'s. ``what`` names the hypotheses in the log."""
        best, best_score = first, float(np.mean(first.confidence)) + self.config.hypotheses.min_gain
        for start in starts:
            other = self.run(image, start)
            score = float(np.mean(other.confidence))
            if score >= best_score and accept(other):
                best, best_score = other, score
        if best is not first:
            logger.debug("%s: confidence %s -> %s", what, first.confidence, best.confidence)
        return best

    def second_look(
        self, image: np.ndarray, first: FineResult, *, pixel_spacing_mm: float | None = None, accept: Accept
    ) -> FineResult:
        """The fine stage's result, or a second hypothesis from a wider view that the network is
        surer of (``hypotheses.wide_factors``).

        A result whose mean landmark confidence is above ``wide_max_confidence`` is returned as it
        is. Otherwise the last pass's ROI scaled by each factor goes through the fine network in one
        batch; each wider view that puts a landmark ``wide_min_shift_mm`` (mm at the detector) or
        more from ``first``'s is followed by all fine passes from a ROI fitted to its result. Of
        these hypotheses, those that ``accept`` takes for a detection, the one of the highest mean
        landmark confidence replaces ``first`` if that mean is ``min_gain`` or more above
        ``first``'s. (The mean, not the smaller one: a CM cut short has its landmark at the cut
        unsure, and the other end's often too.)
        """
        hyp = self.config.hypotheses
        if not hyp.wide_factors or float(np.mean(first.confidence)) > hyp.wide_max_confidence:
            return first
        views = [scaled_view(first.view, f) for f in hyp.wide_factors]
        logits, pts, conf = self.views(image, views)
        spacing_mm = pixel_spacing_mm or self.assumed_spacing_mm
        shift_mm = np.linalg.norm(pts - first.landmarks_px, axis=-1).max(axis=-1) * spacing_mm
        starts = []
        for j in np.flatnonzero(shift_mm >= hyp.wide_min_shift_mm):
            refit = self.refit(image, views[j], logits[j], pts[j], conf[j])
            if refit is not None:
                starts.append(refit[0])
        return self.surest(image, first, starts, accept=accept, what="second look")
