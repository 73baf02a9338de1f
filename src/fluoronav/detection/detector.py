"""Inference API of the learned CM detector, image loaders and the ``detect`` output files.

``Detector.load()`` reads the shipped weights (``fluoronav/data/detector.pt``) or a model file written
by ``fluoronav train``; ``Detector.detect(image)`` runs the coarse stage on the whole image, the fine
stage on a region of interest around the coarse detection, refines the landmarks on tube-aligned
patches where the model has a refinement stage (:mod:`fluoronav.detection.refine`), extracts the
centreline (:func:`fluoronav.detection.centerline.extract_centerline`) from the fine mask between the
landmarks, and, where the model has them, redraws the mask along that centreline and at its two ends
on tube-aligned patches (the tube-mask and mask-end stages, :mod:`fluoronav.detection.ends`).

Input images are detector images after the log transform, bone and metal bright (as ``simulate``
writes them). :func:`load_image` converts other files to that form:

- ``.npz`` (key ``image``) and ``.npy``: taken as-is.
- 8/16-bit PNG/TIFF/JPEG: raw intensities where dark = attenuating; converted with
  ``−ln((I + 1) / (I_max + 1))``, I_max the type's full scale (255 or 65535). Colour is averaged to
  grey. The constant offset of that rule does not matter: the detector normalises each image.
- float TIFF: taken as-is (already a log image).
- DICOM (read with SimpleITK): values after the modality rescale; MONOCHROME2 is taken as-is (bright =
  attenuating, as radiographs are presented), MONOCHROME1 is inverted (max − value). The pixel spacing
  is Imager Pixel Spacing (0018,1164), else Pixel Spacing (0028,0030), when present.
"""

from __future__ import annotations

import copy
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch
from scipy import ndimage as ndi

from fluoronav.detection.centerline import extract_centerline
from fluoronav.detection.ends import end_zone_paste, sample_patches, tube_frames, tube_paste
from fluoronav.detection.evidence import end_continuation, local_tube_width_px, mask_edge_ratio
from fluoronav.detection.heatmaps import decode_landmarks
from fluoronav.detection.model import (
    MODEL_FORMAT_VERSION,
    DetectorConfig,
    DetectorNet,
    fold_batch_norm,
    pack_for_cpu,
)
from fluoronav.detection.refine import RefinePatch, decode_refine_logits, refine_patch
from fluoronav.detection.strip import path_strips, strip_log_probs, v_apex, window_probability
from fluoronav.detection.views import View, full_view, normalize_intensity, paste, resample, roi_view
from fluoronav.device import resolve_device
from fluoronav.errors import FluoronavError, InputError

logger = logging.getLogger(__name__)

SHIPPED_MODEL_NAME = "detector.pt"
IMAGE_SUFFIXES = (".npz", ".npy", ".png", ".tif", ".tiff", ".jpg", ".jpeg", ".dcm", ".dicom")


def shipped_model_path() -> Path:
    """Where the shipped weights live inside the installed package."""
    return Path(str(resources.files("fluoronav") / "data" / SHIPPED_MODEL_NAME))


#: a found landmark further than this (mm at the detector) from the mask is not on the CM: its
#: detection is not usable (the CM's tube is ~6 mm wide and A and B lie on it; no landmark of the
#: validation sets is more than 3 mm off its mask, stop 35)
OFF_MASK_MM = 3.0

#: pixel spacing (mm) taken for images without one: the training images' (the 1536² detector binned
#: 3×), the configuration's default for the refinement and ``min_mask_mm2``
ASSUMED_SPACING_MM: float = DetectorConfig.refine_assumed_spacing_mm


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
        (:func:`truncated_landmarks`). All False when nothing was found."""
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
        dist_px = _distances_to_mask(self.mask, np.asarray(self.landmarks_px))
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


@dataclass(frozen=True)
class FineResult:
    """One fine-stage hypothesis: landmarks (2, 2) input px, confidences (2,), mask (rows, cols) bool
    and the last pass's ROI at scale 1."""

    landmarks_px: np.ndarray
    confidence: np.ndarray
    mask: np.ndarray
    view: View


class Finished(NamedTuple):
    """A detection's last steps from its fine landmarks: refined landmarks (2, 2) input px, the
    centreline (N, 2) and the final mask (rows, cols) bool."""

    landmarks_px: np.ndarray
    centerline_px: np.ndarray
    mask: np.ndarray


def truncated_landmarks(
    mask: np.ndarray, landmarks_px: np.ndarray, *, edge_px: float = 3.0, reach_px: float = 10.0
) -> np.ndarray:
    """Which landmarks (2, 2) (u, v) sit where a mask (rows, cols) is cut by the image border → (2,) bool.

    A landmark counts as truncated when it lies within ``edge_px`` of a border and the mask has pixels
    on that border within ``reach_px`` of it: the CM leaves the field there, and the detector, which
    only sees the image, puts the landmark at the cut.
    """
    rows, cols = mask.shape
    out = np.zeros(2, dtype=bool)
    for k, (u, v) in enumerate(np.asarray(landmarks_px, dtype=np.float64).reshape(2, 2)):
        # (distance to the border, the mask's border line, the landmark's position along it)
        borders = (
            (u, mask[:, 0], v),
            (cols - 1 - u, mask[:, -1], v),
            (v, mask[0, :], u),
            (rows - 1 - v, mask[-1, :], u),
        )
        for dist, line, along in borders:
            if dist > edge_px:
                continue
            idx = np.flatnonzero(line)
            if idx.size and float(np.min(np.abs(idx - along))) <= reach_px:
                out[k] = True
    return out


def _component_at(mask: np.ndarray, seeds_uv: np.ndarray) -> np.ndarray:
    """The connected components of ``mask`` within 2 px of any seed (N, 2) (u, v); the largest if none."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:
        return mask.astype(bool)
    keep: set[int] = set()
    rows, cols = mask.shape
    for u, v in np.asarray(seeds_uv, dtype=np.float64).reshape(-1, 2):
        r0, r1 = int(max(round(v) - 2, 0)), int(min(round(v) + 3, rows))
        c0, c1 = int(max(round(u) - 2, 0)), int(min(round(u) + 3, cols))
        keep.update(int(x) for x in np.unique(labels[r0:r1, c0:c1]) if x > 0)
    if not keep:
        return labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return np.isin(labels, sorted(keep))


#: (quarter turns, mirrored) of the dihedral group, in the order the test-time augmentation adds them
DIHEDRAL: tuple[tuple[int, bool], ...] = (
    (0, False),
    (0, True),
    (2, False),
    (2, True),
    (1, False),
    (1, True),
    (3, False),
    (3, True),
)


#: the precisions a :class:`Detector` runs its networks in
PRECISIONS = ("auto", "float32", "bfloat16")


def native_bf16() -> bool:
    """Whether this CPU has native bfloat16 arithmetic (x86 AVX512-BF16 or AMX-BF16), where oneDNN
    runs bfloat16 convolutions about twice as fast as float32 ones; elsewhere it would emulate them,
    slower than float32."""
    caps = torch.cpu.get_capabilities()
    return bool(caps.get("avx512_bf16", False) or caps.get("amx_bf16", False))


def resolve_precision(name: str, device: torch.device) -> str:
    """``float32`` or ``bfloat16`` for a precision name of :data:`PRECISIONS` on ``device``: ``auto``
    is ``bfloat16`` on a CPU with :func:`native_bf16`, else ``float32`` (on CUDA too: the shipped
    model's bfloat16 results were measured on the CPU only)."""
    key = str(name).lower()
    if key not in PRECISIONS:
        raise InputError("--precision", f"unknown precision {name!r}; use {', '.join(PRECISIONS)}")
    if key == "auto":
        return "bfloat16" if device.type == "cpu" and native_bf16() else "float32"
    return key


def _mirror_mean(net: torch.nn.Module, x: torch.Tensor, tta: int) -> torch.Tensor:
    """A patch network's output (N, C, rows, cols) on tube-aligned patches ``x`` (N, 1, rows, cols);
    with ``tta`` 2 averaged with its output on the patches mirrored about the tube's axis (rows
    flipped), both in one batch; float32 whatever precision the network ran in."""
    if tta == 1:
        return net(x).float()
    n = x.shape[0]
    out = net(torch.cat([x, x.flip(-2)])).float()
    return 0.5 * (out[:n] + out[n:].flip(-2))


def _dihedral(x: torch.Tensor, quarter_turns: int, mirrored: bool) -> torch.Tensor:
    """(…, S, S) mirrored left-right (if asked), then turned by quarter turns."""
    y = torch.flip(x, dims=[-1]) if mirrored else x
    return torch.rot90(y, quarter_turns, dims=(-2, -1)) if quarter_turns else y


def _dihedral_inverse(y: torch.Tensor, quarter_turns: int, mirrored: bool) -> torch.Tensor:
    """Undo :func:`_dihedral`."""
    x = torch.rot90(y, -quarter_turns, dims=(-2, -1)) if quarter_turns else y
    return torch.flip(x, dims=[-1]) if mirrored else x


def _check_image(image: np.ndarray, source: str) -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim == 3 and 1 in (arr.shape[0], arr.shape[-1]):
        arr = arr.reshape(arr.shape[1:] if arr.shape[0] == 1 else arr.shape[:-1])
    if arr.ndim != 2 or min(arr.shape) < 8:
        raise InputError(source, f"expected a 2-D image of at least 8×8 pixels, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise InputError(source, f"image values must be numeric, got {arr.dtype}")
    arr = arr.astype(np.float32)
    if not np.all(np.isfinite(arr)):
        raise InputError(source, "image contains NaN or infinite values")
    return arr


def load_net(path: str | Path | None = None) -> DetectorNet:
    """The networks of a model file written by ``fluoronav train`` (None: the shipped weights), as
    trained (batch norms unfolded, train mode), validated: a missing, damaged or foreign file
    raises :class:`~fluoronav.errors.InputError` naming it."""
    if path is None:
        path = shipped_model_path()
        if not path.is_file():
            raise FluoronavError(
                f"no shipped detector weights at {path}; train a model with "
                "`fluoronav simulate --n 2000 --out DATA` then "
                "`fluoronav train --data DATA --out MODEL.pt` and pass it with --model MODEL.pt"
            )
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "model file not found")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for damaged files
        raise InputError(path, f"unreadable model file ({exc.__class__.__name__})") from exc
    if not isinstance(blob, dict) or "state_dict" not in blob or "config" not in blob:
        raise InputError(path, "not a fluoronav detector model (no state_dict/config)")
    if int(blob.get("format_version", 0)) > MODEL_FORMAT_VERSION:
        raise InputError(path, f"model format {blob.get('format_version')} is newer than this fluoronav")
    try:
        net = DetectorNet(DetectorConfig.from_dict(blob["config"]))
        net.load_state_dict(blob["state_dict"])
    except (RuntimeError, TypeError, ValueError) as exc:
        raise InputError(
            path, f"weights do not match the model configuration ({exc.__class__.__name__})"
        ) from exc
    return net


class Detector:
    """The CM detector (coarse, fine and, where the model has one, refinement stage) on one torch device."""

    def __init__(
        self,
        net: DetectorNet,
        *,
        device: str | torch.device = "auto",
        precision: str = "float32",
        source: str = "<memory>",
    ) -> None:
        """``precision``: ``float32`` (the default) runs every network in float32; ``bfloat16`` runs
        the model's ``bf16_stages`` in bfloat16 (autocast; the decoding stays in float32): faster on
        a CPU with native bfloat16 arithmetic, its logits ~0.05 off, which tips some ambiguous
        views the other way; ``auto`` is ``bfloat16`` on a CPU with native bfloat16
        (:func:`native_bf16`) and ``float32`` elsewhere. The chosen one is in :attr:`precision`."""
        self.device = resolve_device(device)
        self.config: DetectorConfig = net.config
        self.source = source
        self.precision = resolve_precision(precision, self.device)
        names = self.config.bf16_stages if self.precision == "bfloat16" else ()
        self.net = copy.deepcopy(net).to(self.device).eval()  # the caller's networks stay trainable
        # the float32 networks as inference needs them: each batch norm folded into its convolution
        # (a pass over the activations less per layer; the same function to fp32 rounding)
        exact = [m for n, m in self.net.named_children() if n not in names]
        for m in exact:
            fold_batch_norm(m)
        if self.device.type == "cpu":
            # oneDNN runs these small-channel convolutions, the transposed ones above all, 10-30 %
            # faster on channels-last weights (the inputs follow); the results are the same to fp32
            # rounding. Module.to takes memory_format at run time; torch's stubs leave it out.
            self.net = self.net.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
            for m in exact:
                pack_for_cpu(m)  # each convolution and its PReLU in one oneDNN call, bit-identical
        self._bf16_nets = [m for m in (getattr(self.net, n, None) for n in names) if m is not None]

    def _autocast(self, net: torch.nn.Module) -> torch.autocast:
        """The autocast context a network runs in: bfloat16 where it is one of the ``bf16_stages``
        and the precision allows it, else off (float32)."""
        on = any(net is m for m in self._bf16_nets)
        return torch.autocast(device_type=self.device.type, dtype=torch.bfloat16, enabled=on)

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

    @torch.no_grad()
    def _run(
        self,
        net: torch.nn.Module,
        view_images: np.ndarray,
        *,
        tta: int = 1,
        min_separation_px: float = 0.0,
        support_px: float = 0.0,
        exclude: torch.Tensor | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(N, S, S) normalised views → seg logits (N, S, S), landmarks (N, 2, 2) view px, confidences (N, 2).

        All views and their transforms go through the network in one batch. ``tta`` > 1 averages the
        logits over that many dihedral transforms of each view (each mapped back): the network's small
        orientation biases cancel, which sharpens mask edges and landmarks. ``min_separation_px``: see
        :func:`~fluoronav.detection.heatmaps.separation_exclusion`; ``support_px``: see
        :func:`off_support_exclusion`; ``exclude``: (N, 2, S, S) bool heatmap pixels that may not
        be a landmark besides.
        """
        x = torch.from_numpy(np.ascontiguousarray(view_images, dtype=np.float32))[:, None].to(self.device)
        transforms = DIHEDRAL[:tta]
        with self._autocast(net):
            outs = net(torch.cat([_dihedral(x, k, f) for k, f in transforms]))
        outs, n = outs.float(), x.shape[0]  # the mean and the decoding in float32 (faster, too)
        out = torch.stack(
            [_dihedral_inverse(outs[i * n : (i + 1) * n], k, f) for i, (k, f) in enumerate(transforms)]
        ).mean(0)  # (N, 3, S, S)
        if exclude is not None:
            exclude = exclude.to(out.device)
        if support_px > 0.0:
            off = off_support_exclusion(
                out[:, 0], out[:, 1:], threshold_logit=self.config.mask_threshold_logit, support_px=support_px
            )
            exclude = off if exclude is None else exclude | off
        pts, conf = decode_landmarks(
            out[:, 1:],
            mode=self.config.heatmap,
            sigma_px=self.config.sigma_px,
            min_separation_px=min_separation_px,
            exclude=exclude,
        )
        return out[:, 0].cpu().numpy(), pts.cpu().numpy().astype(np.float64), conf.cpu().numpy()

    def _view_input(self, image: np.ndarray, view: View) -> np.ndarray:
        cfg = self.config
        return normalize_intensity(resample(image, view), low_pct=cfg.low_pct, high_pct=cfg.high_pct)

    def coarse_view(self, shape: tuple[int, int], pixel_spacing_mm: float | None = None) -> View:
        """The coarse stage's view of a (rows, cols) image: the whole image, widened to
        ``coarse_min_field_mm`` where the pixel spacing (mm) is known and the image is smaller."""
        field_mm = self.config.coarse_min_field_mm
        min_side = field_mm / pixel_spacing_mm if field_mm > 0 and pixel_spacing_mm else 0.0
        return full_view(shape, self.config.input_size, min_side_px=min_side)

    def coarse(
        self, image: np.ndarray, *, pixel_spacing_mm: float | None = None
    ) -> tuple[View, np.ndarray, np.ndarray, np.ndarray]:
        """Coarse stage: view, seg logit (S, S), landmarks (2, 2) in input px, confidences (2,)."""
        cv = self.coarse_view(image.shape, pixel_spacing_mm)
        logit, pts, conf = self._run(self.net.coarse, self._view_input(image, cv)[None])
        return cv, logit[0], cv.to_input(pts[0]), conf[0]

    def fine(
        self, image: np.ndarray, view: View, *, tta: int | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Fine stage on a ROI: seg logit (R, R), landmarks (2, 2) in input px, confidences (2,).
        ``tta``: dihedral transforms (None: ``fine_tta``)."""
        logits, pts, conf = self.fine_views(image, [view], tta=tta)
        return logits[0], pts[0], conf[0]

    def fine_views(
        self,
        image: np.ndarray,
        views: list[View],
        *,
        tta: int | None = None,
        exclude_disk: tuple[int, np.ndarray, float] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Fine stage on several ROIs in one batch: seg logits (N, R, R), landmarks (N, 2, 2) in input
        px, confidences (N, 2). ``tta``: dihedral transforms per view (None: ``fine_tta``).
        ``exclude_disk``: (landmark index, centre (2,) input px, radius input px), a disk where that
        landmark may not be taken."""
        stack = np.stack([self._view_input(image, v) for v in views])
        tta = self.config.fine_tta if tta is None else tta
        cfg = self.config
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
        logits, pts, conf = self._run(
            self.net.fine,
            stack,
            tta=tta,
            min_separation_px=cfg.fine_min_separation_px,
            support_px=cfg.fine_support_px,
            exclude=exclude,
        )
        return logits, np.stack([v.to_input(p) for v, p in zip(views, pts, strict=True)]), conf

    def detect(self, image: np.ndarray, *, pixel_spacing_mm: float | None = None) -> Detection:
        """Detect the CM in a (rows, cols) log image (bright = attenuating).

        Returns a :class:`Detection` in the input's pixels; ``found`` is False when the coarse mask is
        smaller than ``min_mask_px`` or a landmark confidence is below ``min_confidence`` (a weak coarse
        mask, between ``weak_mask_px`` and ``min_mask_px``, needs ``weak_min_confidence`` instead), or
        when the final mask covers less than ``min_mask_mm2`` at the detector, or when its boundary
        lies on no edge of the image (``min_edge_ratio``, ``unsure_min_edge_ratio`` for a landmark
        confidence below ``unsure_below_confidence``;
        :func:`~fluoronav.detection.evidence.mask_edge_ratio`).
        ``pixel_spacing_mm`` (mm per input pixel at the detector), where given, lets an image smaller
        than ``coarse_min_field_mm`` be seen by the coarse stage at the scale of a whole field; such a
        detection needs ``padded_min_confidence``.
        """
        img = _check_image(image, "image")
        cfg = self.config
        shape = img.shape
        thr_logit = cfg.mask_threshold_logit
        empty = Detection(False, None, np.zeros(2), np.zeros(shape, bool), None, pixel_spacing_mm)
        cv, c_logit, c_pts, c_conf = self.coarse(img, pixel_spacing_mm=pixel_spacing_mm)
        padded = cv.side > max(shape)
        c_mask = c_logit > thr_logit
        c_area = int(c_mask.sum())
        weak = c_area < cfg.min_mask_px
        if c_area < (cfg.weak_mask_px or cfg.min_mask_px):
            return empty
        # false alarms on CM-free images mostly start as small coarse masks: those need surer landmarks
        need = max(cfg.weak_min_confidence, cfg.min_confidence) if weak else cfg.min_confidence
        if padded:
            need = max(need, cfg.padded_min_confidence)
        spacing_mm = pixel_spacing_mm or cfg.refine_assumed_spacing_mm

        def accepted(r: FineResult) -> bool:
            area_mm2 = float(r.mask.sum()) * spacing_mm**2
            return bool(r.mask.any()) and float(r.confidence.min()) >= need and area_mm2 >= cfg.min_mask_mm2

        confident = c_conf >= cfg.min_confidence
        both = bool(confident.all())
        first_mask = _component_at(c_mask, cv.from_input(c_pts[confident]))
        res = self.fine_stage(img, self._roi(cv, first_mask, c_pts[confident]))
        if (cfg.coarse_split and both) or cfg.coarse_other_min_px > 0:
            res = self._coarse_hypotheses(
                img, cv, c_mask, c_pts, res, accept=accepted, first_mask=first_mask, both=both
            )
        # the second look takes only hypotheses that are a detection; where the first result is none,
        # it is looked at again only with fine_wide_unfound
        if accepted(res) or (cfg.fine_wide_unfound and res.mask.any()):
            res = self.second_look(img, res, pixel_spacing_mm=pixel_spacing_mm, accept=accepted)
        if not accepted(res):
            conf = res.confidence.astype(np.float64)
            return Detection(False, None, conf, res.mask, None, pixel_spacing_mm)
        f_conf = res.confidence

        def finish(fine_pts: np.ndarray) -> Finished:
            """Refined landmarks, the centreline and the final mask from the fine landmarks."""
            pts = self.refine(img, fine_pts, res.mask, pixel_spacing_mm=pixel_spacing_mm)
            # the centreline of the fine mask: the patch-mask stages move its edges by a pixel or less
            line = extract_centerline(res.mask, pts[0], pts[1])
            m = self.mask_tube(img, line, res.mask, pixel_spacing_mm=pixel_spacing_mm)
            return Finished(pts, line, self.mask_ends(img, pts, m, pixel_spacing_mm=pixel_spacing_mm))

        final = finish(res.landmarks_px)
        if cfg.free_end_max_continuation > 0.0:
            final = self.off_free_end(img, res, final, finish, pixel_spacing_mm=pixel_spacing_mm)
        cut = final
        if cfg.shaft_cut_min_mm > 0.0:
            cut = self.off_shaft(img, res, final, finish, pixel_spacing_mm=pixel_spacing_mm)
        if cut is final and cfg.apex_max_confidence > 0.0:  # the shaft stage moved nothing
            cut = self.off_apex(img, res, final, finish, pixel_spacing_mm=pixel_spacing_mm)
        final = cut
        f_pts, centerline, mask = final.landmarks_px, final.centerline_px, final.mask
        need_ratio = cfg.needed_edge_ratio(float(f_conf.min()))
        if need_ratio > 0.0:
            ratio = mask_edge_ratio(img, mask, pixel_spacing_mm=spacing_mm)
            if ratio < need_ratio:
                logger.debug("no edge on the mask's boundary (ratio %.2f < %.2f): no CM", ratio, need_ratio)
                return Detection(False, None, f_conf.astype(np.float64), mask, None, pixel_spacing_mm)
        return Detection(True, f_pts, f_conf.astype(np.float64), mask, centerline, pixel_spacing_mm)

    @torch.no_grad()
    def refine(
        self,
        image: np.ndarray,
        landmarks_px: np.ndarray,
        mask: np.ndarray,
        *,
        pixel_spacing_mm: float | None = None,
    ) -> np.ndarray:
        """The landmarks (2, 2) (u, v) input px refined on tube-aligned patches
        (:mod:`fluoronav.detection.refine`); unchanged without a refinement stage, and each landmark
        whose direction the mask does not give (a CM seen end-on) keeps its place.

        Each landmark is read from one patch per ``refine_shifts_px`` (moved along the tube, the
        prior staying at the landmark) and the mean of those estimates is taken. All patches of
        both landmarks and their mirror images (``refine_tta``) go through the network in one batch.
        """
        net, cfg = self.net.refine, self.config
        if net is None:
            return landmarks_px
        step = cfg.refine_step_px(pixel_spacing_mm)
        todo: list[tuple[int, RefinePatch]] = []  # (landmark, patch)
        for k, p in enumerate(landmarks_px):
            frame = refine_patch(mask, p, step_px=step, shape=cfg.refine_shape)
            if frame is not None:
                todo += [(k, frame.shifted(d)) for d in cfg.refine_shifts_px]
        if not todo:
            return landmarks_px
        x = torch.from_numpy(np.stack([fr.sample(image) for _, fr in todo]))[:, None].to(self.device)
        with self._autocast(net):
            out = _mirror_mean(net, x, cfg.refine_tta).cpu()
        ks = np.array([k for k, _ in todo])
        sel = out[torch.arange(len(todo)), torch.from_numpy(ks)][:, None]
        # the prior stays at the fine stage's landmark in every shifted patch
        centers = np.stack([fr.from_input(landmarks_px[k]) for k, fr in todo])
        pts, _ = decode_refine_logits(
            sel,
            sigma_px=cfg.refine_sigma_px,
            prior_px=cfg.refine_prior_px,
            prior_center_px=torch.from_numpy(centers).float(),
        )
        estimates = np.stack(
            [fr.to_input(q) for (_, fr), q in zip(todo, pts.numpy().astype(np.float64), strict=True)]
        )
        refined = np.array(landmarks_px, dtype=np.float64, copy=True)
        for k in np.unique(ks):
            refined[k] = estimates[ks == k].mean(axis=0)
        return refined

    @torch.no_grad()
    def mask_ends(
        self,
        image: np.ndarray,
        landmarks_px: np.ndarray,
        mask: np.ndarray,
        *,
        pixel_spacing_mm: float | None = None,
    ) -> np.ndarray:
        """The mask (rows, cols) bool with its ends redrawn by the mask-end stage
        (:mod:`fluoronav.detection.ends`) on a tube-aligned patch at each landmark (2, 2) (u, v) input
        px; unchanged without that stage, and at a landmark whose direction the mask does not give.
        Both patches (and with ``ends_tta`` 2 their mirror images about the tube's axis, the logits
        averaged) go through the network in one batch."""
        net, cfg = self.net.ends, self.config
        if net is None:
            return mask
        step = cfg.refine_step_px(pixel_spacing_mm)
        frames = [refine_patch(mask, p, step_px=step, shape=cfg.ends_shape) for p in landmarks_px]
        todo = [f for f in frames if f is not None]
        if not todo:
            return mask
        for frame, logit in zip(todo, self._patch_logits(net, image, todo), strict=True):
            mask = end_zone_paste(mask, frame, logit, inner_px=cfg.ends_inner_px)
        return mask

    @torch.no_grad()
    def mask_tube(
        self,
        image: np.ndarray,
        centerline_px: np.ndarray,
        mask: np.ndarray,
        *,
        pixel_spacing_mm: float | None = None,
    ) -> np.ndarray:
        """The mask (rows, cols) bool redrawn along the tube by the tube-mask stage
        (:mod:`fluoronav.detection.ends`): patches every ``tube_spacing_px`` along the CM's
        centreline (N, 2) (u, v) input px from A to B, each deciding the band of ``tube_band_px``
        around its centre (mean logits where bands overlap); unchanged without that stage. All
        patches (and with ``ends_tta`` 2 their mirror images) go through the network in one batch."""
        net, cfg = self.net.tube, self.config
        if net is None:
            return mask
        step = cfg.refine_step_px(pixel_spacing_mm)
        frames = tube_frames(
            centerline_px, step_px=step, shape=cfg.ends_shape, spacing_px=cfg.tube_spacing_px * step
        )
        if not frames:
            return mask
        return tube_paste(mask, frames, self._patch_logits(net, image, frames), band_px=cfg.tube_band_px)

    def _patch_logits(self, net: torch.nn.Module, image: np.ndarray, frames: list[RefinePatch]) -> np.ndarray:
        """(P, rows, cols) mask logits of a patch-mask stage on ``frames``' patches of ``image``, with
        ``ends_tta`` 2 each averaged with that of its mirror image about the tube's axis (one batch)."""
        x = torch.from_numpy(sample_patches(image, frames))[:, None].to(self.device)
        with self._autocast(net):
            out = _mirror_mean(net, x, self.config.ends_tta)
        return out[:, 0].cpu().numpy()

    def _coarse_hypotheses(
        self,
        image: np.ndarray,
        cv: View,
        c_mask: np.ndarray,
        c_pts: np.ndarray,
        first: FineResult,
        *,
        accept: Callable[[FineResult], bool],
        first_mask: np.ndarray | None = None,
        both: bool = True,
    ) -> FineResult:
        """``first``, or a hypothesis from another part of the coarse mask (view px) that is surer by
        ``fine_wide_min_gain``: with ``coarse_split``, where the two landmarks (2, 2) input px
        (``both`` confident) lie on different components, the fine stage from each one's component
        alone with its landmark; with ``coarse_other_min_px``, from each component of that many
        pixels or more outside ``first_mask`` (the components ``first`` started from) alone."""
        cfg = self.config
        starts: list[View] = []
        if cfg.coarse_split and both:
            seeds = cv.from_input(c_pts)
            # a seed on no component gets the largest one, a mask of one component itself: both overlap
            parts = [_component_at(c_mask, seeds[k : k + 1]) for k in range(2)]
            if not bool((parts[0] & parts[1]).any()):
                starts += [self._roi(cv, parts[k], c_pts[k : k + 1]) for k in range(2)]
        if cfg.coarse_other_min_px > 0 and first_mask is not None:
            n, labels, stats, _ = cv2.connectedComponentsWithStats(c_mask.astype(np.uint8), connectivity=8)
            for j in range(1, n):
                part = labels == j
                if stats[j, cv2.CC_STAT_AREA] >= cfg.coarse_other_min_px and not (part & first_mask).any():
                    starts.append(self._roi(cv, part, np.zeros((0, 2))))
        return self._surest(image, first, starts, accept=accept, what="another part of the coarse mask")

    def _surest(
        self,
        image: np.ndarray,
        first: FineResult,
        starts: list[View],
        *,
        accept: Callable[[FineResult], bool],
        what: str,
    ) -> FineResult:
        """``first``, or of the fine stage's results from ``starts`` (first ROIs) those that
        ``accept`` takes, the one of the highest mean landmark confidence where that mean is
        ``fine_wide_min_gain`` or more above ``first``'s. ``what`` names the hypotheses in the log."""
        best, best_score = first, float(np.mean(first.confidence)) + self.config.fine_wide_min_gain
        for start in starts:
            other = self.fine_stage(image, start)
            score = float(np.mean(other.confidence))
            if score >= best_score and accept(other):
                best, best_score = other, score
        if best is not first:
            logger.debug("%s: confidence %s -> %s", what, first.confidence, best.confidence)
        return best

    def second_look(
        self,
        image: np.ndarray,
        first: FineResult,
        *,
        pixel_spacing_mm: float | None = None,
        accept: Callable[[FineResult], bool] | None = None,
    ) -> FineResult:
        """The fine stage's result, or a second hypothesis from a wider view that the network is
        surer of (``fine_wide_factors``; see :class:`~fluoronav.detection.model.DetectorConfig`).

        A detection whose mean landmark confidence is above ``fine_wide_max_confidence`` is
        returned as it is. Otherwise the last pass's ROI scaled by each factor goes through the fine
        stage in one batch; each wider view that puts a landmark ``fine_wide_min_shift_mm`` (mm at
        the detector) or more from ``first``'s is followed by all fine passes from a ROI fitted to
        its result. Of these hypotheses, those that ``accept`` takes for a detection (by default:
        any with a mask), the one of the highest mean landmark confidence replaces ``first`` if that
        mean is ``fine_wide_min_gain`` or more above ``first``'s. (The mean, not the smaller one: a
        CM cut short has its landmark at the cut unsure, and the other end's often too.)
        """
        cfg = self.config
        if not cfg.fine_wide_factors or float(np.mean(first.confidence)) > cfg.fine_wide_max_confidence:
            return first
        views = [_scaled_view(first.view, f) for f in cfg.fine_wide_factors]
        logits, pts, conf = self.fine_views(image, views)
        spacing_mm = pixel_spacing_mm or cfg.refine_assumed_spacing_mm
        shift_mm = np.linalg.norm(pts - first.landmarks_px, axis=-1).max(axis=-1) * spacing_mm
        starts = []
        for j in np.flatnonzero(shift_mm >= cfg.fine_wide_min_shift_mm):
            refit = self._refit(image, views[j], logits[j], pts[j], conf[j])
            if refit is not None:
                starts.append(refit[0])
        if accept is None:
            accept = _has_mask
        return self._surest(image, first, starts, accept=accept, what="second look")

    def off_free_end(
        self,
        image: np.ndarray,
        res: FineResult,
        final: Finished,
        finish: Callable[[np.ndarray], Finished],
        *,
        pixel_spacing_mm: float | None = None,
    ) -> Finished:
        """``final``, or the same with landmark A read again away from the free end of a tube.

        A is where the CM meets its shaft, so the tube goes on beyond it. Where A's fine confidence
        is at least ``free_end_min_confidence`` and the image has less tube around the final A
        outside the final mask than ``free_end_max_continuation``
        (:func:`~fluoronav.detection.evidence.end_continuation`), A is on a free end, such as the
        far end of a short shaft stub that the fine stage took for part of the CM; the heatmap of A
        then has a second mode where the CM meets that stub. The last pass's views go through the
        fine stage again with A's map excluded within one tube width of the fine A; ``finish``
        (refinement, centreline and patch-mask stages) runs from the new fine landmarks, and its
        result replaces ``final`` where the new A lies on the fine mask, a quarter of a tube width or
        more short of B along the line from the free end to B (the stub's end, A and B lie in this
        order; the CM's tip goes on beyond B, as a shaft does beyond A), and has more tube than that
        fraction around it. B's fine landmark, the fine mask and the confidences stay.
        ``pixel_spacing_mm`` (mm per input pixel, where known) lets finer images be binned for the
        measure.
        """
        cfg = self.config
        pts, mask = final.landmarks_px, final.mask
        if float(res.confidence[0]) < cfg.free_end_min_confidence:
            return final
        c = end_continuation(image, mask, pts[0], pixel_spacing_mm=pixel_spacing_mm)
        if c is None or c >= cfg.free_end_max_continuation:
            return final
        width_px = local_tube_width_px(mask, pts[0])
        assert width_px is not None  # end_continuation is None for an empty mask
        fine_a = res.landmarks_px[0]
        views = [_scaled_view(res.view, f) for f in cfg.fine_scales]
        _, view_pts, _ = self.fine_views(image, views, exclude_disk=(0, fine_a, width_px))
        fine_pts = res.landmarks_px.copy()
        fine_pts[0] = np.median(view_pts[:, 0], axis=0)
        if _distances_to_mask(res.mask, fine_pts[:1])[0] > 1.0:
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
        if c_new is None or c_new <= cfg.free_end_max_continuation:
            logger.debug("A on a free end (continuation %.2f); no better place (%s)", c, c_new)
            return final
        moved = float(np.linalg.norm(other.landmarks_px[0] - pts[0]))
        logger.debug(
            "A on a free end (continuation %.2f): moved %.1f px (continuation %.2f)", c, moved, c_new
        )
        return other

    @torch.no_grad()
    def shaft_start(
        self,
        image: np.ndarray,
        mask: np.ndarray,
        centerline_px: np.ndarray,
        *,
        pixel_spacing_mm: float | None = None,
    ) -> tuple[int, np.ndarray] | None:
        """Where the shaft stage says the CM begins along a centreline (N, 2) (u, v) px from A to B,
        where that is ``shaft_cut_min_mm`` or more beyond A: the centreline's index and the fine
        ``mask`` (rows, cols) bool redrawn by the shaft stage along it; None where A is on the CM,
        or the stage cannot judge, or the model has no shaft stage or the check is off.

        The shaft stage (a tube-mask network trained with patches on the mounting shaft too) redraws
        the mask on the tube-mask stage's patches. It judges only where it sees the notched CM
        clearly in one patch at least (``shaft_min_cm_logit``, :func:`core_logits`); A is off the CM
        where most of the centreline's first ``shaft_cut_run_mm`` (mm at the detector) lies outside
        its mask, and the CM begins at the centreline's first stretch of that length wholly inside
        (:func:`cm_start_index`)."""
        cfg, net = self.config, self.net.shaft
        if net is None or cfg.shaft_cut_min_mm <= 0.0:
            return None
        spacing_mm = pixel_spacing_mm or cfg.refine_assumed_spacing_mm
        step = cfg.refine_step_px(pixel_spacing_mm)
        line = np.asarray(centerline_px, dtype=np.float64)
        frames = tube_frames(line, step_px=step, shape=cfg.ends_shape, spacing_px=cfg.tube_spacing_px * step)
        if not frames:
            return None
        logits = self._patch_logits(net, image, frames)
        if core_logits(logits, band_px=cfg.tube_band_px).max() < cfg.shaft_min_cm_logit:
            return None  # the stage does not see the notched CM clearly anywhere: it cannot judge
        cm = tube_paste(mask, frames, logits, band_px=cfg.tube_band_px)
        run_px = cfg.shaft_cut_run_mm / spacing_mm
        inside, arc = along_centerline(line, cm)
        if float(inside[arc < run_px].mean()) >= 0.5:  # the CM begins at A
            return None
        start = cm_start_index(line, cm, run_px=run_px)
        if start is None or arc[start] * spacing_mm < cfg.shaft_cut_min_mm:
            return None
        return start, cm

    def off_shaft(
        self,
        image: np.ndarray,
        res: FineResult,
        final: Finished,
        finish: Callable[[np.ndarray], Finished],
        *,
        pixel_spacing_mm: float | None = None,
    ) -> Finished:
        """``final``, or the same with landmark A read again where the shaft stage's CM begins.

        Where :meth:`shaft_start` finds the CM beginning well beyond A along the final centreline, the
        fine stage took a plain stretch of shaft for part of the CM and put A on the shaft. The fine
        stage's last pass then runs again on a ROI fitted to the rest of the CM (the component of
        the fine mask, less what the shaft stage left out, that holds B) and B; its A is taken where
        it lies on that rest, no more than 2 mm before the cut along the centreline, else the
        centreline's point where the CM begins. ``finish`` (refinement, centreline and patch-mask
        stages) runs from there, B's fine landmark staying; the pixels of the fine mask that the shaft
        stage left out stay out of the final mask, which keeps the components that hold the
        landmarks. Unchanged without a shaft stage."""
        found = self.shaft_start(image, res.mask, final.centerline_px, pixel_spacing_mm=pixel_spacing_mm)
        if found is None:
            return final
        start, cm = found
        cfg = self.config
        spacing_mm = pixel_spacing_mm or cfg.refine_assumed_spacing_mm
        line = np.asarray(final.centerline_px, dtype=np.float64)
        _, arc = along_centerline(line, cm)
        fine_pts = res.landmarks_px.copy()
        fine_pts[0] = line[start]
        rest = _component_at(res.mask & cm, fine_pts[1:])
        if rest.any():
            # the fine stage sees the CM without the shaft: it places A where the notches begin
            vv, uu = np.nonzero(rest)
            corners = np.array([[uu.min() - 0.5, vv.min() - 0.5], [uu.max() + 0.5, vv.max() + 0.5]])
            roi = roi_view(
                np.concatenate([corners, fine_pts[1:]]),
                cfg.roi_size,
                margin_frac=cfg.roi_margin_frac,
                min_side_px=cfg.roi_min_side_px,
            )
            _, view_pts, _ = self.fine_views(image, [_scaled_view(roi, f) for f in cfg.fine_scales])
            a_new = np.median(view_pts[:, 0], axis=0)
            at = int(np.argmin(np.linalg.norm(line - a_new, axis=1)))
            if _distances_to_mask(rest, a_new[None])[0] <= 2.0 and arc[at] >= arc[start] - 2.0 / spacing_mm:
                fine_pts[0] = a_new
        logger.debug("A on the shaft: %.1f mm of the centreline not CM", arc[start] * spacing_mm)
        other = finish(fine_pts)
        # the shaft's end beyond the old A, outside every band, is left apart from the CM: dropped
        kept = _component_at(other.mask & ~(res.mask & ~cm), other.landmarks_px)
        return other._replace(mask=kept)

    @torch.no_grad()
    def strip_probabilities(
        self, image: np.ndarray, paths_px: list[np.ndarray], *, pixel_spacing_mm: float | None = None
    ) -> np.ndarray:
        """The strip stage's probabilities (P, cols + 1) of A at each column of each path (N, 2) (u,
        v) input px, the last of A on none of its columns (:func:`~fluoronav.detection.strip.
        strip_log_probs`; one batch). Raises ValueError where the model has no strip stage."""
        net, cfg = self.net.strip, self.config
        if net is None:
            raise ValueError("the model has no strip stage (strip_channels)")
        strips, valid = path_strips(
            image, paths_px, step_px=cfg.refine_step_px(pixel_spacing_mm), shape=cfg.strip_shape
        )
        x = torch.from_numpy(strips)[:, None].to(self.device)
        with self._autocast(net):
            logits = net(x)
        return strip_log_probs(logits, torch.from_numpy(valid).to(self.device)).exp().cpu().numpy()

    def off_apex(
        self,
        image: np.ndarray,
        res: FineResult,
        final: Finished,
        finish: Callable[[np.ndarray], Finished],
        *,
        pixel_spacing_mm: float | None = None,
    ) -> Finished:
        """``final``, or the same with landmark A moved to the apex of a V-shaped final mask.

        Where A's fine confidence is under ``apex_max_confidence`` and the final mask's farthest
        pixel from the segment A–B lies more than ``apex_min_offset_mm`` from it, the mask may be a
        foreshortened shaft stub and the CM meeting at a corner, A taken at the stub's far end
        (:mod:`fluoronav.detection.strip`). The strip stage then reads two paths: the detection's
        own centreline and A → apex (:func:`~fluoronav.detection.strip.v_apex`) → B. A moves to the
        apex where the first gives A within ± ``apex_window_mm`` of its start a probability under
        ``apex_start_max_prob``, the second gives A at its start (the same A) one under
        ``apex_path_start_max_prob`` and A within ± ``apex_window_mm`` of the apex one over
        ``apex_min_prob`` and over that at its start; ``finish`` runs from there, B's fine landmark
        staying. Unchanged without a strip stage."""
        cfg = self.config
        if self.net.strip is None or float(res.confidence[0]) >= cfg.apex_max_confidence:
            return final
        spacing_mm = pixel_spacing_mm or cfg.refine_assumed_spacing_mm
        a, b = final.landmarks_px
        found = v_apex(final.mask, a, b)
        if found is None or found[1] * spacing_mm <= cfg.apex_min_offset_mm:
            return final
        apex = found[0]
        step_px = cfg.refine_step_px(pixel_spacing_mm)
        paths = [np.asarray(final.centerline_px), np.stack([a, apex, b])]
        probs = self.strip_probabilities(image, paths, pixel_spacing_mm=pixel_spacing_mm)
        half = max(round(cfg.apex_window_mm / cfg.refine_step_mm), 1)
        at_start = window_probability(probs[0], 0.0, half)
        apex_start = window_probability(probs[1], 0.0, half)
        apex_col = float(np.linalg.norm(apex - a)) / step_px
        # an apex near the strip's far end is read from a truncated neighbourhood: no evidence
        at_apex = window_probability(probs[1], apex_col, half) if apex_col < cfg.strip_shape[1] - 4 else 0.0
        if not (
            at_start < cfg.apex_start_max_prob
            and apex_start < cfg.apex_path_start_max_prob
            and at_apex > max(cfg.apex_min_prob, apex_start)
        ):
            return final
        logger.debug("A at the V's apex: P(start) %.2f / %.2f, P(apex) %.2f", at_start, apex_start, at_apex)
        fine_pts = res.landmarks_px.copy()
        fine_pts[0] = apex
        return finish(fine_pts)

    def fine_stage(self, image: np.ndarray, view: View) -> FineResult:
        """All fine passes from a first ROI: landmarks (2, 2) in input px, confidences (2,), the mask
        (rows, cols) bool at the input size and the last pass's ROI (at scale 1).

        Each pass but the last refits the ROI to its result; the last runs on the ROI scaled by each of
        ``fine_scales`` in one batch (median landmarks and confidences, mean logits), with
        ``fine_sure_tta`` transforms where the pass before it was sure of both landmarks. While a pass's mask
        reaches the edge of its ROI inside the image (the CM goes on beyond it: the coarse stage found
        only part of it), passes are added, up to ``fine_max_passes`` in all, each on a ROI refitted
        to the larger mask.
        """
        cfg = self.config
        thr_logit = cfg.mask_threshold_logit
        first_tta = cfg.fine_tta if cfg.fine_first_tta is None else cfg.fine_first_tta
        spare = max(cfg.fine_max_passes - max(cfg.fine_passes, 1), 0)
        remaining = max(cfg.fine_passes, 1) - 1  # single passes before the last
        sure = False  # whether the pass before the last was sure of both landmarks
        while remaining > 0:
            f_logit, f_pts, f_conf = self.fine(image, view, tta=first_tta)
            sure = bool(np.all(f_conf >= cfg.fine_sure_confidence))
            refit = self._refit(image, view, f_logit, f_pts, f_conf)
            if refit is None:
                break
            view, reached = refit
            remaining -= 1
            if reached and spare > 0:
                spare, remaining = spare - 1, remaining + 1
        while True:
            views = [_scaled_view(view, f) for f in cfg.fine_scales]
            tta = cfg.fine_sure_tta if sure else None  # None: fine_tta
            logits, pts, confs = self.fine_views(image, views, tta=tta)
            f_pts, f_conf = np.median(pts, axis=0), np.median(confs, axis=0)
            if spare > 0:
                # the view of the scale nearest 1 decides whether the CM goes on beyond the ROI
                k = int(np.argmin([abs(f - 1.0) for f in cfg.fine_scales]))
                refit = self._refit(image, views[k], logits[k], pts[k], confs[k])
                if refit is not None and refit[1]:
                    spare -= 1
                    view = refit[0]
                    sure = bool(np.all(f_conf >= cfg.fine_sure_confidence))
                    continue
            mask = self._mask_at_input(
                logits, views, image.shape, thr_logit, f_pts, join_frac=cfg.mask_join_frac
            )
            return FineResult(f_pts, f_conf, mask, view)

    def _refit(
        self, image: np.ndarray, view: View, logit: np.ndarray, pts: np.ndarray, conf: np.ndarray
    ) -> tuple[View, bool] | None:
        """The ROI fitted to one pass's result (seg logit (R, R), landmarks (2, 2) input px,
        confidences (2,)) and whether its mask reached the old ROI's edge; None if the mask is empty."""
        cfg = self.config
        roi_mask = logit > cfg.mask_threshold_logit
        if not roi_mask.any():
            return None
        sure = pts[conf >= cfg.min_confidence]
        component = _component_at(roi_mask, view.from_input(sure))
        # again on a ROI fitted to this pass's result: its scale matches training more closely
        return self._roi(view, component, sure), _reaches_edge(component, view, image.shape)

    def _roi(self, view: View, view_mask: np.ndarray, landmarks_input: np.ndarray) -> View:
        """Fine-stage ROI around a mask in ``view`` pixels and landmarks (N, 2) in input pixels."""
        vv, uu = np.nonzero(view_mask)
        corners = view.to_input(
            np.array([[uu.min() - 0.5, vv.min() - 0.5], [uu.max() + 0.5, vv.max() + 0.5]])
        )
        cfg = self.config
        return roi_view(
            np.concatenate([corners, np.asarray(landmarks_input).reshape(-1, 2)]),
            cfg.roi_size,
            margin_frac=cfg.roi_margin_frac,
            min_side_px=cfg.roi_min_side_px,
        )

    @staticmethod
    def _mask_at_input(
        logits: np.ndarray,
        views: list[View],
        shape: tuple[int, int],
        thr_logit: float,
        landmarks_px: np.ndarray,
        *,
        join_frac: float = 0.0,
    ) -> np.ndarray:
        """Threshold the mean of the views' logits (N, R, R) bilinearly mapped to the input grid; keep
        the largest component and, with ``join_frac`` > 0, the fragments along the landmarks (2, 2)
        (:func:`_cm_components`). Outside a view its logits count as certain background."""
        rows, cols = shape
        out = np.zeros(shape, dtype=bool)
        # the union of the views, clipped to the image: the only place the mask can be
        cx0, cy0 = max(min(v.x0 for v in views), 0), max(min(v.y0 for v in views), 0)
        cx1 = min(max(v.x0 + v.side for v in views), cols)
        cy1 = min(max(v.y0 + v.side for v in views), rows)
        if cx1 <= cx0 or cy1 <= cy0:
            return out
        acc = np.zeros((cy1 - cy0, cx1 - cx0), np.float32)
        for logit, v in zip(logits, views, strict=True):
            acc += paste(logit, v, (rows, cols), fill=_OUTSIDE_LOGIT, box=(cx0, cy0, cx1, cy1))
        sub = acc / len(views) > thr_logit
        if sub.any():
            local = np.asarray(landmarks_px, dtype=np.float64) - np.array([cx0, cy0], dtype=np.float64)
            out[cy0:cy1, cx0:cx1] = _cm_components(sub, local, join_frac=join_frac)
        return out


def off_support_exclusion(
    seg_logits: torch.Tensor, heatmaps: torch.Tensor, *, threshold_logit: float, support_px: float
) -> torch.Tensor:
    """Heatmap pixels a landmark may not take where its map peaks away from the CM's mask.

    A and B lie on the CM. The CM's region is the largest connected component of the view's
    thresholded mask grown by ``support_px``: pieces of one tube less than 2 · ``support_px`` apart
    (a thin part of the mask broken by noise) are one region, a blob farther away (noise, a bone
    edge) is not. A map whose argmax lies outside that region has every pixel outside it
    excluded, so the landmark is taken at its best peak on the CM, unless the other landmark lies in
    the region and the region runs towards this one (the median of its pixels' positions along the
    segment from the other landmark to this one is ≥ 0): then this is the far end of a tube the mask
    has cut in two, and it stays. Maps that peak in the region are left alone (no exclusion).

    Args:
        seg_logits: (N, S, S) segmentation logits.
        heatmaps: (N, K, S, S) landmark maps (only their argmax is read).
        threshold_logit: mask threshold on the logits.
        support_px: growth of the mask, view pixels (> 0).

    Returns:
        (N, K, S, S) bool, all False for a view without a mask.
    """
    n, k, _, cols = heatmaps.shape
    exclude = torch.zeros(heatmaps.shape, dtype=torch.bool)
    masks = (seg_logits > threshold_logit).cpu().numpy()
    idx = heatmaps.reshape(n, k, -1).argmax(dim=-1).cpu().numpy()
    for i in range(n):
        if not masks[i].any():
            continue
        grown = ndi.distance_transform_edt(~masks[i]) <= support_px
        _, labels, stats, _ = cv2.connectedComponentsWithStats(grown.astype(np.uint8), connectivity=8)
        largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        far = labels != largest
        off = far.reshape(-1)[idx[i]]  # (K,) maps peaking off the CM
        if k == 2 and off.sum() == 1:
            j = int(np.argmin(off))  # the landmark on the CM
            pj = np.array([idx[i, j] % cols, idx[i, j] // cols], dtype=np.float64)
            pk = np.array([idx[i, 1 - j] % cols, idx[i, 1 - j] // cols], dtype=np.float64)
            vv, uu = np.nonzero(~far)
            t = (np.stack([uu, vv], axis=1) - pj) @ (pk - pj)
            if float(np.median(t)) >= 0.0:
                off[:] = False
        if off.any():
            exclude[i, torch.from_numpy(off)] = torch.from_numpy(far)
    return exclude.to(heatmaps.device)


def core_logits(logits: np.ndarray, *, band_px: float, core_px: float = 8.0) -> np.ndarray:
    """(P,) mean logit of each tube-aligned patch's core: the pixels (P, rows, cols) within
    ``band_px`` patch px of its centre along the tube (cols) and ``core_px`` of its axis (rows)."""
    _, rows, cols = logits.shape
    along = np.abs(np.arange(cols) - (cols - 1) / 2.0) <= band_px
    across = np.abs(np.arange(rows) - (rows - 1) / 2.0) <= core_px
    return logits[:, across][:, :, along].mean(axis=(1, 2))


def along_centerline(centerline_px: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether each point of a centreline (N, 2) (u, v) px lies in ``mask`` (rows, cols) bool (nearest
    pixel; points outside the image count as outside), (N,) bool, and its arc length (N,) px."""
    line = np.asarray(centerline_px, dtype=np.float64).reshape(-1, 2)
    h, w = mask.shape
    iu, iv = np.rint(line[:, 0]).astype(int), np.rint(line[:, 1]).astype(int)
    ok = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
    inside = np.zeros(len(line), bool)
    inside[ok] = mask[iv[ok], iu[ok]]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    return inside, arc[: len(line)]


def cm_start_index(centerline_px: np.ndarray, mask: np.ndarray, *, run_px: float) -> int | None:
    """Index of the first point of a centreline (N, 2) (u, v) px from which it runs ``run_px`` px of
    arc length or more wholly inside ``mask`` (rows, cols) bool (:func:`along_centerline`); None
    where it never does."""
    inside, arc = along_centerline(centerline_px, mask)
    run_start: int | None = None
    for i, good in enumerate(inside):
        if not good:
            run_start = None
            continue
        run_start = i if run_start is None else run_start
        if arc[i] - arc[run_start] >= run_px:
            return run_start
    return None


def _distances_to_mask(mask: np.ndarray, points_px: np.ndarray) -> np.ndarray:
    """(N,) distances (px) from points (N, 2) (u, v) to the nearest pixel of a mask (inf for an
    empty mask); the mask's pixels are listed once for all the points."""
    vv, uu = np.nonzero(mask)
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    if vv.size == 0:
        return np.full(len(pts), np.inf)
    pixels = np.stack([uu, vv], axis=1).astype(np.float64)
    return np.sqrt(((pixels[None] - pts[:, None]) ** 2).sum(axis=-1)).min(axis=1)


def _has_mask(r: FineResult) -> bool:
    """The default acceptance of a second-look hypothesis: it has a mask."""
    return bool(r.mask.any())


def _cm_components(mask: np.ndarray, landmarks_px: np.ndarray, *, join_frac: float) -> np.ndarray:
    """The CM's part of a thresholded mask (rows, cols): its largest connected component and, with
    ``join_frac`` > 0, every other component that comes within max(3, ``join_frac`` · |AB|) pixels of
    the segment between the landmarks (2, 2) (u, v).

    Noise or a crossing bone can cut the mask of one tube into pieces; the pieces between its two
    ends belong to it, a blob elsewhere does not. The margin covers the bend of the CM away from the
    chord A–B (≲ 0.09 · |AB| at the sampled curvatures) and the tube's radius in end-on views.
    """
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:
        return mask.astype(bool)
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    if join_frac <= 0.0:
        return labels == largest
    a, b = np.asarray(landmarks_px, dtype=np.float64).reshape(2, 2)
    ab = b - a
    margin = max(3.0, join_frac * float(np.hypot(*ab)))
    vv, uu = np.nonzero(labels)
    p = np.stack([uu, vv], axis=1).astype(np.float64)
    t = np.clip((p - a) @ ab / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    near = np.hypot(*(p - (a + t[:, None] * ab)).T) <= margin
    keep = {largest, *np.unique(labels[vv[near], uu[near]]).tolist()}
    return np.isin(labels, sorted(keep))


#: logit given to input pixels outside a fine view when the views' logits are averaged
_OUTSIDE_LOGIT = -20.0


def _reaches_edge(view_mask: np.ndarray, view: View, shape: tuple[int, int], *, ring_px: int = 2) -> bool:
    """Whether a mask (S, S) in ``view`` pixels has pixels in the view's outer ring of ``ring_px``
    view pixels that lie inside the image ``shape`` (rows, cols) (not counting the image's own edge)."""
    ring = view_mask.copy()
    ring[ring_px:-ring_px, ring_px:-ring_px] = False
    vv, uu = np.nonzero(ring)
    if vv.size == 0:
        return False
    uv = view.to_input(np.stack([uu, vv], axis=1).astype(np.float64))
    rows, cols = shape
    inside = (uv[:, 0] >= 1.0) & (uv[:, 0] <= cols - 2.0) & (uv[:, 1] >= 1.0) & (uv[:, 1] <= rows - 2.0)
    return bool(inside.any())


def _scaled_view(view: View, factor: float) -> View:
    """The view with its side × ``factor`` about the same centre (same output size)."""
    side = max(round(view.side * factor), 2)
    return View(
        round(view.x0 + (view.side - side) / 2.0), round(view.y0 + (view.side - side) / 2.0), side, view.size
    )


def load_image(path: str | Path) -> tuple[np.ndarray, float | None]:
    """Read an image file as a float32 log image (bright = attenuating) and its pixel spacing (mm).

    See the module docstring for the conversion rules. Raises InputError for unreadable files.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    suffix = path.suffix.lower()
    spacing: float | None = None
    if suffix == ".npz":
        try:
            with np.load(path) as npz:
                if "image" not in npz.files:
                    raise InputError(path, f"no 'image' array (has {', '.join(npz.files) or 'nothing'})")
                arr = np.asarray(npz["image"])
                if "pixel_spacing_mm" in npz.files:
                    spacing = float(np.mean(npz["pixel_spacing_mm"]))
        except (OSError, ValueError, EOFError) as exc:
            raise InputError(path, f"unreadable .npz ({exc.__class__.__name__})") from exc
    elif suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise InputError(path, f"unreadable .npy ({exc.__class__.__name__})") from exc
    elif suffix in (".png", ".tif", ".tiff", ".jpg", ".jpeg"):
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise InputError(path, "unreadable image file")
        if raw.ndim == 3:
            raw = (
                raw[..., :3].astype(np.float64).mean(axis=2).astype(raw.dtype)
                if raw.shape[2] >= 3
                else raw[..., 0]
            )
        if np.issubdtype(raw.dtype, np.integer):
            full = float(np.iinfo(raw.dtype).max)
            arr = -np.log((raw.astype(np.float64) + 1.0) / (full + 1.0))
        else:
            arr = raw
    else:
        arr, spacing = _load_dicom(path)
    return _check_image(arr, str(path)), spacing


def _load_dicom(path: Path) -> tuple[np.ndarray, float | None]:
    import SimpleITK as sitk  # noqa: N813

    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    try:
        reader.ReadImageInformation()
        img = reader.Execute()
    except RuntimeError as exc:
        raise InputError(path, "unreadable image (not a DICOM or other format SimpleITK reads)") from exc
    arr = sitk.GetArrayFromImage(img).astype(np.float64)
    if arr.ndim == 3:
        if arr.shape[0] != 1:
            raise InputError(path, f"multi-frame image ({arr.shape[0]} frames); give one frame")
        arr = arr[0]

    def tag(key: str) -> str | None:
        return reader.GetMetaData(key).strip() if reader.HasMetaDataKey(key) else None

    if (tag("0028|0004") or "").upper() == "MONOCHROME1":
        arr = arr.max() - arr
    spacing = None
    for key in ("0018|1164", "0028|0030"):
        value = tag(key)
        if value:
            try:
                spacing = float(np.mean([float(x) for x in value.split("\\")]))
                break
            except ValueError:
                continue
    return arr, spacing


def detection_to_dict(det: Detection, mask_file: str) -> dict:
    """The contract JSON of a detection (see CONTRACTS.md, "Detection output")."""
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
