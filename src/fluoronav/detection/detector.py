"""Inference API of the learned CM detector: :class:`Detector` runs a model's declared stages.

``Detector.load()`` reads the shipped weights (``fluoronav/data/detector.pt``) or a model file written
by ``fluoronav train``; ``Detector.detect(image)`` runs the model's stages in the order of
:data:`~fluoronav.detection.config.STAGE_ORDER`: ``coarse`` on the whole image, ``fine`` on regions
of interest around it (:mod:`fluoronav.detection.localize`; the result must pass the ``accept``
rules), the last steps from the fine landmarks (:meth:`Detector.finish`: ``refine``, the centreline,
``tube`` and ``ends``), then the checks ``free_end``, ``shaft`` and ``edge``
(:mod:`fluoronav.detection.checks`). Input images are detector images after the log transform, bone
and metal bright; :func:`~fluoronav.detection.image_io.load_image` converts other files to that form.
docs/detector.md ("From image to detection") describes each step.
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import numpy as np
import torch

from fluoronav.detection.centerline import extract_centerline
from fluoronav.detection.checks import EdgeCheck, Finished, FreeEndCheck, ShaftCheck
from fluoronav.detection.config import DetectorConfig
from fluoronav.detection.decoder import component_at, truncated_landmarks
from fluoronav.detection.image_io import IMAGE_SUFFIXES, check_image, load_image
from fluoronav.detection.localize import CoarseStage, FineResult, FineStage
from fluoronav.detection.model import DetectorNet, load_net, shipped_model_path
from fluoronav.detection.patch_stages import EndsStage, RefineStage, TubeStage
from fluoronav.detection.result import (
    ASSUMED_SPACING_MM,
    OFF_MASK_MM,
    Detection,
    detection_to_dict,
    write_detection,
)
from fluoronav.detection.runtime import Networks

logger = logging.getLogger(__name__)

__all__ = [
    "ASSUMED_SPACING_MM",
    "IMAGE_SUFFIXES",
    "OFF_MASK_MM",
    "Detection",
    "Detector",
    "detection_to_dict",
    "load_image",
    "load_net",
    "shipped_model_path",
    "truncated_landmarks",
    "write_detection",
]


class Detector:
    """The CM detector: a model's declared stages on one torch device.

    Args:
        net: the model's networks (:class:`~fluoronav.detection.model.DetectorNet`, its ``config``
            the declared stages); they stay as they are (the detector runs a prepared copy).
        device: ``cpu``, ``cuda`` or ``auto``.
        precision: ``float32`` (the default) runs every network in float32; ``bfloat16`` runs the
            model's ``bf16_stages`` in bfloat16 (autocast; the decoding stays in float32): faster on
            a CPU with native bfloat16 arithmetic, its logits ~0.05 off, which tips some ambiguous
            views the other way; ``auto`` is ``bfloat16`` on a CPU with native bfloat16
            (:func:`~fluoronav.detection.runtime.native_bf16`) and ``float32`` elsewhere. The chosen
            one is in :attr:`precision`.
        source: where the model came from (a path), for reports.

    Attributes:
        coarse, fine: the view stages; refine, tube, ends: the patch stages; free_end, shaft, edge:
            the checks (None for a stage the model does not list).
    """

    def __init__(
        self,
        net: DetectorNet,
        *,
        device: str | torch.device = "auto",
        precision: str = "float32",
        source: str = "<memory>",
    ) -> None:
        self.config: DetectorConfig = net.config
        self.source = source
        self.networks = Networks(net, device=device, precision=precision)
        self.device, self.precision = self.networks.device, self.networks.precision
        cfg, spacing = self.config, self.config.assumed_spacing_mm
        nets = self.networks
        self.coarse = CoarseStage(cfg.coarse, nets)
        self.fine = FineStage(
            cfg.fine, nets, min_confidence=cfg.accept.min_confidence, assumed_spacing_mm=spacing
        )
        self.refine = (
            None if cfg.refine is None else RefineStage(cfg.refine, nets, assumed_spacing_mm=spacing)
        )
        self.tube = None if cfg.tube is None else TubeStage(cfg.tube, nets, assumed_spacing_mm=spacing)
        self.ends = None if cfg.ends is None else EndsStage(cfg.ends, nets, assumed_spacing_mm=spacing)
        self.free_end = None if cfg.free_end is None else FreeEndCheck(cfg.free_end, self.fine)
        self.shaft = (
            None if cfg.shaft is None else ShaftCheck(cfg.shaft, nets, self.fine, assumed_spacing_mm=spacing)
        )
        self.edge = None if cfg.edge is None else EdgeCheck(cfg.edge)

    @property
    def net(self) -> DetectorNet:
        """The networks the detector runs (prepared for inference)."""
        return self.networks.net

    @classmethod
    def load(
        cls,
        path: str | Path | None = None,
        device: str | torch.device = "auto",
        *,
        precision: str = "float32",
    ) -> Detector:
        """Load a model file written by ``fluoronav train`` (None: the shipped weights);
        ``precision``: see :class:`Detector`."""
        net = load_net(path)
        source = shipped_model_path() if path is None else Path(path)
        return cls(net, device=device, precision=precision, source=str(source))

    def detect(self, image: np.ndarray, *, pixel_spacing_mm: float | None = None) -> Detection:
        """Detect the CM in a (rows, cols) log image (bright = attenuating).

        Returns a :class:`~fluoronav.detection.result.Detection` in the input's pixels. ``found`` is
        False when the coarse mask is smaller than ``coarse.decoder.min_mask_px`` (a weak coarse
        mask, from ``weak_mask_px``, needs ``accept.weak_min_confidence`` of both fine landmarks), a
        fine landmark confidence is below ``accept.min_confidence``, the fine mask covers less than
        ``accept.min_mask_mm2`` at the detector, or the final mask's boundary lies on no edge of
        the image (the ``edge`` check). ``pixel_spacing_mm`` (mm per input pixel at the detector),
        where given, lets an image smaller than ``coarse.sampler.min_field_mm`` be seen by the
        coarse stage at the scale of a whole field; such a detection needs
        ``accept.padded_min_confidence``.
        """
        img = check_image(image, "image")
        cfg, acc = self.config, self.config.accept
        shape = img.shape
        empty = Detection(False, None, np.zeros(2), np.zeros(shape, bool), None, pixel_spacing_mm)
        cv, c_logit, c_pts, c_conf = self.coarse(img, pixel_spacing_mm=pixel_spacing_mm)
        padded = cv.side > max(shape)
        c_dec = cfg.coarse.decoder
        c_mask = c_logit > c_dec.threshold_logit
        c_area = int(c_mask.sum())
        weak = c_area < c_dec.min_mask_px
        if c_area < (c_dec.weak_mask_px or c_dec.min_mask_px):
            return empty
        # false alarms on CM-free images mostly start as small coarse masks: those need surer landmarks
        need = max(acc.weak_min_confidence, acc.min_confidence) if weak else acc.min_confidence
        if padded:
            need = max(need, acc.padded_min_confidence)
        spacing_mm = pixel_spacing_mm or cfg.assumed_spacing_mm

        def accepted(r: FineResult) -> bool:
            area_mm2 = float(r.mask.sum()) * spacing_mm**2
            return bool(r.mask.any()) and float(r.confidence.min()) >= need and area_mm2 >= acc.min_mask_mm2

        confident = c_conf >= acc.min_confidence
        both = bool(confident.all())
        first_mask = component_at(c_mask, cv.from_input(c_pts[confident]))
        res = self.fine(img, self.fine.roi(cv, first_mask, c_pts[confident]))
        hyp = cfg.fine.hypotheses
        if (hyp.coarse_split and both) or hyp.coarse_other_min_px > 0:
            res = self.fine.hypotheses(
                img, cv, c_mask, c_pts, res, accept=accepted, first_mask=first_mask, both=both
            )
        # the second look takes only hypotheses that are a detection; where the first result is none,
        # it is looked at again only with wide_unfound
        if accepted(res) or (hyp.wide_unfound and res.mask.any()):
            res = self.fine.second_look(img, res, pixel_spacing_mm=pixel_spacing_mm, accept=accepted)
        if not accepted(res):
            return Detection(False, None, res.confidence.astype(np.float64), res.mask, None, pixel_spacing_mm)
        f_conf = res.confidence
        finish = functools.partial(self.finish, img, res.mask, pixel_spacing_mm=pixel_spacing_mm)
        final = finish(res.landmarks_px)
        for check in (self.free_end, self.shaft):
            if check is not None:
                final = check(img, res, final, finish, pixel_spacing_mm=pixel_spacing_mm)
        if self.edge is not None and not self.edge(
            img, final.mask, confidence=float(f_conf.min()), spacing_mm=spacing_mm
        ):
            return Detection(False, None, f_conf.astype(np.float64), final.mask, None, pixel_spacing_mm)
        return Detection(
            True,
            final.landmarks_px,
            f_conf.astype(np.float64),
            final.mask,
            final.centerline_px,
            pixel_spacing_mm,
        )

    def finish(
        self,
        image: np.ndarray,
        fine_mask: np.ndarray,
        fine_pts: np.ndarray,
        *,
        pixel_spacing_mm: float | None = None,
    ) -> Finished:
        """A detection's last steps from its fine landmarks (2, 2) input px and fine mask (rows, cols)
        bool: the landmarks refined (``refine``), the centreline of the fine mask between them (the
        patch-mask stages move its edges by a pixel or less), and the mask redrawn along it
        (``tube``) and at its ends (``ends``). A stage the model does not list leaves its input."""
        pts = fine_pts
        if self.refine is not None:
            pts = self.refine(image, fine_pts, fine_mask, pixel_spacing_mm=pixel_spacing_mm)
        line = extract_centerline(fine_mask, pts[0], pts[1])
        mask = fine_mask
        if self.tube is not None:
            mask = self.tube(image, line, mask, pixel_spacing_mm=pixel_spacing_mm)
        if self.ends is not None:
            mask = self.ends(image, pts, mask, pixel_spacing_mm=pixel_spacing_mm)
        return Finished(pts, line, mask)
