"""The learned CM detector network: a coarse and a fine multi-task U-Net (MONAI ``UNet``, 2-D).

Each stage outputs 3 channels: a segmentation logit of the CM's notched region and two landmark
heatmaps (A = CM base origin, B = distal end of the last notch), trained jointly as in Gao et al. 2022
(Dice loss on the segmentation, L2 on the heatmaps).

- Coarse stage: the whole image, area-resampled (isotropically, padded to a square) to
  ``input_size``² (default 128), intensities normalised per image (1st/99th percentile → 0/1). It
  finds the CM and places the region of interest.
- Fine stage: a square region of interest around the coarse mask and landmarks (margin
  ``roi_margin_frac`` of its extent on each side), resampled from the *input* image to ``roi_size``²
  (default 128) and normalised the same way. Its mask is mapped back to the input grid and its
  heatmaps are decoded with a sub-pixel Gaussian fit, so the final precision is set by the ROI's pixel
  size (≈ the CM's extent / 128 × 1.5), not by the coarse grid.
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, dataclass, fields

import torch
from monai.networks.nets import UNet
from torch import nn
from torch.nn import functional as tnf
from torch.nn.utils import fuse_conv_bn_eval

#: version of the model file layout (state_dict + config)
MODEL_FORMAT_VERSION = 1

#: channels of the landmark refinement U-Net that ``train --stage refine`` adds to a model without one
DEFAULT_REFINE_CHANNELS = (16, 32, 64, 128)

#: channels of the mask-end U-Net that ``train --stage ends`` adds to a model without one
DEFAULT_ENDS_CHANNELS = (16, 32, 64, 128)

#: channels of the tube-mask U-Net that ``train --stage tube`` adds: a quarter of the mask-end one's
#: width (41 k parameters) did as well on validation (Dice 0.9613 against 0.9617) at a fifth of the cost
DEFAULT_TUBE_CHANNELS = (8, 16, 32, 64)

#: channels of the strip U-Net that ``train --stage strip`` adds to a model without one
DEFAULT_STRIP_CHANNELS = (16, 32, 64, 128)

#: the detector's networks, as ``DetectorNet`` attributes (``bf16_stages`` names some of them)
STAGES = ("coarse", "fine", "refine", "ends", "tube", "shaft", "strip")

#: the integer fields of the patch stages (refinement, mask ends)
_PATCH_NET_FIELDS = (
    "refine_channels",
    "refine_shape",
    "ends_channels",
    "ends_shape",
    "tube_channels",
    "shaft_channels",
    "strip_channels",
    "strip_shape",
)


@dataclass(frozen=True)
class DetectorConfig:
    """Architecture, working resolutions and decoding settings of the detector.

    Attributes:
        input_size: coarse working resolution (pixels, square).
        roi_size: fine-stage resolution of the region of interest (pixels, square).
        channels: feature channels per level of the coarse U-Net.
        roi_channels: feature channels per level of the fine U-Net.
        num_res_units: residual units per level (MONAI ``UNet``).
        sigma_px: standard deviation of the heatmap Gaussians, in working pixels of each stage.
        heatmap: ``"softmax"``: the heatmap channels are logits of a spatial softmax trained with
            cross-entropy against normalised Gaussians (decoded by
            :func:`~fluoronav.detection.heatmaps.decode_logit_heatmaps`); ``"gaussian"``: peak-1
            Gaussians regressed with L2 (the paper's loss; model files without this key).
        roi_margin_frac: ROI margin on each side as a fraction of the detected extent.
        roi_min_side_px: smallest ROI side in input pixels.
        fine_passes: fine-stage passes; each pass after the first uses a ROI fitted to the previous one.
        fine_max_passes: passes allowed in all when a pass's mask reaches the edge of its ROI (the CM
            goes on beyond it); each extra pass refits the ROI to the larger mask. Values below
            ``fine_passes`` (the default 0) add none.
        fine_tta: test-time augmentation of the fine stage (inference only): its logits averaged
            over this many transforms of the ROI from the dihedral group (1: none; 2: the mirror
            image; 4: + the 180° turn and its mirror; 8: all quarter turns and their mirrors). Model
            files with the older ``fine_flip_tta`` flag read it as 2 (True) or 1.
        fine_first_tta: the dihedral transforms of the fine passes before the last (they only place
            the last pass's ROI); None: ``fine_tta``.
        fine_sure_tta: the dihedral transforms of the last fine pass where the pass before it was
            sure of both landmarks (confidences ≥ ``fine_sure_confidence``); None: ``fine_tta``
            always. Averaging over more transforms matters for ambiguous views; a sure view pays
            for them in time only.
        fine_sure_confidence: the landmark confidence from which a pass counts as sure for
            ``fine_sure_tta``.
        fine_scales: ROI side multipliers of the last fine pass (inference only; ``(1.0,)``: the
            ROI alone). Each scaled ROI (same centre) is run in the same batch; the landmarks are
            the median over the scales, the mask logits their mean on the input grid. Different
            scales put the CM on different pixel grids and sizes, so their errors partly cancel.
        fine_min_separation_px: smallest distance between the fine stage's A and B peaks, in ROI
            pixels (0: none). Where both heatmaps peak on the same end of the CM, the one whose best
            peak outside that disk keeps the higher joint probability moves there
            (:func:`~fluoronav.detection.heatmaps.separation_exclusion`). The fitted ROI puts A and B
            ≥ 13 ROI pixels apart in every training image, also the CMs seen nearly end-on.
        fine_support_px: where a fine landmark map peaks outside the largest connected component
            of its view's mask grown by this many ROI pixels (on a blob apart from the CM), the
            landmark is taken at the map's best pixel inside it
            (:func:`~fluoronav.detection.detector.off_support_exclusion`); 0: off.
        fine_wide_factors: a second look after the fine stage (inference only; empty: none): the
            last pass's ROI scaled by each factor (same centre, one batch). The fine stage, shown a
            part of a CM only (the coarse stage found that part), can take it for the whole CM and
            stop its mask and a landmark inside the tube; a wider view shows the rest. Where a wider
            view puts a landmark ``fine_wide_min_shift_mm`` or more from the detection's, the fine
            stage is run again from a ROI fitted to that view's result (a second hypothesis), and
            the hypothesis whose mean landmark confidence is ``fine_wide_min_gain`` or more above
            the detection's replaces it (:meth:`~fluoronav.detection.detector.Detector.second_look`).
            Only a detection that is found is looked at again, and only by hypotheses that would be
            found themselves, so the second look adds no detection on an image without a CM.
        fine_wide_min_shift_mm: landmark shift (mm at the detector; images of unknown pixel spacing
            are taken to have ``refine_assumed_spacing_mm``) from which a wider view is a second
            hypothesis.
        fine_wide_min_gain: gain in the mean landmark confidence by which a second hypothesis
            replaces the detection.
        fine_wide_max_confidence: a detection whose mean landmark confidence is above this gets no
            second look (1: every detection does). The fine stage's confidence tops out near 0.86
            (a prediction as sharp as the training targets), so a detection above 0.86 minus
            ``fine_wide_min_gain`` cannot be replaced and the look would only cost time.
        fine_wide_unfound: True: a fine result that is no detection (a landmark confidence under the
            floor) gets the second look too, and is one if a wider view's hypothesis is (a CM the
            first ROI showed in part can be too unsure to count, and so missed); False: only
            detections get it.
        coarse_split: where the two confident coarse landmarks lie on different connected components
            of the coarse mask, the fine stage also runs from each component alone with its
            landmark (two more hypotheses; by default the ROI holds both components: one CM cut in
            two by a crossing bone), and a hypothesis whose mean landmark confidence is
            ``fine_wide_min_gain`` or more above the first one's replaces it. This mends a coarse
            landmark that went to a blob far from the CM, whose ROI then shows the CM too small
            to be found. Unlike the second look it can turn a non-detection into a detection (the
            hypothesis must be found itself). False: off.
        coarse_other_min_px: each connected component of the coarse mask of this many coarse pixels
            or more that the first fine ROI was not fitted to (the landmarks lie elsewhere) is a
            hypothesis too: the fine stage from it alone, judged as ``coarse_split``'s. The coarse
            stage can put both landmarks on a tube-like blob apart from the CM (the far end of its
            mounting shaft) while the CM is a second blob. 0: off.
        mask_threshold: probability above which a pixel is CM.
        mask_join_frac: the final mask is its largest connected component plus, when this is > 0,
            the components within max(3 px, this · |AB|) of the segment A–B (a tube's mask cut into
            pieces by noise or a crossing bone); 0: the largest component only.
        min_mask_px: smallest coarse mask area (coarse pixels) counted as a detection.
        min_confidence: smallest landmark confidence (heatmap peak) counted as a detection.
        min_mask_mm2: smallest final mask area at the detector (mm²) counted as a detection (0: off).
            A tube of diameter d projects to at least a disc of diameter d (magnification ≥ 1), so a
            smaller mask is not a whole CM (the paper's CM: π · 3² = 28.3 mm²). Images that do not
            give their pixel spacing are taken to have ``refine_assumed_spacing_mm``.
        weak_mask_px: with 0 < this < ``min_mask_px``, coarse masks of this many coarse pixels or
            more but fewer than ``min_mask_px`` (a small or faint CM, or a false alarm) go on to the
            fine stage too, and count as a detection only if both fine landmark confidences are at
            least ``weak_min_confidence``; 0: off (such masks are no detection).
        weak_min_confidence: the fine landmark confidence a weak coarse mask needs.
        low_pct, high_pct: percentiles mapped to 0 and 1 by the intensity normalisation.
        coarse_min_field_mm: the coarse view covers at least this field (mm at the detector) where
            the image's pixel spacing is known: a smaller image (a collimated field read out alone)
            is centred in a window that wide, its edge pixels repeated, so its CM has the size in
            coarse pixels that the whole fields of training gave it. 0: off (the image alone).
        padded_min_confidence: the fine landmark confidence both landmarks need where the coarse
            view was widened by ``coarse_min_field_mm`` (repeated edges can look like a tube).
        min_edge_ratio: the boundary-to-surroundings gradient ratio every detection's final mask
            needs (:func:`fluoronav.detection.evidence.mask_edge_ratio`: the mean image gradient on
            the mask's boundary over its median around the mask); 0: off. A CM's tube is bounded by
            a strong step; false alarms on CM-free images are blobs on bone whose boundary lies on
            no edge.
        unsure_below_confidence, unsure_min_edge_ratio: a detection whose smaller landmark
            confidence is below the first needs the second ratio instead, where it is larger (an
            unsure detection needs clearer evidence); 0: off.
        free_end_max_continuation: where landmark A has less tube than this around it outside the
            mask (:func:`fluoronav.detection.evidence.end_continuation`: 0 for a free end of a
            tube, about 1 where the shaft goes on), A is on the free end of a tube, not where the CM
            meets its shaft (the fine stage can take the far end of a short shaft stub for A); A is
            then read again from the last fine pass's heatmap away from that end, and that place is
            taken where it has more tube around it than this. 0: off.
        free_end_min_confidence: the fine confidence of A that the free-end check needs: an unsure
            A in a noisy view, its shaft pointing at the source, has little tube around it too.
        shaft_cut_min_mm: where the shaft stage (``shaft_channels``) leaves this much (mm at the
            detector) or more of the centreline's start out of the CM's mask, A is on the mounting
            shaft (the fine stage took a plain stretch of shaft for part of the CM); A is then read
            again where the shaft stage's CM begins. 0: off.
        shaft_cut_run_mm: the CM begins at the first stretch of the centreline of this length (mm at
            the detector) that lies wholly in the shaft stage's mask.
        shaft_min_cm_logit: the shaft stage judges only where it sees the notched CM clearly
            somewhere along the centreline: the mean logit of a patch's core (within 8 patch px of
            the axis, its band along the tube) of this or more in one patch at least. In heavy noise
            its logits stay near 0 all along and its cut would be a guess.
        bf16_stages: the networks (names from :data:`STAGES`) that run in bfloat16 where the
            detector is asked for it (``Detector(precision="bfloat16")``, or ``"auto"`` on a CPU with
            native bfloat16 arithmetic); the others, and every network by default, run in float32.
        refine_channels: feature channels per level of the landmark refinement U-Net
            (:mod:`fluoronav.detection.refine`); empty (the default): no refinement stage.
            ``fluoronav train --stage refine`` adds one of :data:`DEFAULT_REFINE_CHANNELS`.
        refine_shape: (rows, cols) of the tube-aligned refinement patches (across × along the tube).
        refine_step_mm: patch pixel size at the detector, mm (images of unknown pixel spacing are
            taken to have ``refine_assumed_spacing_mm``).
        refine_sigma_px: σ of the refinement heatmap targets, patch pixels.
        refine_prior_px: σ of the Gaussian prior around the fine stage's landmark at inference, patch
            pixels (0: none; the patch alone sometimes takes the tube's end for B or the base for A,
            a few mm off, which the fine stage's view of the whole CM rules out).
        refine_shifts_px: each landmark is read from patches centred this many patch pixels along
            the tube from it (one batch; the prior stays at the fine stage's landmark) and the mean
            of their estimates is taken; (0,): one patch.
        refine_tta: 2: the refinement logits are averaged with those of the patch mirrored about the
            tube's axis; 1: the patch alone.
        refine_assumed_spacing_mm: the pixel spacing taken for images that do not give theirs (the
            training images' 512² storage of the 1536 × 0.194 mm detector), by the refinement stage
            and ``min_mask_mm2``.
        ends_channels: feature channels per level of the mask-end U-Net
            (:mod:`fluoronav.detection.ends`); empty (the default): no such stage.
            ``fluoronav train --stage ends`` adds one of :data:`DEFAULT_ENDS_CHANNELS`.
        ends_shape: (rows, cols) of its tube-aligned patches (across × along the tube), centred on
            each refined landmark, at ``refine_step_mm`` per patch pixel.
        ends_inner_px: the mask-end stage decides the mask from this many patch pixels inside each
            landmark (towards the CM) outwards; the fine stage's mask stays elsewhere.
        tube_channels: feature channels per level of the tube-mask U-Net (patches of ``ends_shape``
            along the centreline; :mod:`fluoronav.detection.ends`); empty (the default): no such
            stage. ``fluoronav train --stage tube`` adds one of :data:`DEFAULT_TUBE_CHANNELS`.
        shaft_channels: feature channels per level of the shaft U-Net: a tube-mask network (same
            patches and bands) trained with patches on the mounting shaft too, labelled not-CM
            (``fluoronav train --stage shaft --tube-shaft-prob P``, started from the tube-mask
            stage's weights); it only decides where the CM begins along the centreline
            (``shaft_cut_min_mm``), the tube-mask stage draws the mask. Empty: none.
        ends_tta: 2: the patch-mask stages (mask ends, tube mask) average their logits with those of
            the patch mirrored about the tube's axis; 1: the patch alone.
        tube_spacing_px: patch pixels of arc length between the tube-mask patches' centres.
        tube_band_px: each tube-mask patch decides the mask within this many patch pixels of its
            centre along the tube (where bands overlap, their mean logit); the mask-end stage then
            redraws the ends.
        strip_channels: feature channels per level of the strip U-Net
            (:mod:`fluoronav.detection.strip`; ``fluoronav train --stage strip`` adds one of
            :data:`DEFAULT_STRIP_CHANNELS`): per position along a path, where A lies on it, or that
            it lies nowhere on it. Empty (the default): none.
        strip_shape: (rows, cols) of its strips (across × along the path, from the path's start),
            at ``refine_step_mm`` per strip pixel.
        strip_sigma_px: σ of its training targets along the strip, strip pixels.
        apex_max_confidence: the strip stage judges detections whose A has a fine confidence under
            this (0: off): where the final mask is a V (its farthest pixel from the segment A–B
            more than ``apex_min_offset_mm`` from it, mm at the detector), the fine stage may have
            taken the far end of a foreshortened shaft for A, and the V's apex
            (:func:`~fluoronav.detection.strip.v_apex`) is A.
        apex_min_offset_mm: see ``apex_max_confidence``.
        apex_window_mm: the strip stage's probabilities are summed over ± this (mm at the
            detector) around a place on a path.
        apex_start_max_prob: A moves to the apex only where the strip stage gives the detection's
            own centreline less than this probability of A at its start ...
        apex_path_start_max_prob: ... and the path A → apex → B less than this of A at its start
            ...
        apex_min_prob: ... and more than this of A at the apex (and more than at its start).
    """

    input_size: int = 128
    roi_size: int = 128
    channels: tuple[int, ...] = (16, 32, 64, 128, 256)
    roi_channels: tuple[int, ...] = (16, 32, 64, 128, 256)
    num_res_units: int = 0
    sigma_px: float = 2.0
    heatmap: str = "softmax"
    roi_margin_frac: float = 0.2
    roi_min_side_px: float = 24.0
    fine_passes: int = 2
    fine_max_passes: int = 0
    fine_tta: int = 8
    fine_first_tta: int | None = None
    fine_sure_tta: int | None = None
    fine_sure_confidence: float = 0.6
    fine_scales: tuple[float, ...] = (1.0,)
    fine_min_separation_px: float = 0.0
    fine_support_px: float = 0.0
    fine_wide_factors: tuple[float, ...] = ()
    fine_wide_min_shift_mm: float = 5.0
    fine_wide_min_gain: float = 0.15
    fine_wide_max_confidence: float = 1.0
    fine_wide_unfound: bool = False
    coarse_split: bool = False
    coarse_other_min_px: int = 0
    mask_threshold: float = 0.5
    mask_join_frac: float = 0.0
    min_mask_px: int = 6
    min_confidence: float = 0.3
    min_mask_mm2: float = 0.0
    weak_mask_px: int = 0
    weak_min_confidence: float = 0.15
    low_pct: float = 1.0
    high_pct: float = 99.0
    coarse_min_field_mm: float = 0.0
    padded_min_confidence: float = 0.0
    min_edge_ratio: float = 0.0
    unsure_below_confidence: float = 0.0
    unsure_min_edge_ratio: float = 0.0
    free_end_max_continuation: float = 0.0
    free_end_min_confidence: float = 0.0
    shaft_cut_min_mm: float = 0.0
    shaft_cut_run_mm: float = 3.0
    shaft_min_cm_logit: float = 0.0
    bf16_stages: tuple[str, ...] = ()
    refine_channels: tuple[int, ...] = ()
    refine_shape: tuple[int, int] = (48, 80)
    refine_step_mm: float = 0.291
    refine_sigma_px: float = 1.5
    refine_prior_px: float = 3.0
    refine_shifts_px: tuple[float, ...] = (0.0,)
    refine_tta: int = 2
    refine_assumed_spacing_mm: float = 0.582
    ends_channels: tuple[int, ...] = ()
    ends_shape: tuple[int, int] = (80, 64)
    ends_inner_px: float = 8.0
    ends_tta: int = 2
    tube_channels: tuple[int, ...] = ()
    shaft_channels: tuple[int, ...] = ()
    tube_spacing_px: float = 16.0
    tube_band_px: float = 16.0
    strip_channels: tuple[int, ...] = ()
    strip_shape: tuple[int, int] = (64, 384)
    strip_sigma_px: float = 2.0
    apex_max_confidence: float = 0.0
    apex_min_offset_mm: float = 8.0
    apex_window_mm: float = 2.0
    apex_start_max_prob: float = 0.3
    apex_path_start_max_prob: float = 1.0
    apex_min_prob: float = 0.3

    def __post_init__(self) -> None:
        if not set(self.bf16_stages) <= set(STAGES):
            raise ValueError(f"bf16_stages must be names from {STAGES}, got {self.bf16_stages}")
        for name in ("fine_tta", "fine_first_tta", "fine_sure_tta"):
            value = getattr(self, name)
            if value not in (1, 2, 4, 8) and not (name != "fine_tta" and value is None):
                raise ValueError(f"{name} must be 1, 2, 4 or 8, got {value}")
        if not self.fine_sure_confidence >= 0.0:
            raise ValueError(f"fine_sure_confidence must be 0 or more, got {self.fine_sure_confidence}")
        if self.fine_max_passes < 0:
            raise ValueError(f"fine_max_passes must be 0 or more, got {self.fine_max_passes}")
        if not self.fine_scales or not all(0.25 <= float(f) <= 4.0 for f in self.fine_scales):
            raise ValueError(f"fine_scales must be 1 or more factors in [0.25, 4], got {self.fine_scales}")
        if not all(1.0 < float(f) <= 4.0 for f in self.fine_wide_factors):
            raise ValueError(f"fine_wide_factors must be factors in (1, 4], got {self.fine_wide_factors}")
        if not (self.fine_wide_min_shift_mm >= 0.0 and 0.0 <= self.fine_wide_min_gain <= 1.0):
            raise ValueError(
                "fine_wide_min_shift_mm must be 0 or more and fine_wide_min_gain in [0, 1], got "
                f"{self.fine_wide_min_shift_mm} and {self.fine_wide_min_gain}"
            )
        if not 0.0 <= self.fine_wide_max_confidence <= 1.0:
            raise ValueError(
                f"fine_wide_max_confidence must be in [0, 1], got {self.fine_wide_max_confidence}"
            )
        if not 0.0 <= self.mask_join_frac <= 1.0:
            raise ValueError(f"mask_join_frac must be in [0, 1], got {self.mask_join_frac}")
        if self.coarse_other_min_px < 0:
            raise ValueError(f"coarse_other_min_px must be 0 or more, got {self.coarse_other_min_px}")
        if not 0 <= self.weak_mask_px <= self.min_mask_px:
            raise ValueError(f"weak_mask_px must be in [0, min_mask_px], got {self.weak_mask_px}")
        if not 0.0 <= self.weak_min_confidence <= 1.0:
            raise ValueError(f"weak_min_confidence must be in [0, 1], got {self.weak_min_confidence}")
        if not self.min_mask_mm2 >= 0.0:
            raise ValueError(f"min_mask_mm2 must be 0 or more, got {self.min_mask_mm2}")
        if not self.coarse_min_field_mm >= 0.0:
            raise ValueError(f"coarse_min_field_mm must be 0 or more, got {self.coarse_min_field_mm}")
        if not 0.0 <= self.padded_min_confidence <= 1.0:
            raise ValueError(f"padded_min_confidence must be in [0, 1], got {self.padded_min_confidence}")
        if not (self.min_edge_ratio >= 0.0 and self.unsure_min_edge_ratio >= 0.0):
            raise ValueError(
                "min_edge_ratio and unsure_min_edge_ratio must be 0 or more, got "
                f"{self.min_edge_ratio} and {self.unsure_min_edge_ratio}"
            )
        if not 0.0 <= self.unsure_below_confidence <= 1.0:
            raise ValueError(f"unsure_below_confidence must be in [0, 1], got {self.unsure_below_confidence}")
        if not self.refine_shifts_px or not all(abs(float(d)) <= 16.0 for d in self.refine_shifts_px):
            raise ValueError(
                f"refine_shifts_px must be 1 or more shifts in [-16, 16], got {self.refine_shifts_px}"
            )
        if not 0.0 <= self.free_end_max_continuation <= 1.0:
            raise ValueError(
                f"free_end_max_continuation must be in [0, 1], got {self.free_end_max_continuation}"
            )
        if not 0.0 <= self.free_end_min_confidence <= 1.0:
            raise ValueError(f"free_end_min_confidence must be in [0, 1], got {self.free_end_min_confidence}")
        if self.shaft_cut_min_mm < 0.0 or self.shaft_cut_run_mm <= 0.0:
            raise ValueError(
                "shaft_cut_min_mm must be ≥ 0 and shaft_cut_run_mm > 0, got "
                f"{self.shaft_cut_min_mm} and {self.shaft_cut_run_mm}"
            )
        if self.refine_tta not in (1, 2):
            raise ValueError(f"refine_tta must be 1 or 2, got {self.refine_tta}")
        if self.refine_channels:
            div = 2 ** (len(self.refine_channels) - 1)
            if len(self.refine_shape) != 2 or any(int(n) <= 0 or int(n) % div for n in self.refine_shape):
                raise ValueError(f"refine_shape must be 2 sizes divisible by {div}, got {self.refine_shape}")
        for name in ("ends_channels", "tube_channels"):
            chans = getattr(self, name)
            div = 2 ** (len(chans) - 1)
            if chans and (
                len(self.ends_shape) != 2 or any(int(n) <= 0 or int(n) % div for n in self.ends_shape)
            ):
                raise ValueError(f"ends_shape must be 2 sizes divisible by {div}, got {self.ends_shape}")
        if self.strip_channels:
            div = 2 ** (len(self.strip_channels) - 1)
            if len(self.strip_shape) != 2 or any(int(n) <= 0 or int(n) % div for n in self.strip_shape):
                raise ValueError(f"strip_shape must be 2 sizes divisible by {div}, got {self.strip_shape}")
        if not self.strip_sigma_px > 0.0:
            raise ValueError(f"strip_sigma_px must be > 0, got {self.strip_sigma_px}")
        for name in (
            "apex_max_confidence",
            "apex_start_max_prob",
            "apex_path_start_max_prob",
            "apex_min_prob",
        ):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if not (self.apex_min_offset_mm >= 0.0 and self.apex_window_mm > 0.0):
            raise ValueError(
                "apex_min_offset_mm must be ≥ 0 and apex_window_mm > 0, got "
                f"{self.apex_min_offset_mm} and {self.apex_window_mm}"
            )
        if self.ends_tta not in (1, 2):
            raise ValueError(f"ends_tta must be 1 or 2, got {self.ends_tta}")
        if not (self.tube_spacing_px > 0 and 0 < self.tube_band_px <= self.ends_shape[1] / 2):
            raise ValueError(
                "tube_spacing_px must be > 0 and tube_band_px in (0, ends_shape[1] / 2], got "
                f"{self.tube_spacing_px} and {self.tube_band_px}"
            )
        if not 0.0 <= self.ends_inner_px <= self.ends_shape[1] / 2:
            raise ValueError(f"ends_inner_px must be in [0, ends_shape[1] / 2], got {self.ends_inner_px}")
        if not (self.refine_step_mm > 0 and self.refine_sigma_px > 0 and self.refine_assumed_spacing_mm > 0):
            raise ValueError("refine_step_mm, refine_sigma_px and refine_assumed_spacing_mm must be > 0")
        if not self.refine_prior_px >= 0.0:
            raise ValueError(f"refine_prior_px must be 0 or more, got {self.refine_prior_px}")
        if not 0.0 <= self.fine_support_px < self.roi_size:
            raise ValueError(f"fine_support_px must be in [0, roi_size), got {self.fine_support_px}")
        if not 0.0 <= self.fine_min_separation_px < self.roi_size:
            raise ValueError(
                f"fine_min_separation_px must be in [0, roi_size), got {self.fine_min_separation_px}"
            )

    def refine_step_px(self, pixel_spacing_mm: float | None) -> float:
        """Input pixels per refinement patch pixel for an image of this pixel spacing (mm;
        None: ``refine_assumed_spacing_mm``)."""
        return self.refine_step_mm / (pixel_spacing_mm or self.refine_assumed_spacing_mm)

    @property
    def mask_threshold_logit(self) -> float:
        """``mask_threshold`` as a logit (the networks' segmentation output)."""
        return float(math.log(self.mask_threshold / (1.0 - self.mask_threshold)))

    def needed_edge_ratio(self, smaller_confidence: float) -> float:
        """The edge ratio a detection with this smaller landmark confidence needs (0: no check)."""
        if smaller_confidence < self.unsure_below_confidence:
            return max(self.min_edge_ratio, self.unsure_min_edge_ratio)
        return self.min_edge_ratio

    def to_dict(self) -> dict:
        d = asdict(self)
        d["channels"], d["roi_channels"] = list(self.channels), list(self.roi_channels)
        d["fine_scales"], d["fine_wide_factors"] = list(self.fine_scales), list(self.fine_wide_factors)
        d["refine_channels"], d["refine_shape"] = list(self.refine_channels), list(self.refine_shape)
        d["refine_shifts_px"] = list(self.refine_shifts_px)
        d["ends_channels"], d["ends_shape"] = list(self.ends_channels), list(self.ends_shape)
        d["tube_channels"] = list(self.tube_channels)
        d["strip_channels"], d["strip_shape"] = list(self.strip_channels), list(self.strip_shape)
        d["bf16_stages"] = list(self.bf16_stages)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> DetectorConfig:
        known = {f.name for f in fields(cls)}
        kw = {k: v for k, v in d.items() if k in known}
        kw.setdefault("heatmap", "gaussian")  # files written before the softmax heatmaps
        if "fine_tta" not in kw and "fine_flip_tta" in d:  # files before the dihedral TTA
            kw["fine_tta"] = 2 if d["fine_flip_tta"] else 1
        for key in ("channels", "roi_channels", *_PATCH_NET_FIELDS):
            if key in kw:
                kw[key] = tuple(int(c) for c in kw[key])
        for key in ("fine_scales", "fine_wide_factors", "refine_shifts_px"):
            if key in kw:
                kw[key] = tuple(float(f) for f in kw[key])
        if "bf16_stages" in kw:
            kw["bf16_stages"] = tuple(str(n) for n in kw["bf16_stages"])
        return cls(**kw)


def build_unet(
    channels: tuple[int, ...],
    *,
    num_res_units: int = 0,
    out_channels: int = 3,
) -> nn.Module:
    """2-D MONAI U-Net, 1 input channel → ``out_channels`` (seg logit, heatmap A, heatmap B).

    Input (B, 1, H, W) with H, W divisible by 2^(len(channels) − 1); output (B, out_channels, H, W).
    """
    return UNet(
        spatial_dims=2,
        in_channels=1,
        out_channels=out_channels,
        channels=tuple(channels),
        strides=(2,) * (len(channels) - 1),
        num_res_units=num_res_units,
        norm="batch",
    )


class DetectorNet(nn.Module):
    """Coarse + fine multi-task U-Nets, each (B, 1, S, S) → (B, 3, S, S), and, where
    ``refine_channels`` is set, the landmark refinement U-Net (B, 1, rows, cols) → (B, 2, rows, cols)
    (heatmap logits of A and B; each patch uses the channel of its landmark), and where
    ``ends_channels`` is set, the mask-end U-Net (B, 1, rows, cols) → (B, 1, rows, cols) (seg logit),
    and likewise the tube-mask U-Net where ``tube_channels`` is set and the shaft U-Net where
    ``shaft_channels`` is, and where ``strip_channels`` is, the strip U-Net (B, 1, rows, cols) →
    (B, 2, rows, cols) (:mod:`fluoronav.detection.strip`)."""

    def __init__(self, config: DetectorConfig | None = None) -> None:
        super().__init__()
        self.config = config or DetectorConfig()
        c = self.config
        self.coarse = build_unet(c.channels, num_res_units=c.num_res_units)
        self.fine = build_unet(c.roi_channels, num_res_units=c.num_res_units)
        for stage in (self.coarse, self.fine):
            _init_head(stage)
        self.refine: nn.Module | None = None
        if c.refine_channels:
            self.refine = build_unet(c.refine_channels, num_res_units=c.num_res_units, out_channels=2)
        self.ends: nn.Module | None = None
        if c.ends_channels:
            self.ends = build_unet(c.ends_channels, num_res_units=c.num_res_units, out_channels=1)
        self.tube: nn.Module | None = None
        if c.tube_channels:
            self.tube = build_unet(c.tube_channels, num_res_units=c.num_res_units, out_channels=1)
        self.shaft: nn.Module | None = None
        if c.shaft_channels:
            self.shaft = build_unet(c.shaft_channels, num_res_units=c.num_res_units, out_channels=1)
        self.strip: nn.Module | None = None
        if c.strip_channels:
            self.strip = build_unet(c.strip_channels, num_res_units=c.num_res_units, out_channels=2)

    def forward(self, coarse: torch.Tensor, fine: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 1, input_size²), (B, 1, roi_size²) → their (B, 3, ·, ·) outputs."""
        return self.coarse(coarse), self.fine(fine)


def fold_batch_norm(module: nn.Module) -> nn.Module:
    """Fold each batch norm that directly follows a convolution (MONAI ``Convolution`` blocks,
    ``conv`` then ``adn`` with the norm first) into that convolution's weights and bias, in place;
    returns ``module``. For inference only: ``module`` must be in eval mode (running statistics).

    The folded network computes the same function to float32 rounding (logits within ~1e-5 of
    the unfolded ones) without a separate pass over the activations per batch norm (a detection
    ~4 % faster on this CPU). Its ``state_dict`` has no batch-norm entries, so it cannot be
    trained on or saved as a model file.
    """
    if module.training:
        raise ValueError("fold_batch_norm needs a module in eval mode")
    for block in list(module.modules()):
        conv, adn = getattr(block, "conv", None), getattr(block, "adn", None)
        if not isinstance(conv, (nn.Conv2d, nn.ConvTranspose2d)) or not isinstance(adn, nn.Sequential):
            continue
        norm = adn._modules.get("N")
        if not isinstance(norm, nn.BatchNorm2d) or next(iter(adn._modules)) != "N":
            continue  # no norm, or an activation before it
        block.conv = fuse_conv_bn_eval(conv, norm, transpose=isinstance(conv, nn.ConvTranspose2d))
        adn.N = nn.Identity()
    return module


class PackedConvolution(nn.Module):
    """A MONAI ``Convolution`` block after :func:`fold_batch_norm` (a convolution or transposed
    convolution, then a one-slope PReLU or nothing) as one oneDNN call on weights reordered once.

    For CPU inference in float32: eager PyTorch hands oneDNN plain weights on every call and runs
    the activation as a separate pass; here neither (a detection ~4 % faster on this CPU). The
    result is bit-identical to the eager block for batches of two or more (to float32 rounding for
    one). Under autograd, autocast, another device or dtype the block runs eagerly, with the same
    function. The reordered weights are made on the first call and again when the weights change.
    """

    def __init__(self, conv: nn.Conv2d | nn.ConvTranspose2d, slope: float | None) -> None:
        super().__init__()
        self.conv = conv
        self.slope = slope
        self._packed: tuple[int, torch.Tensor] | None = None  # (weight version, reordered weight)
        # padding, output padding (transposed only), stride, dilation, as oneDNN's calls take them
        self._pad, self._stride, self._dil = list(conv.padding), list(conv.stride), list(conv.dilation)
        self._out_pad = list(conv.output_padding) if isinstance(conv, nn.ConvTranspose2d) else []

    def __deepcopy__(self, memo: dict) -> PackedConvolution:
        # the reordered weight is an opaque oneDNN tensor: a copy makes its own
        return PackedConvolution(copy.deepcopy(self.conv, memo), self.slope)

    def _eager(self, x: torch.Tensor) -> torch.Tensor:
        y = self.conv(x)
        return y if self.slope is None else tnf.leaky_relu(y, self.slope)

    def _weight(self) -> torch.Tensor:
        c, w = self.conv, self.conv.weight.detach()
        if self._packed is None or self._packed[0] != w._version:
            pad, stride, dil = self._pad, self._stride, self._dil
            if isinstance(c, nn.ConvTranspose2d):
                packed = torch.ops.mkldnn._reorder_convolution_transpose_weight(
                    w, pad, self._out_pad, stride, dil, c.groups, None
                )
            else:
                packed = torch._C._nn.mkldnn_reorder_conv2d_weight(w.to_mkldnn(), pad, stride, dil, c.groups)
            self._packed = (w._version, packed)
        return self._packed[1]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        c = self.conv
        if (
            torch.is_grad_enabled()
            or x.device.type != "cpu"
            or x.dtype != torch.float32
            or c.weight.dtype != torch.float32
            or torch.is_autocast_enabled("cpu")
        ):
            return self._eager(x)
        attr, scalars = ("none", []) if self.slope is None else ("leaky_relu", [self.slope])
        pad, stride, dil = self._pad, self._stride, self._dil
        if isinstance(c, nn.ConvTranspose2d):
            return torch.ops.mkldnn._convolution_transpose_pointwise(
                x, self._weight(), c.bias, pad, self._out_pad, stride, dil, c.groups, attr, scalars, ""
            )
        return torch.ops.mkldnn._convolution_pointwise(
            x, self._weight(), c.bias, pad, stride, dil, c.groups, attr, scalars, ""
        )


def _packable(block: nn.Module) -> tuple[bool, float | None]:
    """Whether a MONAI ``Convolution`` block is a plain 2-D convolution followed by nothing but
    identities, eval-mode dropout and at most a one-slope PReLU (last), and that slope."""
    conv = getattr(block, "conv", None)
    if not isinstance(block, nn.Sequential) or not isinstance(conv, (nn.Conv2d, nn.ConvTranspose2d)):
        return False, None
    if conv.padding_mode != "zeros" or isinstance(conv.padding, str) or conv.bias is None:
        return False, None
    names = list(block._modules)
    if names not in (["conv"], ["conv", "adn"]):
        return False, None
    slope: float | None = None
    if names == ["conv", "adn"]:
        parts = list(block.adn._modules.values())  # type: ignore[union-attr]
        for i, m in enumerate(parts):
            if isinstance(m, nn.PReLU) and m.weight.numel() == 1 and i == len(parts) - 1:
                slope = float(m.weight.detach())
            elif not isinstance(m, (nn.Identity, nn.Dropout)) or (isinstance(m, nn.Dropout) and m.training):
                return False, None
    return True, slope


def pack_for_cpu(module: nn.Module) -> nn.Module:
    """Replace, in place, each MONAI ``Convolution`` block of ``module`` that :func:`fold_batch_norm`
    left as a convolution and a one-slope PReLU (or a convolution alone) with a
    :class:`PackedConvolution`; returns ``module``. A no-op where this PyTorch has no oneDNN.
    Inference only (eval mode); see :class:`PackedConvolution`."""
    if not (torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_convolution_pointwise")):
        return module
    for parent in list(module.modules()):
        for name, child in list(parent.named_children()):
            ok, slope = _packable(child)
            if ok:
                setattr(parent, name, PackedConvolution(child.conv, slope))  # type: ignore[arg-type]
    return module


def _init_head(stage: nn.Module) -> None:
    """Start near the answer for an empty image: small heatmaps and a CM prior of ~2 % per pixel.

    Random output layers start with heatmap errors hundreds of times the target energy and a 50 %
    CM prior; the first epochs would go to unlearning that.
    """
    last = [m for m in stage.modules() if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d))][-1]
    with torch.no_grad():
        last.weight.mul_(0.1)
        if last.bias is not None:
            last.bias.zero_()
            last.bias[0] = -4.0


def count_parameters(module: nn.Module, *, trainable_only: bool = True) -> int:
    """Number of parameters: those that train (``requires_grad``), or all of them."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable_only)
