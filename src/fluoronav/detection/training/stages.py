"""The training set-ups of the detector's stages (:data:`STAGE_SETUPS`): what each trains, on which
data, with which loss and which validation.

The view stages (coarse, fine) train jointly or one of them alone on whole views and regions of
interest (:class:`~fluoronav.detection.training.dataset.CMDetectionDataset`,
:func:`~fluoronav.detection.training.loss.detector_loss`); a patch stage trains alone on its tube-aligned
patches, added to a model without it: the landmark refinement (``refine``,
:class:`~fluoronav.detection.training.dataset.RefineDataset`, heatmap cross-entropy) and the patch-mask
stages (``ends``, ``tube``, ``shaft``, :class:`~fluoronav.detection.training.dataset.EndsDataset`, BCE +
Dice). A new shaft stage starts as a copy of the tube-mask stage: it learns one thing more.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from monai.losses import DiceLoss
from torch import nn
from torch.nn import functional as tnf
from torch.utils.data import DataLoader

from fluoronav.detection.config import DetectorConfig, EndsConfig, TubeConfig
from fluoronav.detection.decoder import decode_refine_logits
from fluoronav.detection.heatmaps import decode_landmarks, heatmap_cross_entropy
from fluoronav.detection.model import DetectorNet
from fluoronav.detection.training.augment import AugmentConfig
from fluoronav.detection.training.config import TrainConfig
from fluoronav.detection.training.dataset import CMDetectionDataset, EndsDataset, RefineDataset
from fluoronav.detection.training.loss import (
    detector_loss,
    ends_loss,
    ends_outputs,
    refine_loss,
    refine_outputs,
)
from fluoronav.detection.training.patches import EndJitter, RefineJitter

__all__ = [
    "STAGE_SETUPS",
    "StageSetup",
    "TrainingRun",
    "recorded_augmentation",
    "run_stages",
    "stage_setup",
    "validate",
    "validate_ends",
    "validate_refine",
]


def run_stages(
    net: DetectorNet, batch: dict[str, torch.Tensor], stages: tuple[str, ...], device: torch.device
) -> dict[str, torch.Tensor]:
    """The outputs (B, 3, S, S) of the listed stages on a batch's views."""
    return {stage: getattr(net, stage)(batch[f"{stage}_image"].to(device)) for stage in stages}


def _mean_or_nan(values: Sequence[float]) -> float:
    """Mean of a validation metric's values; NaN where there are none (e.g. no positives)."""
    return float(np.mean(values)) if len(values) else float("nan")


@torch.no_grad()
def validate_refine(
    net: DetectorNet, loader: DataLoader, device: torch.device, cfg: DetectorConfig
) -> dict[str, float]:
    """Validation loss and landmark error (input pixels) of the refinement stage from jittered starts:
    ``val_landmark_px`` with the inference prior (``decoder.prior_px``), ``val_start_px`` where the
    patches started."""
    assert cfg.refine is not None
    sampler, decoder = cfg.refine.sampler, cfg.refine.decoder
    net.eval()
    losses, errs, starts = [], [], []
    centre = torch.tensor([(sampler.shape[1] - 1) / 2.0, (sampler.shape[0] - 1) / 2.0])
    scale = sampler.step_px(
        None, cfg.assumed_spacing_mm
    )  # input pixels per patch pixel at the training spacing
    for batch in loader:
        sel, target = refine_outputs(net, batch, device)
        losses.append(float(heatmap_cross_entropy(sel, target, sigma_px=decoder.sigma_px)))
        pts, _ = decode_refine_logits(sel.cpu(), sigma_px=decoder.sigma_px, prior_px=decoder.prior_px)
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


@torch.no_grad()
def validate_ends(
    stage: nn.Module, loader: DataLoader, device: torch.device, cfg: EndsConfig | TubeConfig, dice: DiceLoss
) -> dict[str, float]:
    """Validation loss and the pixel error of a patch-mask stage's network on the part of the patches
    that it decides at inference (``inner_px`` inside the landmark outwards for the mask-end stage,
    ``band_px`` around the centre for the tube-mask and shaft stages): ``val_end_error`` the
    fraction of those pixels labelled wrongly, ``val_end_dice`` the Dice there."""
    stage.eval()
    losses, wrong, total, inter, sizes = [], 0.0, 0.0, 0.0, 0.0
    cols_n = cfg.sampler.shape[1]
    centre = (cols_n - 1) / 2.0
    cols = torch.arange(cols_n, dtype=torch.float32)
    keep = (
        cols <= centre + cfg.inner_px if isinstance(cfg, EndsConfig) else (cols - centre).abs() <= cfg.band_px
    )
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


def _view_loss(
    outputs: dict[str, torch.Tensor],
    batch: dict[str, torch.Tensor],
    device: torch.device,
    cfg: DetectorConfig,
    tcfg: TrainConfig,
    dice: DiceLoss,
) -> torch.Tensor:
    """:func:`~fluoronav.detection.training.loss.detector_loss` with the training settings' weights."""
    return detector_loss(
        outputs,
        batch,
        device,
        cfg,
        dice=dice,
        heatmap_weight=tcfg.heatmap_weight,
        fg_weight=tcfg.heatmap_fg_weight,
        bce_weight=tcfg.bce_weight,
    )


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
        losses.append(float(_view_loss(trained, batch, device, cfg, tcfg, dice)))
        pos = batch["positive"].numpy()
        fd, cd = cfg.fine.decoder, cfg.coarse.decoder
        pred = (torch.sigmoid(fo[:, 0]) > fd.mask_threshold).cpu().numpy()
        true = batch["fine_mask"][:, 0].numpy() > 0.5
        fpts, _ = decode_landmarks(fo[:, 1:].cpu(), mode=fd.heatmap, sigma_px=fd.sigma_px)
        cpts, _ = decode_landmarks(co[:, 1:].cpu(), mode=cd.heatmap, sigma_px=cd.sigma_px)
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


# ----- the set-ups ------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrainingRun:
    """What a set-up's data, loss and validation read.

    Attributes:
        net: the detector being trained (all its stages; those not trained are frozen).
        config: its configuration.
        settings: the training settings.
        device: where the network runs.
        dice: the Dice loss of the mask terms.
    """

    net: DetectorNet
    config: DetectorConfig
    settings: TrainConfig
    device: torch.device
    dice: DiceLoss


DatasetFn = Callable[..., CMDetectionDataset]
LossFn = Callable[[TrainingRun, dict[str, torch.Tensor]], torch.Tensor]
ValidateFn = Callable[[TrainingRun, DataLoader], dict[str, float]]


@dataclass(frozen=True)
class StageSetup:
    """How a stage trains: the trained stages are ``TrainConfig.stages`` (the others frozen), the
    schedule (Adam, step decay) that of :class:`~fluoronav.detection.training.config.TrainConfig`.

    Attributes:
        dataset: ``dataset(root, settings, **kw)``, the data set of one directory (``kw``: config,
            split, val_fraction, augment, seed).
        loss: ``loss(run, batch)``, the scalar loss of a training batch.
        validate: ``validate(run, loader)``, the validation metrics.
        jitter: the patches' placement jitter (recorded in the model file; None: the view stages,
            whose augmentation is recorded).
        added: a model configuration without the stage gets it (a patch stage trained alone).
        copy_of: a stage whose settings and weights a newly added stage starts from (None: its
            defaults and fresh weights).
    """

    dataset: DatasetFn
    loss: LossFn
    validate: ValidateFn
    jitter: RefineJitter | EndJitter | None = None
    added: bool = False
    copy_of: str | None = None


#: the patches' placement jitter of the refinement and the patch-mask stages (their data sets' defaults)
_REFINE_JITTER = RefineJitter()
_END_JITTER = EndJitter()


def _view_dataset(root: str | Path, settings: TrainConfig, **kw: object) -> CMDetectionDataset:
    return CMDetectionDataset(root, **kw)  # type: ignore[arg-type]


def _view_step_loss(run: TrainingRun, batch: dict[str, torch.Tensor]) -> torch.Tensor:
    outputs = run_stages(run.net, batch, run.settings.stages, run.device)
    return _view_loss(outputs, batch, run.device, run.config, run.settings, run.dice)


def _view_validate(run: TrainingRun, loader: DataLoader) -> dict[str, float]:
    return validate(run.net, loader, run.device, run.config, run.settings, run.dice)


def _refine_dataset(root: str | Path, settings: TrainConfig, **kw: object) -> CMDetectionDataset:
    return RefineDataset(root, repeats=settings.refine_repeats, jitter=_REFINE_JITTER, **kw)


def _refine_step_loss(run: TrainingRun, batch: dict[str, torch.Tensor]) -> torch.Tensor:
    return refine_loss(run.net, batch, run.device, run.config)


def _refine_validate(run: TrainingRun, loader: DataLoader) -> dict[str, float]:
    return validate_refine(run.net, loader, run.device, run.config)


def _mask_dataset(root: str | Path, settings: TrainConfig, *, stage: str, **kw: object) -> CMDetectionDataset:
    return EndsDataset(
        root,
        repeats=settings.refine_repeats,
        jitter=_END_JITTER,
        stage=stage,
        shaft_prob=settings.tube_shaft_prob,
        **kw,
    )


def _mask_step_loss(run: TrainingRun, batch: dict[str, torch.Tensor], *, stage: str) -> torch.Tensor:
    return ends_loss(getattr(run.net, stage), batch, run.device, run.dice)


def _mask_validate(run: TrainingRun, loader: DataLoader, *, stage: str) -> dict[str, float]:
    return validate_ends(getattr(run.net, stage), loader, run.device, getattr(run.config, stage), run.dice)


def _mask_setup(stage: str, *, copy_of: str | None = None) -> StageSetup:
    """The set-up of the patch-mask stage ``stage``, trained alone."""
    return StageSetup(
        dataset=functools.partial(_mask_dataset, stage=stage),
        loss=functools.partial(_mask_step_loss, stage=stage),
        validate=functools.partial(_mask_validate, stage=stage),
        jitter=_END_JITTER,
        added=True,
        copy_of=copy_of,
    )


_VIEWS = StageSetup(dataset=_view_dataset, loss=_view_step_loss, validate=_view_validate)

#: the training set-up of each stage (the view stages share one: they train jointly)
STAGE_SETUPS: dict[str, StageSetup] = {
    "coarse": _VIEWS,
    "fine": _VIEWS,
    "refine": StageSetup(
        dataset=_refine_dataset,
        loss=_refine_step_loss,
        validate=_refine_validate,
        jitter=_REFINE_JITTER,
        added=True,
    ),
    "ends": _mask_setup("ends"),
    "tube": _mask_setup("tube"),
    "shaft": _mask_setup("shaft", copy_of="tube"),
}


def stage_setup(stages: Sequence[str]) -> StageSetup:
    """The set-up that trains ``stages`` (valid ``TrainConfig.stages``: view stages, or one alone)."""
    return STAGE_SETUPS[stages[0]]


def recorded_augmentation(setup: StageSetup, augment: AugmentConfig | None) -> dict[str, object] | None:
    """The augmentation ranges a model file records (None: off)."""
    if augment is None:
        return None
    return asdict(setup.jitter if setup.jitter is not None else augment)
