"""Training of the CM detector (both stages jointly) on a ``fluoronav simulate`` data set.

Loss (per stage, summed over the coarse and fine stage): MONAI ``DiceLoss`` (sigmoid, batch-wise, so
that negatives' false positives count) on the segmentation logit — plus, by default, a binary
cross-entropy term (``bce_weight``; the paper uses Dice alone, which converges much more slowly from
random weights) — plus the L2 error of the two
heatmaps, ``heatmap_weight · Σ (1 + fg·t)(h − t)² / (B · 2 · π σ²)`` — a sum of squares scaled by
the Gaussian's energy πσ² so that it stays comparable to the Dice term, with pixels near the landmark
weighted up (fg = ``heatmap_fg_weight``) so the peaks are learned before the network settles on
predicting zeros everywhere. Adam, lr 1e-3 × 0.1 every 10 epochs
(Gao et al. 2022). A checkpoint (``MODEL.ckpt``: weights, optimiser, scheduler, epoch) is written after
every epoch and ``--resume`` continues from it; the model file is rewritten after every epoch and
per-epoch metrics are appended to ``MODEL.log.jsonl``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from monai.losses import DiceLoss
from torch import nn
from torch.nn import functional as tnf
from torch.utils.data import ConcatDataset, DataLoader
from tqdm import tqdm

from fluoronav import __version__
from fluoronav.detection.augment import AugmentConfig
from fluoronav.detection.dataset import CMDetectionDataset, EndsDataset, RefineDataset, StripDataset
from fluoronav.detection.ends import EndJitter
from fluoronav.detection.heatmaps import decode_landmarks, gaussian_heatmaps, heatmap_cross_entropy
from fluoronav.detection.model import (
    DEFAULT_ENDS_CHANNELS,
    DEFAULT_REFINE_CHANNELS,
    DEFAULT_STRIP_CHANNELS,
    DEFAULT_TUBE_CHANNELS,
    MODEL_FORMAT_VERSION,
    STAGES,
    DetectorConfig,
    DetectorNet,
    count_parameters,
)
from fluoronav.detection.refine import RefineJitter, decode_refine_logits
from fluoronav.detection.strip import StripJitter, strip_log_probs, strip_targets
from fluoronav.device import resolve_device
from fluoronav.errors import InputError

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings.

    Attributes:
        epochs: number of epochs (total, also when resuming).
        batch_size: samples per step.
        lr: initial Adam learning rate.
        lr_step_epochs, lr_gamma: lr × lr_gamma every lr_step_epochs epochs.
        heatmap_weight: weight of the heatmap L2 term (see the module docstring).
        heatmap_fg_weight: extra per-pixel weight of the L2 term where the target is high.
        bce_weight: weight of a binary cross-entropy term added to the Dice loss (0: Dice only, as in
            the paper; Dice alone converges slowly from random weights).
        val_fraction: fraction of sample ids held out for validation.
        seed: seed of the weights, the shuffling and the augmentations.
        device: ``cpu``, ``cuda`` or ``auto``.
        workers: data loader worker processes.
        max_steps_per_epoch: stop each epoch after this many steps (None: the whole split).
        augment: augment the training samples.
        stages: the stages trained (``("coarse", "fine")``, or one of them): the others keep their
            weights and are not run, so fine-tuning only the fine stage costs about half a step.
            ``("refine",)`` trains the landmark refinement stage alone on tube-aligned patches
            (:class:`~fluoronav.detection.dataset.RefineDataset`), adding it to a model without one;
            ``("ends",)`` the mask-end stage alone (:class:`~fluoronav.detection.dataset.EndsDataset`,
            BCE + Dice on the patch masks), likewise; ``("tube",)`` the tube-mask stage alone, likewise;
            ``("shaft",)`` the shaft stage alone (tube-mask patches, some on the mounting shaft:
            ``tube_shaft_prob``), added to a model without one with the tube-mask stage's weights;
            ``("strip",)`` the strip stage alone (:class:`~fluoronav.detection.dataset.StripDataset`,
            cross-entropy of A's place along paths), added to a model without one.
        edge_negative_prob: probability that a CM-free sample's fine ROI is centred on a strong edge
            of its image (``AugmentConfig.p_edge_negative_roi``) rather than anywhere.
        refine_repeats: patches per landmark and sample in an epoch of the refinement or the mask-end
            stage.
        collimate_prob: probability that a training sample is cropped to a collimated field of view
            first (:func:`~fluoronav.detection.augment.collimation_window`, ``p_collimate``).
        partial_roi_prob: probability that a training sample's fine ROI is fitted to a part of its
            CM only (``AugmentConfig.p_partial_roi``).
        tube_shaft_prob: with ``("tube",)`` or ``("shaft",)``, probability that a patch is centred
            on the projected mounting shaft instead of the CM's centreline (where the manifest has
            the camera and the pose; :func:`~fluoronav.detection.ends.training_tube_patch`).
    """

    epochs: int = 10
    batch_size: int = 16
    lr: float = 1e-3
    lr_step_epochs: int = 10
    lr_gamma: float = 0.1
    heatmap_weight: float = 1.0
    heatmap_fg_weight: float = 20.0
    bce_weight: float = 1.0
    val_fraction: float = 1 / 11
    seed: int = 0
    device: str = "auto"
    workers: int = 0
    max_steps_per_epoch: int | None = None
    augment: bool = True
    stages: tuple[str, ...] = ("coarse", "fine")
    collimate_prob: float = 0.0
    partial_roi_prob: float = 0.0
    edge_negative_prob: float = 0.0
    refine_repeats: int = 5
    tube_shaft_prob: float = 0.0

    def __post_init__(self) -> None:
        alone = self.stages in (("refine",), ("ends",), ("tube",), ("shaft",), ("strip",))
        if not alone and (not self.stages or not set(self.stages) <= {"coarse", "fine"}):
            raise ValueError(
                "stages must be 'coarse' and/or 'fine', or one of 'refine', 'ends', 'tube', 'shaft', "
                "'strip' alone, "
                f"got {self.stages}"
            )
        if self.refine_repeats < 1:
            raise ValueError(f"refine_repeats must be 1 or more, got {self.refine_repeats}")
        if not 0.0 <= self.collimate_prob <= 1.0:
            raise ValueError(f"collimate_prob must be in [0, 1], got {self.collimate_prob}")
        if not 0.0 <= self.partial_roi_prob <= 1.0:
            raise ValueError(f"partial_roi_prob must be in [0, 1], got {self.partial_roi_prob}")
        if not 0.0 <= self.edge_negative_prob <= 1.0:
            raise ValueError(f"edge_negative_prob must be in [0, 1], got {self.edge_negative_prob}")
        if not 0.0 <= self.tube_shaft_prob <= 1.0:
            raise ValueError(f"tube_shaft_prob must be in [0, 1], got {self.tube_shaft_prob}")
        if self.tube_shaft_prob > 0.0 and self.stages not in (("tube",), ("shaft",)):
            raise ValueError("tube_shaft_prob applies to the stages 'tube' and 'shaft' (trained alone)")
        if self.stages == ("shaft",) and self.tube_shaft_prob <= 0.0:
            raise ValueError("the shaft stage learns from patches on the shaft: give tube_shaft_prob > 0")


#: the architecture fields of the refinement stage
REFINE_FIELDS = ("refine_channels", "refine_shape", "refine_step_mm", "refine_sigma_px")

#: the architecture fields of the patch-mask stages (their patch scale is ``refine_step_mm``)
ENDS_FIELDS = ("ends_channels", "ends_shape", "tube_channels", "shaft_channels")

#: the architecture fields of the strip stage (its scale is ``refine_step_mm`` too)
STRIP_FIELDS = ("strip_channels", "strip_shape", "strip_sigma_px")

#: the model configuration fields fixed by trained weights (the rest only steer decoding)
ARCHITECTURE_FIELDS = (
    "input_size",
    "roi_size",
    "channels",
    "roi_channels",
    "num_res_units",
    "sigma_px",
    "heatmap",
    *REFINE_FIELDS,
    *ENDS_FIELDS,
    *STRIP_FIELDS,
)


def check_coarse_size(coarse_size: int | None, stages: Sequence[str]) -> None:
    """Raise ValueError unless ``coarse_size`` is None or a multiple of 16 (≥ 32) with the coarse
    stage among ``stages`` (a new scale for an untrained coarse stage would only spoil it)."""
    if coarse_size is None:
        return
    if coarse_size < 32 or coarse_size % 16:
        raise ValueError(f"coarse_size must be a multiple of 16 of at least 32, got {coarse_size}")
    if "coarse" not in stages:
        raise ValueError("coarse_size changes the coarse stage's scale: train the coarse stage too")


def checkpoint_path(model_path: Path) -> Path:
    return model_path.with_name(model_path.name + ".ckpt")


def log_path(model_path: Path) -> Path:
    return model_path.with_name(model_path.stem + ".log.jsonl")


def sidecar_path(model_path: Path) -> Path:
    return model_path.with_suffix(".json")


def stage_loss(
    out: torch.Tensor,
    mask: torch.Tensor,
    landmarks: torch.Tensor,
    *,
    sigma_px: float,
    heatmap_weight: float,
    dice: DiceLoss,
    fg_weight: float = 0.0,
    bce_weight: float = 0.0,
    heatmap_mode: str = "softmax",
) -> tuple[torch.Tensor, dict[str, float]]:
    """Segmentation + heatmap loss of one stage. out (B, 3, S, S), mask (B, 1, S, S), landmarks (B, 2, 2).

    Heatmaps: cross-entropy of the spatial softmax (``heatmap_mode="softmax"``) or the weighted L2 of
    peak-1 Gaussians (``"gaussian"``, the paper's).
    """
    seg = dice(out[:, :1], mask)
    if bce_weight > 0:
        seg = seg + bce_weight * tnf.binary_cross_entropy_with_logits(out[:, :1], mask)
    if heatmap_mode == "softmax":
        hm = heatmap_cross_entropy(out[:, 1:], landmarks, sigma_px=sigma_px)
    else:
        target = gaussian_heatmaps(landmarks, (out.shape[-2], out.shape[-1]), sigma_px=sigma_px)
        w = 1.0 + fg_weight * target
        hm = (w * (out[:, 1:] - target) ** 2).sum() / (out.shape[0] * 2 * math.pi * sigma_px**2)
    return seg + heatmap_weight * hm, {"dice_loss": float(seg.detach()), "heatmap_loss": float(hm.detach())}


def detector_loss(
    outputs: dict[str, torch.Tensor],
    batch: dict[str, torch.Tensor],
    device: torch.device,
    cfg: DetectorConfig,
    tcfg: TrainConfig,
    dice: DiceLoss,
) -> torch.Tensor:
    """Sum of the :func:`stage_loss` of each stage in ``outputs`` (stage name → (B, 3, S, S)) on a batch."""
    total = next(iter(outputs.values())).new_zeros(())
    for stage, out in outputs.items():
        loss, _ = stage_loss(
            out,
            batch[f"{stage}_mask"].to(device),
            batch[f"{stage}_landmarks"].to(device),
            sigma_px=cfg.sigma_px,
            heatmap_weight=tcfg.heatmap_weight,
            dice=dice,
            fg_weight=tcfg.heatmap_fg_weight,
            bce_weight=tcfg.bce_weight,
            heatmap_mode=cfg.heatmap,
        )
        total = total + loss
    return total


def save_model(path: Path, net: DetectorNet, *, extra: dict) -> None:
    """Write the model file (state_dict + config + normalisation + version) and its JSON sidecar."""
    cfg = net.config
    meta = {
        "format_version": MODEL_FORMAT_VERSION,
        "fluoronav_version": __version__,
        "config": cfg.to_dict(),
        "normalization": {"method": "percentile", "low_pct": cfg.low_pct, "high_pct": cfg.high_pct},
        # the whole model's size, also when one stage was frozen for this run
        "parameters": count_parameters(net, trainable_only=False),
        **extra,
    }
    state = {k: v.detach().cpu() for k, v in net.state_dict().items()}
    tmp = path.with_name(path.name + ".tmp")
    torch.save({**meta, "state_dict": state}, tmp)
    tmp.replace(path)
    sidecar_path(path).write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")


def run_stages(
    net: DetectorNet, batch: dict[str, torch.Tensor], stages: tuple[str, ...], device: torch.device
) -> dict[str, torch.Tensor]:
    """The outputs (B, 3, S, S) of the listed stages on a batch's views."""
    return {stage: getattr(net, stage)(batch[f"{stage}_image"].to(device)) for stage in stages}


def _mean_or_nan(values: Sequence[float]) -> float:
    """Mean of a validation metric's values; NaN where there are none (e.g. no positives)."""
    return float(np.mean(values)) if len(values) else float("nan")


def refine_outputs(
    net: DetectorNet, batch: dict[str, torch.Tensor], device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """Refinement logits of each patch's own landmark (N, 1, rows, cols) and targets (N, 1, 2) (col, row;
    NaN: no patch), N = 2 × the batch (A and B of each sample)."""
    assert net.refine is not None
    x = batch["refine_image"].to(device)  # (B, 2, 1, rows, cols)
    b = x.shape[0]
    out = net.refine(x.reshape(b * 2, *x.shape[2:]))
    k = torch.arange(2, device=device).repeat(b)
    sel = out[torch.arange(b * 2, device=device), k][:, None]
    return sel, batch["refine_landmarks"].to(device).reshape(b * 2, 1, 2)


def refine_loss(
    net: DetectorNet, batch: dict[str, torch.Tensor], device: torch.device, cfg: DetectorConfig
) -> torch.Tensor:
    """Cross-entropy of the refinement heatmaps (:func:`heatmap_cross_entropy`) on a batch."""
    sel, target = refine_outputs(net, batch, device)
    return heatmap_cross_entropy(sel, target, sigma_px=cfg.refine_sigma_px)


@torch.no_grad()
def validate_refine(
    net: DetectorNet, loader: DataLoader, device: torch.device, cfg: DetectorConfig
) -> dict[str, float]:
    """Validation loss and landmark error (input pixels) of the refinement stage from jittered starts:
    ``val_landmark_px`` with the inference prior (``refine_prior_px``), ``val_start_px`` where the
    patches started."""
    net.eval()
    losses, errs, starts = [], [], []
    centre = torch.tensor([(cfg.refine_shape[1] - 1) / 2.0, (cfg.refine_shape[0] - 1) / 2.0])
    scale = cfg.refine_step_px(None)  # input pixels per patch pixel at the training spacing
    for batch in loader:
        sel, target = refine_outputs(net, batch, device)
        losses.append(float(heatmap_cross_entropy(sel, target, sigma_px=cfg.refine_sigma_px)))
        pts, _ = decode_refine_logits(sel.cpu(), sigma_px=cfg.refine_sigma_px, prior_px=cfg.refine_prior_px)
        t = target[:, 0].cpu()
        ok = torch.isfinite(t).all(dim=1)
        errs.extend((torch.linalg.norm(pts[ok] - t[ok], dim=1) * scale).tolist())
        starts.extend((torch.linalg.norm(centre - t[ok], dim=1) * scale).tolist())
    net.train()
    return {
        "val_loss": _mean_or_nan(losses),
        "val_landmark_px": _mean_or_nan(errs),
        "val_start_px": _mean_or_nan(starts),
    }


def ends_outputs(
    stage: nn.Module, batch: dict[str, torch.Tensor], device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """Patch mask logits (N, 1, rows, cols) of the mask-end or tube-mask ``stage`` and true patch
    masks (N, 1, rows, cols) of the patches that exist (N ≤ 2 × the batch)."""
    x = batch["ends_image"].to(device)  # (B, 2, 1, rows, cols)
    ok = batch["ends_valid"].to(device).reshape(-1) > 0
    out = stage(x.reshape(-1, *x.shape[2:])[ok])
    return out, batch["ends_mask"].to(device).reshape(-1, *x.shape[2:])[ok]


def ends_loss(
    stage: nn.Module, batch: dict[str, torch.Tensor], device: torch.device, dice: DiceLoss
) -> torch.Tensor:
    """Binary cross-entropy + Dice of a patch-mask stage's masks on a batch (0 without patches)."""
    out, target = ends_outputs(stage, batch, device)
    if out.shape[0] == 0:
        return out.sum()
    return tnf.binary_cross_entropy_with_logits(out, target) + dice(out, target)


@torch.no_grad()
def validate_ends(
    stage: nn.Module,
    loader: DataLoader,
    device: torch.device,
    cfg: DetectorConfig,
    dice: DiceLoss,
    *,
    tube: bool = False,
) -> dict[str, float]:
    """Validation loss and the pixel error of a patch-mask stage on the part of the patches that it
    decides at inference (``ends_inner_px`` for the mask-end stage, ``tube_band_px`` for the tube-mask
    one, ``tube``): ``val_end_error`` the fraction of those pixels labelled wrongly, ``val_end_dice``
    the Dice there."""
    stage.eval()
    losses, wrong, total, inter, sizes = [], 0.0, 0.0, 0.0, 0.0
    centre = (cfg.ends_shape[1] - 1) / 2.0
    cols = torch.arange(cfg.ends_shape[1], dtype=torch.float32)
    keep = (cols - centre).abs() <= cfg.tube_band_px if tube else cols <= centre + cfg.ends_inner_px
    for batch in loader:
        out, target = ends_outputs(stage, batch, device)
        if out.shape[0] == 0:
            continue
        losses.append(float(tnf.binary_cross_entropy_with_logits(out, target) + dice(out, target)))
        pred = (out[..., keep.to(out.device)] > 0).float()
        t = target[..., keep.to(out.device)]
        wrong += float((pred != t).float().sum())
        total += float(t.numel())
        inter += float((pred * t).sum())
        sizes += float(pred.sum() + t.sum())
    stage.train()
    return {
        "val_loss": _mean_or_nan(losses),
        "val_end_error": wrong / total if total else float("nan"),
        "val_end_dice": 2.0 * inter / sizes if sizes else float("nan"),
    }


def strip_outputs(
    stage: nn.Module, batch: dict[str, torch.Tensor], device: torch.device
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Log-probabilities (N, cols + 1) of the strip ``stage`` (:func:`strip_log_probs`), the paths'
    columns (N, cols) and A's columns (N,) (−1: none) of the strips that exist (N ≤ 2 × the batch)."""
    x = batch["strip_image"].to(device)  # (B, 2, 1, rows, cols)
    ok = batch["strip_ok"].to(device).reshape(-1) > 0
    valid = batch["strip_valid"].to(device).reshape(-1, x.shape[-1])[ok]
    logp = strip_log_probs(stage(x.reshape(-1, *x.shape[2:])[ok]), valid)
    return logp, valid, batch["strip_a"].to(device).reshape(-1)[ok]


def _strip_cross_entropy(
    logp: torch.Tensor, valid: torch.Tensor, a_col: torch.Tensor, cfg: DetectorConfig
) -> torch.Tensor:
    """Mean cross-entropy of strip log-probabilities (N, cols + 1) against :func:`strip_targets`."""
    target = strip_targets(valid, a_col, sigma_px=cfg.strip_sigma_px)
    return -(target * logp).sum(dim=1).mean()


def strip_loss(
    stage: nn.Module, batch: dict[str, torch.Tensor], device: torch.device, cfg: DetectorConfig
) -> torch.Tensor:
    """Cross-entropy of the strip stage's distributions against :func:`strip_targets` (0 without
    strips)."""
    logp, valid, a_col = strip_outputs(stage, batch, device)
    if logp.shape[0] == 0:
        return logp.sum()
    return _strip_cross_entropy(logp, valid, a_col, cfg)


@torch.no_grad()
def validate_strip(
    stage: nn.Module, loader: DataLoader, device: torch.device, cfg: DetectorConfig
) -> dict[str, float]:
    """Validation loss of the strip stage; on paths without A the fraction told so
    (``val_none_right``), on paths through A the fraction said to have none (``val_a_missed``), the
    median error of the most likely column (``val_a_median_mm``, mm at the detector) and the fraction
    of those more than 3 mm off (``val_a_gross``)."""
    stage.eval()
    losses, none_right, missed, errs = [], [], [], []
    for batch in loader:
        logp, valid, a_col = strip_outputs(stage, batch, device)
        if logp.shape[0] == 0:
            continue
        losses.append(float(_strip_cross_entropy(logp, valid, a_col, cfg)))
        best = logp.argmax(dim=1).cpu().numpy()
        a = a_col.cpu().numpy()
        none = logp.shape[1] - 1
        none_right.extend((best[a < 0] == none).tolist())
        has = a >= 0
        missed.extend((best[has] == none).tolist())
        found = has & (best != none)
        errs.extend((np.abs(best[found] - a[found]) * cfg.refine_step_mm).tolist())
    stage.train()
    return {
        "val_loss": _mean_or_nan(losses),
        "val_none_right": _mean_or_nan(none_right),
        "val_a_missed": _mean_or_nan(missed),
        "val_a_median_mm": float(np.median(errs)) if errs else float("nan"),
        "val_a_gross": _mean_or_nan([e > 3.0 for e in errs]),
    }


@torch.no_grad()
def validate(
    net: DetectorNet,
    loader: DataLoader,
    device: torch.device,
    cfg: DetectorConfig,
    tcfg: TrainConfig,
    dice: DiceLoss,
) -> dict[str, float]:
    """Validation loss (of the trained stages), fine-stage Dice on positives and landmark errors in
    input pixels."""
    net.eval()
    losses, dices, errs, coarse_errs = [], [], [], []
    for batch in loader:
        outputs = run_stages(net, batch, ("coarse", "fine"), device)
        co, fo = outputs["coarse"], outputs["fine"]
        trained = {k: v for k, v in outputs.items() if k in tcfg.stages}
        losses.append(float(detector_loss(trained, batch, device, cfg, tcfg, dice)))
        pos = batch["positive"].numpy()
        pred = (torch.sigmoid(fo[:, 0]) > cfg.mask_threshold).cpu().numpy()
        true = batch["fine_mask"][:, 0].numpy() > 0.5
        fpts, _ = decode_landmarks(fo[:, 1:].cpu(), mode=cfg.heatmap, sigma_px=cfg.sigma_px)
        cpts, _ = decode_landmarks(co[:, 1:].cpu(), mode=cfg.heatmap, sigma_px=cfg.sigma_px)
        view = batch["fine_view"].numpy()
        for i in np.nonzero(pos)[0]:
            inter = np.logical_and(pred[i], true[i]).sum()
            dices.append(2.0 * inter / max(pred[i].sum() + true[i].sum(), 1))
            s = view[i, 2] / view[i, 3]  # input pixels per ROI pixel
            gt_view = batch["fine_landmarks"][i].numpy()
            errs.extend(np.linalg.norm((fpts[i].numpy() - gt_view) * s, axis=1))
            cs = float(batch["coarse_scale"][i])
            errs_c = np.linalg.norm((cpts[i].numpy() - batch["coarse_landmarks"][i].numpy()) * cs, axis=1)
            coarse_errs.extend(errs_c)
    net.train()
    return {
        "val_loss": _mean_or_nan(losses),
        "val_dice": _mean_or_nan(dices),
        "val_landmark_px": _mean_or_nan(errs),
        "val_coarse_landmark_px": _mean_or_nan(coarse_errs),
    }


def train(
    data_dir: str | Path | Sequence[str | Path],
    out_path: str | Path,
    *,
    config: TrainConfig | None = None,
    model_config: DetectorConfig | None = None,
    resume: bool = False,
    init: str | Path | None = None,
    keep_decoding: bool = False,
    coarse_size: int | None = None,
    progress: bool = True,
) -> dict[str, float]:
    """Train the detector on one or more simulate data sets and write the model file ``out_path``.

    Several directories (e.g. one with and one without a CM, ``simulate --no-cm``) are concatenated;
    each keeps its own id-based train/val split.

    Returns the last epoch's metrics. With ``resume`` the checkpoint next to ``out_path`` is
    continued (its model configuration wins over ``model_config``). ``init`` starts from the weights
    of a model file (fine-tuning, e.g. on a new data set) and takes its architecture
    (:data:`ARCHITECTURE_FIELDS`); the decoding settings come from ``model_config`` (default: this
    version's), or with ``keep_decoding`` from the ``init`` file, ``model_config`` aside
    (fine-tuning a tuned model: the result decodes as it did); the optimiser and the learning-rate
    schedule start afresh. ``resume`` wins over ``init``. ``coarse_size`` sets the coarse stage's
    working resolution (``input_size``, pixels; a multiple of 16), also against the ``init`` file's:
    the U-Net is convolutional, so its weights carry over to the new scale and are trained there
    (``coarse`` must be among the stages trained).
    """
    tcfg = config or TrainConfig()
    check_coarse_size(coarse_size, tcfg.stages)
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    device = resolve_device(tcfg.device)
    ckpt_file = checkpoint_path(out_path)
    ckpt = None
    if resume:
        if not ckpt_file.is_file():
            raise InputError(ckpt_file, "no checkpoint to resume from")
        try:
            ckpt = torch.load(ckpt_file, map_location="cpu", weights_only=False)
        except Exception as exc:  # torch raises many types for a damaged file
            raise InputError(ckpt_file, f"unreadable checkpoint ({exc.__class__.__name__})") from exc
        model_config = DetectorConfig.from_dict(ckpt["config"])
    init_state = None
    if init is not None and ckpt is None:
        from fluoronav.detection.detector import load_net

        start = load_net(init)  # validated: one-line error on a bad file
        keep: tuple[str, ...] = ARCHITECTURE_FIELDS
        if not start.config.refine_channels:  # no refinement stage yet: this version's settings
            keep = tuple(f for f in keep if f not in REFINE_FIELDS)
        # likewise the patch-mask stages, which share their patch shape
        c = start.config
        absent = {"ends_channels"} if not c.ends_channels else set()
        absent |= {"tube_channels"} if not c.tube_channels else set()
        absent |= {"shaft_channels"} if not c.shaft_channels else set()
        absent |= set(STRIP_FIELDS) if not c.strip_channels else set()
        if not (c.ends_channels or c.tube_channels):
            absent.add("ends_shape")
        keep = tuple(f for f in keep if f not in absent)
        arch = {f: getattr(start.config, f) for f in keep}
        base = start.config if keep_decoding else model_config or DetectorConfig()
        model_config = dataclasses.replace(base, **arch)
        init_state = start.state_dict()
        logger.info("starting from the weights of %s", init)
    mcfg = model_config or DetectorConfig()
    if coarse_size is not None and ckpt is None:  # a resumed run keeps its checkpoint's configuration
        mcfg = dataclasses.replace(mcfg, input_size=coarse_size)
    refining = tcfg.stages == ("refine",)
    stripping = tcfg.stages == ("strip",)
    shafting = tcfg.stages == ("shaft",)
    tubing = shafting or tcfg.stages == ("tube",)  # patches along the centreline
    ending = tubing or tcfg.stages == ("ends",)  # a patch-mask stage
    if refining and not mcfg.refine_channels:
        mcfg = dataclasses.replace(mcfg, refine_channels=DEFAULT_REFINE_CHANNELS)
    if tubing and not shafting and not mcfg.tube_channels:
        mcfg = dataclasses.replace(mcfg, tube_channels=DEFAULT_TUBE_CHANNELS)
    if shafting and not mcfg.shaft_channels:
        # a new shaft stage starts as a copy of the tube-mask stage: it learns one thing more
        mcfg = dataclasses.replace(mcfg, shaft_channels=mcfg.tube_channels or DEFAULT_TUBE_CHANNELS)
        if init_state is not None and mcfg.shaft_channels == mcfg.tube_channels:
            init_state = {
                **init_state,
                **{"shaft." + k[len("tube.") :]: v for k, v in init_state.items() if k.startswith("tube.")},
            }
    if ending and not tubing and not mcfg.ends_channels:
        mcfg = dataclasses.replace(mcfg, ends_channels=DEFAULT_ENDS_CHANNELS)
    if stripping and not mcfg.strip_channels:
        mcfg = dataclasses.replace(mcfg, strip_channels=DEFAULT_STRIP_CHANNELS)

    torch.manual_seed(tcfg.seed)
    net = DetectorNet(mcfg).to(device)
    if init_state is not None:
        missing, unexpected = net.load_state_dict(init_state, strict=False)
        if unexpected or any(
            not k.startswith(("refine.", "ends.", "tube.", "shaft.", "strip.")) for k in missing
        ):
            raise InputError(str(init), "weights do not match the model configuration")
    for name in STAGES:
        module = getattr(net, name)
        if module is not None:
            module.requires_grad_(name in tcfg.stages)
    # the patch-mask stage that trains; None for the others (a model may carry one all the same)
    patch_stage = (net.shaft if shafting else net.tube if tubing else net.ends) if ending else None
    opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=tcfg.lr)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=tcfg.lr_step_epochs, gamma=tcfg.lr_gamma)
    start_epoch = 0
    if ckpt is not None:
        net.load_state_dict(ckpt["state_dict"])
        opt.load_state_dict(ckpt["optimizer"])
        sched.load_state_dict(ckpt["scheduler"])
        start_epoch = int(ckpt["epoch"]) + 1
        torch.set_rng_state(ckpt["torch_rng"])
        logger.info("resuming from %s at epoch %d", ckpt_file, start_epoch)

    aug = (
        AugmentConfig(
            p_collimate=tcfg.collimate_prob,
            p_partial_roi=tcfg.partial_roi_prob,
            p_edge_negative_roi=tcfg.edge_negative_prob,
        )
        if tcfg.augment
        else None
    )
    dirs = [data_dir] if isinstance(data_dir, (str, Path)) else list(data_dir)
    # the refinement and mask-end stages read patches around the landmarks; the others whole views
    make_ds = (
        functools.partial(RefineDataset, repeats=tcfg.refine_repeats)
        if refining
        else functools.partial(StripDataset, repeats=tcfg.refine_repeats)
        if stripping
        else functools.partial(
            EndsDataset, repeats=tcfg.refine_repeats, tube=tubing, shaft_prob=tcfg.tube_shaft_prob
        )
        if ending
        else CMDetectionDataset
    )
    train_parts = [
        make_ds(
            d,
            config=mcfg,
            split="train",
            val_fraction=tcfg.val_fraction,
            augment=aug,
            seed=tcfg.seed + 7919 * i,
        )
        for i, d in enumerate(dirs)
    ]
    val_parts = [
        make_ds(d, config=mcfg, split="val", val_fraction=tcfg.val_fraction, seed=tcfg.seed) for d in dirs
    ]
    train_ds: ConcatDataset = ConcatDataset(train_parts)
    val_ds: ConcatDataset = ConcatDataset(val_parts)
    if len(train_ds) == 0:
        raise InputError(", ".join(str(d) for d in dirs), "no training samples after the train/val split")
    gen = torch.Generator().manual_seed(tcfg.seed)
    dice = DiceLoss(sigmoid=True, batch=True)
    log_file = log_path(out_path)
    if not resume and log_file.exists():
        log_file.unlink()
    logger.info(
        "training on %d samples (%d val), %d trainable parameters, device %s",
        len(train_ds),
        len(val_ds),
        count_parameters(net),
        device,
    )
    metrics: dict[str, float] = {}
    for epoch in range(start_epoch, tcfg.epochs):
        for part in train_parts:
            part.set_epoch(epoch)
        gen.manual_seed(tcfg.seed * 1_000_003 + epoch)  # same shuffle for an epoch whether resumed or not
        loader = DataLoader(
            train_ds,
            batch_size=tcfg.batch_size,
            shuffle=True,
            generator=gen,
            num_workers=tcfg.workers,
            drop_last=len(train_ds) > tcfg.batch_size,
        )
        n_steps = (
            len(loader) if tcfg.max_steps_per_epoch is None else min(len(loader), tcfg.max_steps_per_epoch)
        )
        t0 = time.perf_counter()
        net.train()
        total, count = 0.0, 0
        bar = tqdm(total=n_steps, desc=f"epoch {epoch + 1}/{tcfg.epochs}", disable=not progress, leave=False)
        for step, batch in enumerate(loader):
            if step >= n_steps:
                break
            if refining:
                loss = refine_loss(net, batch, device, mcfg)
            elif stripping:
                assert net.strip is not None
                loss = strip_loss(net.strip, batch, device, mcfg)
            elif patch_stage is not None:
                loss = ends_loss(patch_stage, batch, device, dice)
            else:
                loss = detector_loss(
                    run_stages(net, batch, tcfg.stages, device), batch, device, mcfg, tcfg, dice
                )
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += float(loss.detach())
            count += 1
            bar.set_postfix(loss=f"{total / count:.4f}")
            bar.update(1)
        bar.close()
        train_seconds = time.perf_counter() - t0
        lr = opt.param_groups[0]["lr"]
        sched.step()
        val_loader = DataLoader(val_ds, batch_size=tcfg.batch_size, shuffle=False, num_workers=tcfg.workers)
        val: dict[str, float] = {}
        if len(val_ds):
            if refining:
                val = validate_refine(net, val_loader, device, mcfg)
            elif stripping:
                assert net.strip is not None
                val = validate_strip(net.strip, val_loader, device, mcfg)
            elif patch_stage is not None:
                val = validate_ends(patch_stage, val_loader, device, mcfg, dice, tube=tubing)
            else:
                val = validate(net, val_loader, device, mcfg, tcfg, dice)
        metrics = {
            "epoch": epoch + 1,
            "lr": lr,
            "train_loss": total / max(count, 1),
            "steps": count,
            "train_seconds": train_seconds,
            "seconds_per_step": train_seconds / max(count, 1),
            **val,
        }
        with open(log_file, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(metrics) + "\n")
        logger.info("epoch %d: %s", epoch + 1, metrics)
        extra = {
            "train": {
                **asdict(tcfg),
                "data": [str(d) for d in dirs],
                "samples": len(train_ds),
                "init": None if init is None else str(init),
                "keep_decoding": keep_decoding and init is not None,
                # the augmentation ranges (None: off), so that a model file says how it was trained
                "augmentation": None
                if aug is None
                else asdict(
                    RefineJitter()
                    if refining
                    else StripJitter()
                    if stripping
                    else EndJitter()
                    if ending
                    else aug
                ),
            },
            "metrics": metrics,
        }
        save_model(out_path, net, extra=extra)
        tmp = ckpt_file.with_name(ckpt_file.name + ".tmp")
        torch.save(
            {
                "config": mcfg.to_dict(),
                "state_dict": net.state_dict(),
                "optimizer": opt.state_dict(),
                "scheduler": sched.state_dict(),
                "epoch": epoch,
                "torch_rng": torch.get_rng_state(),
                "train": asdict(tcfg),
            },
            tmp,
        )
        tmp.replace(ckpt_file)
    return metrics
