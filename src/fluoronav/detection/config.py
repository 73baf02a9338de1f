"""The detector's declared configuration: the stages a model runs, in order, and each stage's settings.

A model lists its stages in ``stages`` (a subsequence of :data:`STAGE_ORDER`; ``coarse`` and ``fine``
always) and holds one frozen, validated config object per listed stage, grouped as its network, its
sampler (the views or patches it sees) and its decoder (the rules that turn its outputs into
landmarks and masks): ``coarse`` (the whole image; places the region of interest), ``fine`` (the
landmarks and the mask in ROIs around the CM), ``refine``, ``tube`` and ``ends`` (tube-aligned
patches: the landmarks, the mask, its ends), ``free_end`` and ``shaft`` (landmark A read again),
``edge`` (an image edge along the mask's boundary). ``accept`` holds the rules a detection must pass
after the fine stage. docs/detector.md ("From image to detection") describes each stage.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = [
    "ASSUMED_SPACING_MM",
    "NETWORK_STAGES",
    "STAGE_ORDER",
    "AcceptConfig",
    "CoarseConfig",
    "CoarseDecoder",
    "DetectorConfig",
    "EdgeConfig",
    "EndsConfig",
    "FineConfig",
    "FineDecoder",
    "FineHypotheses",
    "FinePasses",
    "FreeEndConfig",
    "NetworkConfig",
    "PatchSampler",
    "RefineConfig",
    "RefineDecoder",
    "RefineSampler",
    "RoiSampler",
    "ShaftConfig",
    "TubeConfig",
    "TubeSampler",
    "WholeViewSampler",
]

#: the stages a detector can run, in the order it runs them
STAGE_ORDER = ("coarse", "fine", "refine", "tube", "ends", "free_end", "shaft", "edge")

#: the stages with a network, in the order :class:`~fluoronav.detection.model.DetectorNet` builds them
NETWORK_STAGES = ("coarse", "fine", "refine", "ends", "tube", "shaft")

#: pixel spacing (mm at the detector) taken for images that do not give theirs: the training images'
#: (the 1536² detector of 0.194 mm pixels stored at 512²)
ASSUMED_SPACING_MM = 0.582

#: the numbers of dihedral transforms a test-time augmentation can average over
Tta = Literal[1, 2, 4, 8]


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


class NetworkConfig(_Frozen):
    """A stage's U-Net (MONAI ``UNet``, 2-D, batch norms): ``channels`` feature channels per level
    (strides of 2 between levels) and ``num_res_units`` residual units per level."""

    channels: tuple[int, ...]
    num_res_units: int = Field(0, ge=0)

    @property
    def divisor(self) -> int:
        """What the input's sides must be divisible by."""
        return 2 ** (len(self.channels) - 1)


def _unet(*channels: int) -> NetworkConfig:
    return NetworkConfig(channels=channels)


class WholeViewSampler(_Frozen):
    """The coarse stage's view: the whole image, area-resampled (isotropically, padded to a square)
    to ``size``², intensities normalised per view (``low_pct`` / ``high_pct`` percentiles → 0 / 1).

    ``min_field_mm``: the view covers at least this field (mm at the detector) where the image's
    pixel spacing is known: a smaller image (a collimated field read out alone) is centred in a
    window that wide, its edge pixels repeated, so its CM has the size in coarse pixels that the whole
    fields of training gave it (0: the image alone).
    """

    size: int = Field(128, gt=0)
    min_field_mm: float = Field(0.0, ge=0.0)
    low_pct: float = 1.0
    high_pct: float = 99.0


class CoarseDecoder(_Frozen):
    """How the coarse stage's outputs are read.

    Attributes:
        heatmap: ``"softmax"``: the heatmap channels are logits of a spatial softmax trained with
            cross-entropy against normalised Gaussians; ``"gaussian"``: peak-1 Gaussians regressed
            with L2 (the paper's loss).
        sigma_px: σ of the heatmap targets, view pixels.
        mask_threshold: probability above which a pixel is CM.
        min_mask_px: smallest coarse mask (coarse pixels) that goes on to the fine stage as a
            detection.
        weak_mask_px: with 0 < this < ``min_mask_px``, masks of this many coarse pixels or more go
            on too, as a weak detection (:attr:`AcceptConfig.weak_min_confidence`); 0: off.
    """

    heatmap: Literal["softmax", "gaussian"] = "softmax"
    sigma_px: float = Field(2.0, gt=0.0)
    mask_threshold: float = Field(0.5, gt=0.0, lt=1.0)
    min_mask_px: int = Field(6, ge=0)
    weak_mask_px: int = Field(0, ge=0)

    @model_validator(mode="after")
    def _check(self) -> CoarseDecoder:
        if self.weak_mask_px > self.min_mask_px:
            raise ValueError(f"weak_mask_px must be in [0, min_mask_px], got {self.weak_mask_px}")
        return self

    @property
    def threshold_logit(self) -> float:
        """``mask_threshold`` as a logit (the network's segmentation output)."""
        return _logit(self.mask_threshold)


class CoarseConfig(_Frozen):
    """The coarse stage: its network, view and decoder."""

    network: NetworkConfig = _unet(16, 32, 64, 128, 256)
    sampler: WholeViewSampler = WholeViewSampler()
    decoder: CoarseDecoder = CoarseDecoder()


class RoiSampler(_Frozen):
    """The fine stage's views: a square region of interest around the CM (margin ``margin_frac`` of
    its extent on each side, at least ``min_side_px`` input pixels), resampled from the input image
    to ``size``² and normalised as the coarse view.

    ``scales``: ROI side multipliers of the last fine pass ((1.0,): the ROI alone). Each scaled ROI
    (same centre) runs in the same batch; the landmarks are the median over the scales, the mask
    logits their mean on the input grid (different pixel grids and sizes: their errors partly cancel).
    """

    size: int = Field(128, gt=0)
    margin_frac: float = Field(0.2, ge=0.0)
    min_side_px: float = Field(24.0, gt=0.0)
    scales: tuple[float, ...] = (1.0,)
    low_pct: float = 1.0
    high_pct: float = 99.0

    @model_validator(mode="after")
    def _check(self) -> RoiSampler:
        if not self.scales or not all(0.25 <= float(f) <= 4.0 for f in self.scales):
            raise ValueError(f"scales must be 1 or more factors in [0.25, 4], got {self.scales}")
        return self


class FinePasses(_Frozen):
    """The fine stage's passes and test-time augmentation.

    Attributes:
        passes: passes; each after the first runs on a ROI fitted to the one before.
        max_passes: passes allowed in all while a pass's mask reaches the edge of its ROI inside the
            image (the CM goes on beyond it); values below ``passes`` add none.
        tta: dihedral transforms whose logits are averaged (1: none; 2: the mirror image; 4: + the
            180° turn and its mirror; 8: all quarter turns and their mirrors).
        first_tta: the transforms of the passes before the last (they only place the last pass's
            ROI); None: ``tta``.
        sure_tta: the transforms of the last pass where the pass before it was sure of both
            landmarks (confidences ≥ ``sure_confidence``); None: ``tta`` always.
        sure_confidence: the landmark confidence from which a pass counts as sure.
    """

    passes: int = Field(2, ge=1)
    max_passes: int = Field(0, ge=0)
    tta: Tta = 8
    first_tta: Tta | None = None
    sure_tta: Tta | None = None
    sure_confidence: float = Field(0.6, ge=0.0)


class FineDecoder(_Frozen):
    """How the fine stage's outputs are read (see :class:`CoarseDecoder` for ``heatmap``,
    ``sigma_px`` and ``mask_threshold``).

    Attributes:
        min_separation_px: smallest distance between the A and B peaks, ROI pixels (0: none); where
            both maps peak on the same end, one moves to its best peak outside that disk
            (:func:`~fluoronav.detection.heatmaps.separation_exclusion`).
        support_px: a landmark map peaking outside the largest component of its view's mask grown by
            this many ROI pixels is read at its best pixel inside it
            (:func:`~fluoronav.detection.decoder.off_support_exclusion`); 0: off.
        join_frac: the mask is its largest component plus, when this is > 0, the components within
            max(3 px, this · |AB|) of the segment A–B (a tube cut into pieces by noise or a crossing
            bone); 0: the largest component only.
    """

    heatmap: Literal["softmax", "gaussian"] = "softmax"
    sigma_px: float = Field(2.0, gt=0.0)
    mask_threshold: float = Field(0.5, gt=0.0, lt=1.0)
    min_separation_px: float = Field(0.0, ge=0.0)
    support_px: float = Field(0.0, ge=0.0)
    join_frac: float = Field(0.0, ge=0.0, le=1.0)

    @property
    def threshold_logit(self) -> float:
        """``mask_threshold`` as a logit."""
        return _logit(self.mask_threshold)


class FineHypotheses(_Frozen):
    """The other hypotheses the fine stage weighs against its first result.

    A hypothesis replaces the result where its mean landmark confidence is ``min_gain`` or more
    above the result's and the detection's acceptance rules take it.

    Attributes:
        coarse_split: where the two confident coarse landmarks lie on different components of the
            coarse mask, the fine stage also runs from each component alone with its landmark.
        coarse_other_min_px: each component of the coarse mask of this many coarse pixels or more
            that the first ROI was not fitted to is a hypothesis too (0: off).
        wide_factors: the second look: the last pass's ROI scaled by each factor (one batch; empty:
            none). A wider view that puts a landmark ``wide_min_shift_mm`` (mm at the detector) or
            more from the result's gives a hypothesis: the fine stage from a ROI fitted to it.
        wide_min_shift_mm: see ``wide_factors``.
        min_gain: the gain in mean landmark confidence by which a hypothesis replaces the result.
        wide_max_confidence: a result whose mean landmark confidence is above this gets no second
            look (1: every result does).
        wide_unfound: a result that is no detection gets the second look too (where it has a mask).
    """

    coarse_split: bool = False
    coarse_other_min_px: int = Field(0, ge=0)
    wide_factors: tuple[float, ...] = ()
    wide_min_shift_mm: float = Field(5.0, ge=0.0)
    min_gain: float = Field(0.15, ge=0.0, le=1.0)
    wide_max_confidence: float = Field(1.0, ge=0.0, le=1.0)
    wide_unfound: bool = False

    @model_validator(mode="after")
    def _check(self) -> FineHypotheses:
        if not all(1.0 < float(f) <= 4.0 for f in self.wide_factors):
            raise ValueError(f"wide_factors must be factors in (1, 4], got {self.wide_factors}")
        return self


class FineConfig(_Frozen):
    """The fine stage: its network, views, passes, decoder and hypotheses."""

    network: NetworkConfig = _unet(16, 32, 64, 128, 256)
    sampler: RoiSampler = RoiSampler()
    passes: FinePasses = FinePasses()
    decoder: FineDecoder = FineDecoder()
    hypotheses: FineHypotheses = FineHypotheses()

    @model_validator(mode="after")
    def _check(self) -> FineConfig:
        for name in ("min_separation_px", "support_px"):
            if not getattr(self.decoder, name) < self.sampler.size:
                raise ValueError(
                    f"decoder.{name} must be in [0, sampler.size), got {getattr(self.decoder, name)}"
                )
        return self


class AcceptConfig(_Frozen):
    """What a fine result needs to be a detection.

    Attributes:
        min_confidence: smallest landmark confidence counted as found (also the coarse and fine
            landmarks that place a ROI).
        weak_min_confidence: the confidence both landmarks need after a weak coarse mask
            (:attr:`CoarseDecoder.weak_mask_px`).
        padded_min_confidence: the confidence both landmarks need where the coarse view was widened
            (:attr:`WholeViewSampler.min_field_mm`; repeated edges can look like a tube).
        min_mask_mm2: smallest mask area at the detector (mm²; 0: off). A tube of diameter d projects
            to at least a disc of diameter d, so a smaller mask is not a whole CM (the paper's CM:
            π · 3² = 28.3 mm²).
    """

    min_confidence: float = Field(0.3, ge=0.0, le=1.0)
    weak_min_confidence: float = Field(0.15, ge=0.0, le=1.0)
    padded_min_confidence: float = Field(0.0, ge=0.0, le=1.0)
    min_mask_mm2: float = Field(0.0, ge=0.0)


class PatchSampler(_Frozen):
    """Tube-aligned patches of ``shape`` (rows across × cols along the tube) at ``step_mm`` per patch
    pixel at the detector (:class:`~fluoronav.detection.patches.RefinePatch`)."""

    shape: tuple[int, int] = (80, 64)
    step_mm: float = Field(0.291, gt=0.0)

    def step_px(self, pixel_spacing_mm: float | None, assumed_spacing_mm: float) -> float:
        """Input pixels per patch pixel for an image of this pixel spacing (mm; None:
        ``assumed_spacing_mm``)."""
        return self.step_mm / (pixel_spacing_mm or assumed_spacing_mm)


def _check_shape(name: str, network: NetworkConfig, shape: tuple[int, int]) -> None:
    div = network.divisor
    if len(shape) != 2 or any(int(n) <= 0 or int(n) % div for n in shape):
        raise ValueError(f"{name} shape must be 2 sizes divisible by {div}, got {shape}")


class RefineSampler(PatchSampler):
    """The refinement patches: one centred on each landmark, and one per ``shifts_px`` moved that
    many patch pixels along the tube ((0,): one patch)."""

    shape: tuple[int, int] = (48, 80)
    shifts_px: tuple[float, ...] = (0.0,)

    @model_validator(mode="after")
    def _check(self) -> RefineSampler:
        if not self.shifts_px or not all(abs(float(d)) <= 16.0 for d in self.shifts_px):
            raise ValueError(f"shifts_px must be 1 or more shifts in [-16, 16], got {self.shifts_px}")
        return self


class RefineDecoder(_Frozen):
    """How a refinement heatmap is read: ``sigma_px`` the σ of its targets (patch pixels), and a
    Gaussian prior of σ ``prior_px`` (patch pixels; 0: none) around the fine stage's landmark."""

    sigma_px: float = Field(1.5, gt=0.0)
    prior_px: float = Field(3.0, ge=0.0)


class RefineConfig(_Frozen):
    """The landmark refinement stage: its network (heatmap logits of A and B), patches, decoder and
    ``tta`` (2: logits averaged with those of the patch mirrored about the tube's axis)."""

    network: NetworkConfig = _unet(16, 32, 64, 128)
    sampler: RefineSampler = RefineSampler()
    decoder: RefineDecoder = RefineDecoder()
    tta: Literal[1, 2] = 2

    @model_validator(mode="after")
    def _check(self) -> RefineConfig:
        _check_shape("refine sampler", self.network, self.sampler.shape)
        return self


class TubeSampler(PatchSampler):
    """Patches centred every ``spacing_px`` patch pixels of arc length along the centreline."""

    spacing_px: float = Field(16.0, gt=0.0)


class TubeConfig(_Frozen):
    """The tube-mask stage: its network (a mask logit), patches along the centreline, the band of
    ``band_px`` patch pixels either side of its centre along the tube that each patch decides (mean
    logits where bands overlap), and ``tta`` (2: mirrored about the tube's axis too)."""

    network: NetworkConfig = _unet(8, 16, 32, 64)
    sampler: TubeSampler = TubeSampler()
    band_px: float = 16.0
    tta: Literal[1, 2] = 2

    @model_validator(mode="after")
    def _check(self) -> TubeConfig:
        _check_shape(f"{self.__class__.__name__} sampler", self.network, self.sampler.shape)
        if not 0 < self.band_px <= self.sampler.shape[1] / 2:
            raise ValueError(f"band_px must be in (0, sampler.shape[1] / 2], got {self.band_px}")
        return self


class EndsConfig(_Frozen):
    """The mask-end stage: its network (a mask logit), a patch at each landmark, whose mask replaces
    the mask from ``inner_px`` patch pixels inside the landmark outwards, and ``tta``."""

    network: NetworkConfig = _unet(16, 32, 64, 128)
    sampler: PatchSampler = PatchSampler()
    inner_px: float = 8.0
    tta: Literal[1, 2] = 2

    @model_validator(mode="after")
    def _check(self) -> EndsConfig:
        _check_shape("ends sampler", self.network, self.sampler.shape)
        if not 0.0 <= self.inner_px <= self.sampler.shape[1] / 2:
            raise ValueError(f"inner_px must be in [0, sampler.shape[1] / 2], got {self.inner_px}")
        return self


class FreeEndConfig(_Frozen):
    """The free-end check of landmark A: where A's fine confidence is at least ``min_confidence`` and
    the image has less tube around A outside the mask than ``max_continuation``
    (:func:`~fluoronav.detection.evidence.end_continuation`: 0 for a free end, about 1 where the
    shaft goes on), A is read again away from that end, and the new place is taken where it has more
    tube around it than that."""

    max_continuation: float = Field(0.35, gt=0.0, le=1.0)
    min_confidence: float = Field(0.35, ge=0.0, le=1.0)


class ShaftConfig(TubeConfig):
    """The shaft check of landmark A: a tube-mask network trained with patches on the mounting shaft
    too (labelled not-CM) redraws the mask along the centreline; where it leaves ``cut_min_mm`` (mm
    at the detector) or more of the centreline's start out, A is read again where its CM begins (the
    centreline's first stretch of ``cut_run_mm`` wholly inside). It judges only where the mean logit
    of a patch's core is ``min_cm_logit`` or more in one patch at least."""

    cut_min_mm: float = Field(5.0, gt=0.0)
    cut_run_mm: float = Field(3.0, gt=0.0)
    min_cm_logit: float = 2.0


class EdgeConfig(_Frozen):
    """The edge check: a detection's mask needs the boundary-to-surroundings gradient ratio
    ``min_ratio`` (:func:`~fluoronav.detection.evidence.mask_edge_ratio`), and ``unsure_min_ratio``
    where its smaller landmark confidence is below ``unsure_below_confidence``."""

    min_ratio: float = Field(1.4, ge=0.0)
    unsure_below_confidence: float = Field(0.2, ge=0.0, le=1.0)
    unsure_min_ratio: float = Field(2.2, ge=0.0)

    def needed_ratio(self, smaller_confidence: float) -> float:
        """The ratio a detection with this smaller landmark confidence needs (0: none)."""
        if smaller_confidence < self.unsure_below_confidence:
            return max(self.min_ratio, self.unsure_min_ratio)
        return self.min_ratio


#: the config class of each optional stage
_STAGE_CLASSES: dict[str, type[_Frozen]] = {
    "refine": RefineConfig,
    "tube": TubeConfig,
    "ends": EndsConfig,
    "free_end": FreeEndConfig,
    "shaft": ShaftConfig,
    "edge": EdgeConfig,
}


class DetectorConfig(_Frozen):
    """The stages a detector runs and their settings.

    Attributes:
        stages: the stages run, a subsequence of :data:`STAGE_ORDER` holding ``coarse`` and ``fine``.
        assumed_spacing_mm: pixel spacing taken for images that do not give theirs.
        bf16_stages: the networks (names from :data:`NETWORK_STAGES`) that run in bfloat16 where the
            detector is asked for it (``Detector(precision="bfloat16")``); the others in float32.
        accept: what a fine result needs to be a detection.
        coarse, fine, refine, tube, ends, free_end, shaft, edge: each stage's settings; a stage not in
            ``stages`` has none (None), a listed one without settings gets the defaults.
    """

    stages: tuple[str, ...] = ("coarse", "fine")
    assumed_spacing_mm: float = Field(ASSUMED_SPACING_MM, gt=0.0)
    bf16_stages: tuple[str, ...] = ()
    accept: AcceptConfig = AcceptConfig()
    coarse: CoarseConfig = CoarseConfig()
    fine: FineConfig = FineConfig()
    refine: RefineConfig | None = None
    tube: TubeConfig | None = None
    ends: EndsConfig | None = None
    free_end: FreeEndConfig | None = None
    shaft: ShaftConfig | None = None
    edge: EdgeConfig | None = None

    @model_validator(mode="before")
    @classmethod
    def _declare(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        data = dict(data)
        for name in data.get("stages", ()):
            if name in _STAGE_CLASSES and data.get(name) is None:
                data[name] = {}
        return data

    @model_validator(mode="after")
    def _check(self) -> DetectorConfig:
        order = [s for s in STAGE_ORDER if s in self.stages]
        if list(self.stages) != order or len(set(self.stages)) != len(self.stages):
            raise ValueError(f"stages must be a subsequence of {STAGE_ORDER}, got {self.stages}")
        if not {"coarse", "fine"} <= set(self.stages):
            raise ValueError(f"stages must hold 'coarse' and 'fine', got {self.stages}")
        for name in _STAGE_CLASSES:
            if getattr(self, name) is not None and name not in self.stages:
                raise ValueError(f"{name} has settings but is not in stages {self.stages}")
        if not set(self.bf16_stages) <= set(NETWORK_STAGES):
            raise ValueError(f"bf16_stages must be names from {NETWORK_STAGES}, got {self.bf16_stages}")
        return self

    @property
    def network_stages(self) -> tuple[str, ...]:
        """The listed stages that have a network, in :data:`NETWORK_STAGES` order."""
        return tuple(s for s in NETWORK_STAGES if s in self.stages)

    def network(self, stage: str) -> NetworkConfig:
        """The network settings of a listed stage."""
        if stage not in self.network_stages:
            raise KeyError(f"no network stage {stage!r} in {self.stages}")
        network: NetworkConfig = getattr(self, stage).network
        return network

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (lists for tuples; the stages not listed left out)."""
        return self.model_dump(mode="json", exclude_none=True)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> DetectorConfig:
        """A config from :meth:`to_dict`'s form (validated: an unknown key raises)."""
        return cls.model_validate(d)


def _logit(p: float) -> float:
    return float(math.log(p / (1.0 - p)))
