"""Training of the CM detector on ``fluoronav simulate`` data sets.

The view stages (coarse, fine) train jointly or one of them alone on whole views and regions of
interest (:class:`~fluoronav.detection.dataset.CMDetectionDataset`); a patch stage (refine, ends,
tube, shaft) trains alone on its tube-aligned patches, added to a model without it. The losses are
:mod:`fluoronav.detection.loss`'s. Adam, lr 1e-3 × 0.1 every 10 epochs (Gao et al., IEEE TBME 69(1),
2022). A checkpoint (``MODEL.ckpt``: weights, optimiser, scheduler, epoch) is written after every
epoch and ``--resume`` continues from it; the model file is rewritten after every epoch
(:func:`~fluoronav.detection.model.save_model`) and per-epoch metrics are appended to
``MODEL.log.jsonl``.
"""

from __future__ import annotations

import functools
import json
import logging
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from monai.losses import DiceLoss
from torch import nn
from torch.nn import functional as tnf
from torch.utils.data import ConcatDataset, DataLoader
from tqdm import tqdm

from fluoronav.detection.augment import AugmentConfig
from fluoronav.detection.config import NETWORK_STAGES, STAGE_ORDER, DetectorConfig, EndsConfig, TubeConfig
from fluoronav.detection.dataset import CMDetectionDataset, EndsDataset, RefineDataset
from fluoronav.detection.decoder import decode_refine_logits
from fluoronav.detection.heatmaps import decode_landmarks, heatmap_cross_entropy
from fluoronav.detection.loss import detector_loss, ends_loss, ends_outputs, refine_loss, refine_outputs
from fluoronav.detection.model import DetectorNet, count_parameters, load_net, save_model, sidecar_path
from fluoronav.detection.training_patches import EndJitter, RefineJitter
from fluoronav.device import resolve_device
from fluoronav.errors import InputError

__all__ = [
    "ARCHITECTURE",
    "TrainConfig",
    "check_coarse_size",
    "checkpoint_path",
    "init_config",
    "log_path",
    "save_model",
    "sidecar_path",
    "train",
    "validate",
    "validate_ends",
    "validate_refine",
]

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
            ``tube_shaft_prob``), added to a model without one with the tube-mask stage's weights.
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
        alone = self.stages in (("refine",), ("ends",), ("tube",), ("shaft",))
        if not alone and (not self.stages or not set(self.stages) <= {"coarse", "fine"}):
            raise ValueError(
                "stages must be 'coarse' and/or 'fine', or one of 'refine', 'ends', 'tube', 'shaft' alone, "
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


#: per network stage, the settings fixed by its trained weights (the rest only steer decoding)
ARCHITECTURE: dict[str, tuple[str, ...]] = {
    "coarse": ("network", "sampler.size", "decoder.heatmap", "decoder.sigma_px"),
    "fine": ("network", "sampler.size", "decoder.heatmap", "decoder.sigma_px"),
    "refine": ("network", "sampler.shape", "sampler.step_mm", "decoder.sigma_px"),
    "ends": ("network", "sampler.shape", "sampler.step_mm"),
    "tube": ("network", "sampler.shape", "sampler.step_mm"),
    "shaft": ("network", "sampler.shape", "sampler.step_mm"),
}


def init_config(start: DetectorConfig, base: DetectorConfig) -> DetectorConfig:
    """``base``'s settings with ``start``'s networks: each network stage of ``start`` listed, with
    the settings its weights fix (:data:`ARCHITECTURE`) from ``start`` and the others from ``base``
    (the stage's defaults where ``base`` does not list it)."""
    data = base.to_dict()
    stages = set(base.stages)
    for name in start.network_stages:
        stages.add(name)
        ours = data.get(name) or DetectorConfig(stages=("coarse", "fine", name)).to_dict()[name]
        theirs = getattr(start, name).model_dump(mode="json")
        for path in ARCHITECTURE[name]:
            *head, last = path.split(".")
            dst, src = ours, theirs
            for key in head:
                dst, src = dst[key], src[key]
            dst[last] = src[last]
        data[name] = ours
    data["stages"] = [s for s in STAGE_ORDER if s in stages]
    return DetectorConfig.model_validate(data)


def with_stage(config: DetectorConfig, name: str, settings: dict[str, Any] | None = None) -> DetectorConfig:
    """``config`` with stage ``name`` listed, with ``settings`` (None: its defaults)."""
    data = config.to_dict()
    data[name] = {} if settings is None else settings
    data["stages"] = [s for s in STAGE_ORDER if s in config.stages or s == name]
    return DetectorConfig.model_validate(data)


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
    """:func:`~fluoronav.detection.loss.detector_loss` with the training settings' weights."""
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
    of a model file (fine-tuning, e.g. on a new data set) and takes its networks and the settings
    they fix (:func:`init_config`); the other settings come from ``model_config`` (default: this
    version's), or with ``keep_decoding`` from the ``init`` file, ``model_config`` aside
    (fine-tuning a tuned model: the result decodes as it did); the optimiser and the learning-rate
    schedule start afresh. ``resume`` wins over ``init``. ``coarse_size`` sets the coarse stage's
    working resolution (``coarse.sampler.size``, pixels; a multiple of 16), also against the ``init`` file's:
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
        start = load_net(init)  # validated: one-line error on a bad file
        base = start.config if keep_decoding else model_config or DetectorConfig()
        model_config = init_config(start.config, base)
        init_state = start.state_dict()
        logger.info("starting from the weights of %s", init)
    mcfg = model_config or DetectorConfig()
    if coarse_size is not None and ckpt is None:  # a resumed run keeps its checkpoint's configuration
        data = mcfg.to_dict()
        data["coarse"]["sampler"]["size"] = coarse_size
        mcfg = DetectorConfig.model_validate(data)
    refining = tcfg.stages == ("refine",)
    shafting = tcfg.stages == ("shaft",)
    tubing = shafting or tcfg.stages == ("tube",)  # patches along the centreline
    ending = tubing or tcfg.stages == ("ends",)  # a patch-mask stage
    if refining and mcfg.refine is None:
        mcfg = with_stage(mcfg, "refine")
    if tubing and not shafting and mcfg.tube is None:
        mcfg = with_stage(mcfg, "tube")
    if shafting and mcfg.shaft is None:
        # a new shaft stage starts as a copy of the tube-mask stage: it learns one thing more
        tube = mcfg.tube.model_dump(mode="json") if mcfg.tube is not None else None
        mcfg = with_stage(mcfg, "shaft", tube)
        if init_state is not None and tube is not None:
            init_state = {
                **init_state,
                **{"shaft." + k[len("tube.") :]: v for k, v in init_state.items() if k.startswith("tube.")},
            }
    if ending and not tubing and mcfg.ends is None:
        mcfg = with_stage(mcfg, "ends")

    torch.manual_seed(tcfg.seed)
    net = DetectorNet(mcfg).to(device)
    if init_state is not None:
        missing, unexpected = net.load_state_dict(init_state, strict=False)
        if unexpected or any(not k.startswith(("refine.", "ends.", "tube.", "shaft.")) for k in missing):
            raise InputError(str(init), "weights do not match the model configuration")
    for name in NETWORK_STAGES:
        module = getattr(net, name)
        if module is not None:
            module.requires_grad_(name in tcfg.stages)
    # the patch-mask stage that trains; None for the others (a model may carry one all the same)
    patch_name = ("shaft" if shafting else "tube" if tubing else "ends") if ending else None
    patch_stage = getattr(net, patch_name) if patch_name is not None else None
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
    # the patch stages read tube-aligned patches; the view stages whole views and ROIs
    make_ds = (
        functools.partial(RefineDataset, repeats=tcfg.refine_repeats)
        if refining
        else functools.partial(
            EndsDataset, repeats=tcfg.refine_repeats, stage=str(patch_name), shaft_prob=tcfg.tube_shaft_prob
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
            elif patch_stage is not None:
                loss = ends_loss(patch_stage, batch, device, dice)
            else:
                loss = _view_loss(
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
            elif patch_stage is not None:
                stage_cfg = getattr(mcfg, str(patch_name))
                val = validate_ends(patch_stage, val_loader, device, stage_cfg, dice)
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
                else asdict(RefineJitter() if refining else EndJitter() if ending else aug),
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
