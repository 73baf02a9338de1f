"""The patch stages: landmark refinement, the tube mask and the mask's ends, on tube-aligned patches.

- Refinement (:class:`RefineStage`): the fine stage sets where the notch pattern starts (A) and ends
  (B) along the tube to about a stored pixel; this stage reads each landmark again on patches at
  twice the training images' sampling (a spatial-softmax heatmap), with a Gaussian prior around the
  fine landmark (a patch alone can take the tube's end beyond B, or the base before A, for it), from
  several patches moved along the tube, and takes the mean.
- Tube mask (:class:`TubeStage`): a patch every ``spacing_px`` on the centreline decides the mask near it.
- Mask ends (:class:`EndsStage`): each end of the label mask is half the ellipse the tube's
  cross-section projects to there, bulging beyond the landmark; a patch at each refined landmark
  redraws the mask from ``inner_px`` inside the landmark outwards.
"""

from __future__ import annotations

import numpy as np
import torch

from fluoronav.detection.config import EndsConfig, RefineConfig, TubeConfig
from fluoronav.detection.decoder import decode_refine_logits, end_zone_paste, tube_paste
from fluoronav.detection.patches import RefinePatch, refine_patch, sample_patches, tube_frames
from fluoronav.detection.runtime import Networks

__all__ = ["EndsStage", "RefineStage", "TubeStage", "patch_logits"]


def patch_logits(
    networks: Networks, stage: str, image: np.ndarray, frames: list[RefinePatch], *, tta: int
) -> np.ndarray:
    """(P, rows, cols) mask logits of a patch-mask stage's network on ``frames``' patches of
    ``image`` (:func:`~fluoronav.detection.patches.sample_patches`), with ``tta`` 2 each averaged with
    that of its mirror image about the tube's axis (one batch)."""
    out = networks.patches(stage, sample_patches(image, frames), tta=tta)
    return out[:, 0].cpu().numpy()


class RefineStage:
    """The landmark refinement stage of a model."""

    def __init__(self, config: RefineConfig, networks: Networks, *, assumed_spacing_mm: float) -> None:
        self.config = config
        self.networks = networks
        self.assumed_spacing_mm = assumed_spacing_mm

    def __call__(
        self,
        image: np.ndarray,
        landmarks_px: np.ndarray,
        mask: np.ndarray,
        *,
        pixel_spacing_mm: float | None = None,
    ) -> np.ndarray:
        """The landmarks (2, 2) (u, v) input px refined on tube-aligned patches; each landmark whose
        direction the mask (rows, cols) bool does not give (a CM seen end-on) keeps its place.

        Each landmark is read from one patch per ``sampler.shifts_px`` (moved along the tube, the
        prior staying at the landmark) and the mean of those estimates is taken. All patches of both
        landmarks and their mirror images (``tta``) go through the network in one batch.
        """
        cfg = self.config
        step = cfg.sampler.step_px(pixel_spacing_mm, self.assumed_spacing_mm)
        todo: list[tuple[int, RefinePatch]] = []  # (landmark, patch)
        for k, p in enumerate(landmarks_px):
            frame = refine_patch(mask, p, step_px=step, shape=cfg.sampler.shape)
            if frame is not None:
                todo += [(k, frame.shifted(d)) for d in cfg.sampler.shifts_px]
        if not todo:
            return landmarks_px
        out = self.networks.patches(
            "refine", np.stack([fr.sample(image) for _, fr in todo]), tta=cfg.tta
        ).cpu()
        ks = np.array([k for k, _ in todo])
        sel = out[torch.arange(len(todo)), torch.from_numpy(ks)][:, None]
        # the prior stays at the fine stage's landmark in every shifted patch
        centers = np.stack([fr.from_input(landmarks_px[k]) for k, fr in todo])
        pts, _ = decode_refine_logits(
            sel,
            sigma_px=cfg.decoder.sigma_px,
            prior_px=cfg.decoder.prior_px,
            prior_center_px=torch.from_numpy(centers).float(),
        )
        estimates = np.stack(
            [fr.to_input(q) for (_, fr), q in zip(todo, pts.numpy().astype(np.float64), strict=True)]
        )
        refined = np.array(landmarks_px, dtype=np.float64, copy=True)
        for k in np.unique(ks):
            refined[k] = estimates[ks == k].mean(axis=0)
        return refined


class TubeStage:
    """The tube-mask stage of a model."""

    def __init__(self, config: TubeConfig, networks: Networks, *, assumed_spacing_mm: float) -> None:
        self.config = config
        self.networks = networks
        self.assumed_spacing_mm = assumed_spacing_mm

    def frames(
        self, centerline_px: np.ndarray, *, pixel_spacing_mm: float | None = None
    ) -> list[RefinePatch]:
        """The patches along a centreline (N, 2) (u, v) input px from A to B, every ``spacing_px``
        patch pixels of arc length (:func:`~fluoronav.detection.patches.tube_frames`)."""
        sampler = self.config.sampler
        step = sampler.step_px(pixel_spacing_mm, self.assumed_spacing_mm)
        return tube_frames(
            centerline_px, step_px=step, shape=sampler.shape, spacing_px=sampler.spacing_px * step
        )

    def __call__(
        self,
        image: np.ndarray,
        centerline_px: np.ndarray,
        mask: np.ndarray,
        *,
        pixel_spacing_mm: float | None = None,
    ) -> np.ndarray:
        """The mask (rows, cols) bool redrawn along the tube: each patch decides the band of
        ``band_px`` around its centre (mean logits where bands overlap). All patches (and with ``tta``
        2 their mirror images) go through the network in one batch."""
        frames = self.frames(centerline_px, pixel_spacing_mm=pixel_spacing_mm)
        if not frames:
            return mask
        logits = patch_logits(self.networks, "tube", image, frames, tta=self.config.tta)
        return tube_paste(mask, frames, logits, band_px=self.config.band_px)


class EndsStage:
    """The mask-end stage of a model."""

    def __init__(self, config: EndsConfig, networks: Networks, *, assumed_spacing_mm: float) -> None:
        self.config = config
        self.networks = networks
        self.assumed_spacing_mm = assumed_spacing_mm

    def __call__(
        self,
        image: np.ndarray,
        landmarks_px: np.ndarray,
        mask: np.ndarray,
        *,
        pixel_spacing_mm: float | None = None,
    ) -> np.ndarray:
        """The mask (rows, cols) bool with its ends redrawn on a tube-aligned patch at each landmark
        (2, 2) (u, v) input px; unchanged at a landmark whose direction the mask does not give. Both
        patches (and with ``tta`` 2 their mirror images) go through the network in one batch."""
        cfg = self.config
        step = cfg.sampler.step_px(pixel_spacing_mm, self.assumed_spacing_mm)
        frames = [refine_patch(mask, p, step_px=step, shape=cfg.sampler.shape) for p in landmarks_px]
        todo = [f for f in frames if f is not None]
        if not todo:
            return mask
        for frame, logit in zip(
            todo, patch_logits(self.networks, "ends", image, todo, tta=cfg.tta), strict=True
        ):
            mask = end_zone_paste(mask, frame, logit, inner_px=cfg.inner_px)
        return mask
