"""Torch data set over a ``fluoronav simulate`` directory (``manifest.jsonl`` + ``.npz`` samples).

Each item holds the two training views of one sample: the whole image at the coarse working
resolution and a region of interest around the CM at the fine resolution (see
:mod:`fluoronav.detection.localize`), each with its soft mask target and landmarks in view pixels
(``u' = (u − x0 + 0.5)/s − 0.5``). Negatives (no CM: empty mask or no landmarks) have NaN landmarks,
which give all-zero heatmap targets, and a random ROI. The train/val split is a deterministic function
of each sample's id (SHA-1), so it does not depend on the order or size of the manifest.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from fluoronav.detection.centerline import extract_centerline
from fluoronav.detection.config import DetectorConfig, RoiSampler, WholeViewSampler
from fluoronav.detection.training.augment import (
    AugmentConfig,
    augment_geometric,
    augment_photometric,
    collimation_window,
    edge_point,
    lower_dose,
)
from fluoronav.detection.training.patches import (
    EndJitter,
    RefineJitter,
    training_end_patch,
    training_patch,
    training_tube_patch,
)
from fluoronav.detection.views import View, full_view, normalize_intensity, resample, roi_view
from fluoronav.errors import InputError
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.projection import project_cm_points, shaft_ends_cm

logger = logging.getLogger(__name__)

#: in-memory image cache budget (bytes); larger data sets are read from disk every time
CACHE_BUDGET_BYTES = 4 * 1024**3


def read_manifest(root: str | Path) -> list[dict]:
    """The sample records of a data set directory, in file order (last record wins per id)."""
    root = Path(root)
    path = root / "manifest.jsonl"
    if not path.is_file():
        raise InputError(root, "not a data set directory (no manifest.jsonl)")
    records: dict[str, dict] = {}
    with open(path, encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, 1):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                # a crash while writing leaves at most a truncated last line
                logger.warning("%s:%d: skipping a line that is not JSON", path, lineno)
                continue
            if "id" not in rec or "file" not in rec:
                raise InputError(path, f"line {lineno} lacks 'id' or 'file'")
            records[str(rec["id"])] = rec
    if not records:
        raise InputError(path, "no samples")
    return list(records.values())


def split_of(sample_id: str, val_fraction: float) -> str:
    """``"val"`` for a deterministic ``val_fraction`` of ids (by SHA-1), else ``"train"``."""
    h = int.from_bytes(hashlib.sha1(str(sample_id).encode()).digest()[:8], "big") / 2.0**64
    return "val" if h < val_fraction else "train"


def pixel_spacing_of(record: dict) -> float | None:
    """Detector pixel spacing (mm) of a manifest record (mean of a pair), or None."""
    ps = record.get("pixel_spacing_mm")
    if ps is None:
        return None
    return float(np.mean(np.asarray(ps, dtype=np.float64)))


def _recorded(root: str | Path, section: str, key: str) -> object:
    """``root/dataset.json``'s ``section.key`` (as ``simulate`` writes it), or None where unrecorded."""
    path = Path(root) / "dataset.json"
    try:
        return json.loads(path.read_text(encoding="utf-8")).get(section, {}).get(key)
    except (OSError, json.JSONDecodeError, AttributeError):
        return None


def photons_per_pixel_of(root: str | Path) -> float | None:
    """Flat-field photons per stored pixel recorded in ``root/dataset.json`` (``simulate`` writes
    ``storage.photons_per_pixel``), or None (no record, or noise-free)."""
    value = _recorded(root, "storage", "photons_per_pixel")
    return float(value) if isinstance(value, (int, float)) and value > 0 else None


def shaft_length_of(root: str | Path) -> float:
    """Length (mm) of the CM's mounting shaft recorded in ``root/dataset.json`` (``spec.shaft_length_mm``;
    0: the bare CM), else 50 mm, ``simulate``'s default and the length of every set made before the
    option."""
    value = _recorded(root, "spec", "shaft_length_mm")
    return float(value) if isinstance(value, (int, float)) and value >= 0 else 50.0


def shaft_segment_px(record: dict, shaft_length_mm: float) -> np.ndarray | None:
    """The projected mounting shaft of a manifest record: (2, 2) (u, v) stored px of A and of the
    shaft's far end, ``shaft_length_mm`` behind A along −z of the CM's frame. None where the record
    lacks the camera or the pose ``world_from_cm``, or ``shaft_length_mm`` is not positive."""
    if not shaft_length_mm > 0.0 or record.get("camera") is None or record.get("world_from_cm") is None:
        return None
    try:
        camera = Camera.from_dict(record["camera"], source=f"sample {record.get('id')}")
        world_from_cm = np.asarray(record["world_from_cm"], dtype=np.float64)
    except (InputError, TypeError, ValueError):
        return None
    if world_from_cm.shape != (4, 4):
        return None
    return project_cm_points(camera, world_from_cm, shaft_ends_cm(shaft_length_mm))


@dataclass(frozen=True)
class Sample:
    """One stored sample: image (rows, cols) float32, mask (rows, cols) bool, landmarks (2, 2) or None."""

    id: str
    image: np.ndarray
    mask: np.ndarray
    landmarks_px: np.ndarray | None
    pixel_spacing_mm: float | None


def load_sample(root: str | Path, record: dict) -> Sample:
    """Read one sample's ``.npz``; landmarks from the file, else from the manifest record."""
    path = Path(root) / record["file"]
    try:
        with np.load(path) as npz:
            image = np.asarray(npz["image"], dtype=np.float32)
            mask = np.asarray(npz["mask"]) > 0 if "mask" in npz.files else np.zeros(image.shape, bool)
            lm = np.asarray(npz["landmarks_px"], dtype=np.float64) if "landmarks_px" in npz.files else None
    except (OSError, ValueError, KeyError, EOFError) as exc:
        raise InputError(path, f"unreadable sample ({exc})") from exc
    if image.ndim != 2 or mask.shape != image.shape:
        raise InputError(path, f"image {image.shape} and mask {mask.shape} must be equal 2-D shapes")
    if lm is None and record.get("landmarks_px") is not None:
        lm = np.asarray(record["landmarks_px"], dtype=np.float64)
    if lm is not None and (lm.shape != (2, 2) or not np.all(np.isfinite(lm))):
        lm = None
    if lm is None or not mask.any():  # a negative: no CM visible
        lm = None
    return Sample(str(record["id"]), image, mask, lm, pixel_spacing_of(record))


def _cm_extent_points(mask: np.ndarray, landmarks_px: np.ndarray) -> np.ndarray:
    """The points (4, 2) (u, v) that a view of the CM must contain: its mask's bounding-box corners
    and the two landmarks."""
    vv, uu = np.nonzero(mask)
    corners = np.array([[uu.min(), vv.min()], [uu.max(), vv.max()]], dtype=np.float64)
    return np.concatenate([corners, landmarks_px])


def partial_cm_points(
    mask: np.ndarray,
    landmarks_px: np.ndarray,
    rng: np.random.Generator,
    *,
    frac_range: tuple[float, float] = (0.35, 0.75),
) -> np.ndarray:
    """Points (N, 2) (u, v) that a view of part of the CM must contain: the bounding-box corners of
    the mask pixels whose projection on the CM's axis falls within a fraction (uniform in
    ``frac_range``) of its length at the A or the B end (equally likely), and that end's landmark.

    The axis is A → B, or the mask's principal axis where A and B are under 4 px apart (end-on).
    """
    vv, uu = np.nonzero(mask)
    p = np.stack([uu, vv], axis=1).astype(np.float64)
    a, b = np.asarray(landmarks_px, dtype=np.float64).reshape(2, 2)
    axis = b - a
    if float(np.hypot(*axis)) < 4.0:
        centred = p - p.mean(axis=0)
        axis = np.linalg.eigh(centred.T @ centred)[1][:, -1]
    t = (p - a) @ (axis / max(float(np.hypot(*axis)), 1e-9))
    t0, t1 = float(t.min()), float(t.max())
    span = float(rng.uniform(*frac_range)) * (t1 - t0)
    from_a = bool(rng.random() < 0.5)
    keep = t <= t0 + span if from_a else t >= t1 - span
    part = p[keep]
    corners = np.array([part.min(axis=0), part.max(axis=0)])
    return np.concatenate([corners, (a if from_a else b)[None]])


def fine_view_for(
    sample: Sample,
    config: DetectorConfig,
    rng: np.random.Generator | None,
    *,
    augment: AugmentConfig | None = None,
) -> View:
    """The ROI of a sample: around its mask and landmarks (jittered when ``rng`` is given; with
    probability ``augment.p_partial_roi`` around a part of the CM, :func:`partial_cm_points`); a
    random window for negatives (with probability ``augment.p_edge_negative_roi`` centred on a strong
    edge, :func:`~fluoronav.detection.training.augment.edge_point`)."""
    sampler = config.fine.sampler
    rows, cols = sample.image.shape
    if sample.landmarks_px is None:
        r = rng if rng is not None else np.random.default_rng(0)
        side = float(r.uniform(0.1, 0.5)) * max(rows, cols)
        centre = r.uniform([0, 0], [cols, rows])
        # no extra draw when off (short-circuit): the draws are those of a run without the option
        p_edge = augment.p_edge_negative_roi if augment is not None and rng is not None else 0.0
        if augment is not None and p_edge > 0.0 and r.random() < p_edge:
            centre = edge_point(sample.image, r, quantile=augment.edge_quantile)
        return roi_view(centre[None], sampler.size, margin_frac=0.0, min_side_px=max(side, 2.0))
    pts = _cm_extent_points(sample.mask, sample.landmarks_px)
    if rng is None:
        return roi_view(pts, sampler.size, margin_frac=sampler.margin_frac, min_side_px=sampler.min_side_px)
    # log-uniform ×0.8–2: the first fine pass at inference may get a loose ROI from the coarse stage
    max_scale = 2.0
    if augment is not None and augment.p_partial_roi > 0.0 and rng.random() < augment.p_partial_roi:
        pts = partial_cm_points(sample.mask, sample.landmarks_px, rng, frac_range=augment.partial_frac)
        max_scale = 1.5  # a coarse stage that found part of a CM fits its ROI to that part
    return roi_view(
        pts,
        sampler.size,
        margin_frac=sampler.margin_frac,
        min_side_px=sampler.min_side_px,
        scale_factor=float(np.exp(rng.uniform(np.log(0.8), np.log(max_scale)))),
        shift_frac=tuple(rng.uniform(-0.1, 0.1, size=2)),
    )


def crop_sample(sample: Sample, window: tuple[int, int, int, int]) -> Sample:
    """The sample inside ``window`` (x0, y0, x1, y1) in pixels: image, mask and landmarks moved.
    A sample whose CM leaves no mask pixel in the window becomes a negative."""
    x0, y0, x1, y1 = window
    mask = sample.mask[y0:y1, x0:x1]
    lm = None
    if sample.landmarks_px is not None and mask.any():
        lm = sample.landmarks_px - np.array([x0, y0], dtype=np.float64)
    return dataclasses.replace(sample, image=sample.image[y0:y1, x0:x1], mask=mask, landmarks_px=lm)


def collimate(
    sample: Sample, rng: np.random.Generator, *, min_field_frac: float, max_field_frac: float = 1.0
) -> Sample:
    """The sample cropped to a random collimated field of view that keeps its whole CM
    (:func:`~fluoronav.detection.training.augment.collimation_window`)."""
    box = None
    if sample.landmarks_px is not None:
        pts = _cm_extent_points(sample.mask, sample.landmarks_px)
        box = (*pts.min(axis=0), *pts.max(axis=0))
    window = collimation_window(
        rng, sample.image.shape, box, min_field_frac=min_field_frac, max_field_frac=max_field_frac
    )
    return crop_sample(sample, window)


def make_view(
    sample: Sample,
    view: View,
    sampler: WholeViewSampler | RoiSampler,
    *,
    rng: np.random.Generator | None = None,
    augment: AugmentConfig | None = None,
    photons_per_pixel: float | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normalised image (S, S), soft mask (S, S) and landmarks (2, 2) (NaN if absent) in view pixels.

    ``sampler``: the stage's view settings (its intensity normalisation). ``photons_per_pixel`` (the
    data set's flat-field photons per stored pixel) enables the low-dose augmentation, applied to
    the window at the stored pixels before it is resampled.
    """
    if (
        augment is not None
        and rng is not None
        and photons_per_pixel is not None
        and rng.random() < augment.p_low_dose
    ):
        window = resample(sample.image, View(view.x0, view.y0, view.side, view.side))
        f = float(np.exp(rng.uniform(np.log(augment.min_dose_fraction), 0.0)))
        window = lower_dose(rng, window, photons_per_pixel=photons_per_pixel, dose_fraction=f)
        raw = resample(window, View(0, 0, view.side, view.size))
    else:
        raw = resample(sample.image, view)
    image = normalize_intensity(raw, low_pct=sampler.low_pct, high_pct=sampler.high_pct)
    mask = resample(sample.mask.astype(np.float32), view)
    lm = None if sample.landmarks_px is None else view.from_input(sample.landmarks_px)
    if augment is not None and rng is not None:
        image, mask, lm = augment_geometric(rng, image, mask, lm, augment)
        image = augment_photometric(rng, image, augment)
    lm_out = np.full((2, 2), np.nan) if lm is None else lm
    return image.astype(np.float32), np.clip(mask, 0.0, 1.0).astype(np.float32), lm_out.astype(np.float32)


class CMDetectionDataset(Dataset):
    """Training/validation items of a simulate data set.

    Args:
        root: data set directory.
        config: detector configuration (working resolutions, ROI margin).
        split: ``"train"``, ``"val"`` or ``"all"``.
        val_fraction: fraction of ids in the validation split.
        augment: augmentation ranges, or None for none (validation).
        seed: base seed; item i of epoch e uses ``Generator([seed, e, i])``.
        cache: keep decoded samples in memory (default: when they fit in ``CACHE_BUDGET_BYTES``).
    """

    def __init__(
        self,
        root: str | Path,
        *,
        config: DetectorConfig,
        split: str = "train",
        val_fraction: float = 1 / 11,
        augment: AugmentConfig | None = None,
        seed: int = 0,
        cache: bool | None = None,
    ) -> None:
        if split not in ("train", "val", "all"):
            raise ValueError(f"unknown split {split!r}")
        self.root = Path(root)
        self.config = config
        self.augment = augment
        self.seed = int(seed)
        self.epoch = 0
        records = read_manifest(self.root)
        self.records = [r for r in records if split == "all" or split_of(str(r["id"]), val_fraction) == split]
        if cache is None:
            pixels = sum(int(r.get("rows", 0)) * int(r.get("cols", 0)) for r in self.records)
            cache = 0 < pixels * 5 <= CACHE_BUDGET_BYTES
        self._cache: dict[int, Sample] | None = {} if cache else None
        self.photons_per_pixel = photons_per_pixel_of(self.root)

    def __len__(self) -> int:
        return len(self.records)

    def set_epoch(self, epoch: int) -> None:
        """Select the augmentation draws of an epoch (deterministic per epoch and item)."""
        self.epoch = int(epoch)

    def sample(self, index: int) -> Sample:
        if self._cache is not None and index in self._cache:
            return self._cache[index]
        s = load_sample(self.root, self.records[index])
        if self._cache is not None:
            self._cache[index] = s
        return s

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        s = self.sample(index)
        rng = np.random.default_rng([self.seed, self.epoch, index]) if self.augment is not None else None
        if rng is not None and self.augment is not None and rng.random() < self.augment.p_collimate:
            s = collimate(s, rng, min_field_frac=self.augment.min_field_frac)
        coarse, fine = self.config.coarse.sampler, self.config.fine.sampler
        cv = full_view(s.image.shape, coarse.size)
        fv = fine_view_for(s, self.config, rng, augment=self.augment)
        n0 = self.photons_per_pixel
        ci, cm, cl = make_view(s, cv, coarse, rng=rng, augment=self.augment, photons_per_pixel=n0)
        fi, fm, fl = make_view(s, fv, fine, rng=rng, augment=self.augment, photons_per_pixel=n0)
        return {
            "coarse_image": torch.from_numpy(ci)[None],
            "coarse_mask": torch.from_numpy(cm)[None],
            "coarse_landmarks": torch.from_numpy(cl),
            "fine_image": torch.from_numpy(fi)[None],
            "fine_mask": torch.from_numpy(fm)[None],
            "fine_landmarks": torch.from_numpy(fl),
            "coarse_scale": torch.tensor(cv.scale, dtype=torch.float64),
            "fine_view": torch.tensor([fv.x0, fv.y0, fv.side, fv.size], dtype=torch.float64),
            "positive": torch.tensor(s.landmarks_px is not None),
            "index": torch.tensor(index),
        }


class _PatchDataset(CMDetectionDataset):
    """Items of a patch stage: each sample ``repeats`` times per epoch, each time with its own draws
    (:meth:`_draw`)."""

    def __init__(self, root: str | Path, *, repeats: int = 1, **kw: object) -> None:
        super().__init__(root, **kw)  # type: ignore[arg-type]
        self.repeats = int(repeats)

    def __len__(self) -> int:
        return len(self.records) * self.repeats

    def _draw(self, index: int) -> tuple[Sample, bool, np.random.Generator]:
        """Item ``index``'s sample, whether it is a training item (augmented), and its generator: new
        draws every training epoch, the same every epoch for validation."""
        train = self.augment is not None
        rng = np.random.default_rng([self.seed, self.epoch if train else 0, index])
        return self.sample(index % len(self.records)), train, rng


class RefineDataset(_PatchDataset):
    """Training/validation items of the landmark refinement stage: each sample ``repeats`` times per
    epoch, each time with a patch around A and one around B, placed as the fine stage would miss them
    (:func:`~fluoronav.detection.training.patches.training_patch`). Validation items have the same jitter
    every epoch and no photometric augmentation.

    Items: ``refine_image`` (2, 1, rows, cols), ``refine_landmarks`` (2, 2) (col, row) patch pixels,
    NaN for a landmark without a patch (negatives; a CM whose mask gives no direction).
    """

    def __init__(
        self, root: str | Path, *, repeats: int = 1, jitter: RefineJitter | None = None, **kw: object
    ) -> None:
        super().__init__(root, repeats=repeats, **kw)
        if self.config.refine is None:
            raise ValueError("the model configuration has no refinement stage (refine)")
        self.refine = self.config.refine
        self.jitter = jitter or RefineJitter()

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        s, train, rng = self._draw(index)
        sampler = self.refine.sampler
        images = np.zeros((2, 1, *sampler.shape), np.float32)
        targets = np.full((2, 2), np.nan, np.float32)
        if s.landmarks_px is not None:
            step = sampler.step_px(s.pixel_spacing_mm, self.config.assumed_spacing_mm)
            for k in (0, 1):
                got = training_patch(
                    s.image,
                    s.mask,
                    s.landmarks_px[k],
                    rng,
                    step_px=step,
                    shape=sampler.shape,
                    jitter=self.jitter,
                    photometric=train,
                )
                if got is not None:
                    images[k, 0], targets[k] = got
        return {"refine_image": torch.from_numpy(images), "refine_landmarks": torch.from_numpy(targets)}


class EndsDataset(_PatchDataset):
    """Training/validation items of a patch-mask stage: for the mask-end stage (``stage="ends"``)
    each sample ``repeats`` times per epoch, each time with a patch around A and one around B,
    placed as the refined landmarks would miss them
    (:func:`~fluoronav.detection.training.patches.training_end_patch`); for the tube-mask and shaft
    stages (``"tube"``, ``"shaft"``) two patches centred at random points of the true centreline, or
    with probability ``shaft_prob`` of the projected mounting shaft
    (:func:`~fluoronav.detection.training.patches.training_tube_patch`). The patches are the
    stage's (its sampler's shape and scale). Validation items have the same jitter every epoch and
    no photometric augmentation.

    Items: ``ends_image`` (2, 1, rows, cols), ``ends_mask`` (2, 1, rows, cols) the true mask on the
    patch, ``ends_valid`` (2,) 1 where the patch exists (0: negatives; a mask without a direction).
    """

    def __init__(
        self,
        root: str | Path,
        *,
        repeats: int = 1,
        jitter: EndJitter | None = None,
        stage: str = "ends",
        shaft_prob: float = 0.0,
        **kw: object,
    ) -> None:
        super().__init__(root, repeats=repeats, **kw)
        if stage not in ("ends", "tube", "shaft"):
            raise ValueError(f"stage must be 'ends', 'tube' or 'shaft', got {stage!r}")
        settings = getattr(self.config, stage)
        if settings is None:
            raise ValueError(f"the model configuration has no {stage} stage")
        self.sampler = settings.sampler
        self.jitter = jitter or EndJitter()
        self.tube = stage != "ends"
        self.shaft_prob = float(shaft_prob) if self.tube else 0.0
        self.shaft_length_mm = shaft_length_of(self.root)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        s, train, rng = self._draw(index)
        shape = self.sampler.shape
        images = np.zeros((2, 1, *shape), np.float32)
        masks = np.zeros((2, 1, *shape), np.float32)
        valid = np.zeros(2, np.float32)
        if s.landmarks_px is not None:
            step = self.sampler.step_px(s.pixel_spacing_mm, self.config.assumed_spacing_mm)
            line = extract_centerline(s.mask > 0, s.landmarks_px[0], s.landmarks_px[1]) if self.tube else None
            shaft = (
                shaft_segment_px(self.records[index % len(self.records)], self.shaft_length_mm)
                if self.shaft_prob > 0.0
                else None
            )
            for k in (0, 1):
                # the tube-mask stage's patches lie on the centreline (or the shaft), the mask-end
                # stage's on A and B
                if line is not None:
                    got = training_tube_patch(
                        s.image,
                        s.mask,
                        line,
                        rng,
                        step_px=step,
                        shape=shape,
                        jitter=self.jitter,
                        photometric=train,
                        shaft_px=shaft,
                        shaft_prob=self.shaft_prob,
                    )
                else:
                    got = training_end_patch(
                        s.image,
                        s.mask,
                        s.landmarks_px[k],
                        rng,
                        step_px=step,
                        shape=shape,
                        jitter=self.jitter,
                        photometric=train,
                    )
                if got is not None:
                    images[k, 0], masks[k, 0] = got
                    valid[k] = 1.0
        return {
            "ends_image": torch.from_numpy(images),
            "ends_mask": torch.from_numpy(masks),
            "ends_valid": torch.from_numpy(valid),
        }
