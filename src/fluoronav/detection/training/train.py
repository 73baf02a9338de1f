"""Training of the CM detector on ``fluoronav simulate`` data sets.

Each stage trains as its set-up in :data:`~fluoronav.detection.training.stages.STAGE_SETUPS` says: the
view stages (coarse, fine) jointly or one of them alone on whole views and regions of interest, a
patch stage (refine, ends, tube, shaft) alone on its tube-aligned patches, added to a model without
it. The losses are :mod:`fluoronav.detection.training.loss`'s. Adam, lr 1e-3 × 0.1 every 10 epochs (Gao et
al., IEEE TBME 69(1), 2022). A checkpoint (``MODEL.ckpt``: weights, optimiser, scheduler, epoch) is
written after every epoch and ``--resume`` continues from it; the model file is rewritten after
every epoch (:func:`~fluoronav.detection.model.save_model`) and per-epoch metrics are appended to
``MODEL.log.jsonl``.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch
from monai.losses import DiceLoss
from torch.utils.data import ConcatDataset, DataLoader
from tqdm import tqdm

from fluoronav.detection.config import NETWORK_STAGES, STAGE_ORDER, DetectorConfig
from fluoronav.detection.model import DetectorNet, count_parameters, load_net, save_model, sidecar_path
from fluoronav.detection.training.augment import AugmentConfig
from fluoronav.detection.training.config import TrainConfig
from fluoronav.detection.training.dataset import CMDetectionDataset
from fluoronav.detection.training.stages import (
    StageSetup,
    TrainingRun,
    recorded_augmentation,
    stage_setup,
    validate,
    validate_ends,
    validate_refine,
)
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


# ----- the phases of a training run -------------------------------------------------------------
def _read_checkpoint(ckpt_file: Path) -> dict[str, Any]:
    """The checkpoint to resume from; InputError where there is none or it is unreadable."""
    if not ckpt_file.is_file():
        raise InputError(ckpt_file, "no checkpoint to resume from")
    try:
        return torch.load(ckpt_file, map_location="cpu", weights_only=False)
    except Exception as exc:  # torch raises many types for a damaged file
        raise InputError(ckpt_file, f"unreadable checkpoint ({exc.__class__.__name__})") from exc


def _starting_config(
    ckpt: dict[str, Any] | None,
    model_config: DetectorConfig | None,
    init: str | Path | None,
    *,
    keep_decoding: bool,
    coarse_size: int | None,
) -> tuple[DetectorConfig, dict[str, torch.Tensor] | None]:
    """The model configuration a run starts from (see :func:`train`) and the ``init`` file's weights
    (None: fresh weights, or a resumed run)."""
    if ckpt is not None:  # a resumed run keeps its checkpoint's configuration
        return DetectorConfig.from_dict(ckpt["config"]), None
    init_state = None
    if init is not None:
        start = load_net(init)  # validated: one-line error on a bad file
        base = start.config if keep_decoding else model_config or DetectorConfig()
        model_config = init_config(start.config, base)
        init_state = start.state_dict()
        logger.info("starting from the weights of %s", init)
    mcfg = model_config or DetectorConfig()
    if coarse_size is not None:
        data = mcfg.to_dict()
        data["coarse"]["sampler"]["size"] = coarse_size
        mcfg = DetectorConfig.model_validate(data)
    return mcfg, init_state


def _with_trained_stage(
    setup: StageSetup, name: str, mcfg: DetectorConfig, init_state: dict[str, torch.Tensor] | None
) -> tuple[DetectorConfig, dict[str, torch.Tensor] | None]:
    """``mcfg`` and ``init_state`` with the stage ``name`` that ``setup`` adds, where it is missing:
    with its defaults, or as a copy of the stage ``setup.copy_of`` (settings and weights)."""
    if not setup.added or getattr(mcfg, name) is not None:
        return mcfg, init_state
    if setup.copy_of is None:
        return with_stage(mcfg, name), init_state
    source = getattr(mcfg, setup.copy_of)
    settings = source.model_dump(mode="json") if source is not None else None
    mcfg = with_stage(mcfg, name, settings)
    if init_state is not None and settings is not None:
        prefix = setup.copy_of + "."
        copied = {name + "." + k[len(prefix) :]: v for k, v in init_state.items() if k.startswith(prefix)}
        init_state = {**init_state, **copied}
    return mcfg, init_state


def _network(
    mcfg: DetectorConfig,
    tcfg: TrainConfig,
    init_state: dict[str, torch.Tensor] | None,
    init: str | Path | None,
    device: torch.device,
) -> DetectorNet:
    """The seeded network with the ``init`` weights, only the stages trained left trainable."""
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
    return net


@dataclass(frozen=True)
class _Data:
    """A run's data: one training and one validation set per directory, concatenated."""

    dirs: list[str | Path]
    augment: AugmentConfig | None
    train_parts: list[CMDetectionDataset]
    train: ConcatDataset
    val: ConcatDataset


def _data(
    setup: StageSetup, data_dir: str | Path | Sequence[str | Path], mcfg: DetectorConfig, tcfg: TrainConfig
) -> _Data:
    """The set-up's training and validation sets of each directory (each its own id-based split)."""
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
    common = {"config": mcfg, "val_fraction": tcfg.val_fraction}
    train_parts = [
        setup.dataset(d, tcfg, split="train", augment=aug, seed=tcfg.seed + 7919 * i, **common)
        for i, d in enumerate(dirs)
    ]
    val_parts = [setup.dataset(d, tcfg, split="val", seed=tcfg.seed, **common) for d in dirs]
    data = _Data(dirs, aug, train_parts, ConcatDataset(train_parts), ConcatDataset(val_parts))
    if len(data.train) == 0:
        raise InputError(", ".join(str(d) for d in dirs), "no training samples after the train/val split")
    return data


def _train_epoch(
    setup: StageSetup,
    run: TrainingRun,
    opt: torch.optim.Optimizer,
    loader: DataLoader,
    n_steps: int,
    bar: tqdm,
) -> tuple[float, int]:
    """One epoch's optimisation steps (at most ``n_steps``): (summed loss, steps)."""
    run.net.train()
    total, count = 0.0, 0
    for step, batch in enumerate(loader):
        if step >= n_steps:
            break
        loss = setup.loss(run, batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        total += float(loss.detach())
        count += 1
        bar.set_postfix(loss=f"{total / count:.4f}")
        bar.update(1)
    bar.close()
    return total, count


def _epoch(
    setup: StageSetup,
    run: TrainingRun,
    data: _Data,
    opt: torch.optim.Optimizer,
    sched: torch.optim.lr_scheduler.LRScheduler,
    gen: torch.Generator,
    epoch: int,
    *,
    progress: bool,
) -> dict[str, float]:
    """Train one epoch and validate: the epoch's metrics."""
    tcfg = run.settings
    for part in data.train_parts:
        part.set_epoch(epoch)
    gen.manual_seed(tcfg.seed * 1_000_003 + epoch)  # same shuffle for an epoch whether resumed or not
    loader = DataLoader(
        data.train,
        batch_size=tcfg.batch_size,
        shuffle=True,
        generator=gen,
        num_workers=tcfg.workers,
        drop_last=len(data.train) > tcfg.batch_size,
    )
    n_steps = len(loader) if tcfg.max_steps_per_epoch is None else min(len(loader), tcfg.max_steps_per_epoch)
    t0 = time.perf_counter()
    bar = tqdm(total=n_steps, desc=f"epoch {epoch + 1}/{tcfg.epochs}", disable=not progress, leave=False)
    total, count = _train_epoch(setup, run, opt, loader, n_steps, bar)
    train_seconds = time.perf_counter() - t0
    lr = opt.param_groups[0]["lr"]
    sched.step()
    val_loader = DataLoader(data.val, batch_size=tcfg.batch_size, shuffle=False, num_workers=tcfg.workers)
    val = setup.validate(run, val_loader) if len(data.val) else {}
    return {
        "epoch": epoch + 1,
        "lr": lr,
        "train_loss": total / max(count, 1),
        "steps": count,
        "train_seconds": train_seconds,
        "seconds_per_step": train_seconds / max(count, 1),
        **val,
    }


def _save_epoch(
    out_path: Path,
    setup: StageSetup,
    run: TrainingRun,
    data: _Data,
    opt: torch.optim.Optimizer,
    sched: torch.optim.lr_scheduler.LRScheduler,
    epoch: int,
    metrics: dict[str, float],
    *,
    init: str | Path | None,
    keep_decoding: bool,
) -> None:
    """Append the epoch's metrics to the log, rewrite the model file and the checkpoint."""
    with open(log_path(out_path), "a", encoding="utf-8") as fh:
        fh.write(json.dumps(metrics) + "\n")
    logger.info("epoch %d: %s", epoch + 1, metrics)
    extra = {
        "train": {
            **asdict(run.settings),
            "data": [str(d) for d in data.dirs],
            "samples": len(data.train),
            "init": None if init is None else str(init),
            "keep_decoding": keep_decoding and init is not None,
            # the augmentation ranges (None: off), so that a model file says how it was trained
            "augmentation": recorded_augmentation(setup, data.augment),
        },
        "metrics": metrics,
    }
    save_model(out_path, run.net, extra=extra)
    ckpt_file = checkpoint_path(out_path)
    tmp = ckpt_file.with_name(ckpt_file.name + ".tmp")
    torch.save(
        {
            "config": run.config.to_dict(),
            "state_dict": run.net.state_dict(),
            "optimizer": opt.state_dict(),
            "scheduler": sched.state_dict(),
            "epoch": epoch,
            "torch_rng": torch.get_rng_state(),
            "train": asdict(run.settings),
        },
        tmp,
    )
    tmp.replace(ckpt_file)


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
    setup = stage_setup(tcfg.stages)
    ckpt = _read_checkpoint(checkpoint_path(out_path)) if resume else None
    mcfg, init_state = _starting_config(
        ckpt, model_config, init, keep_decoding=keep_decoding, coarse_size=coarse_size
    )
    mcfg, init_state = _with_trained_stage(setup, tcfg.stages[0], mcfg, init_state)
    net = _network(mcfg, tcfg, init_state, init, device)
    opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=tcfg.lr)
    sched = torch.optim.lr_scheduler.StepLR(opt, step_size=tcfg.lr_step_epochs, gamma=tcfg.lr_gamma)
    start_epoch = 0
    if ckpt is not None:
        net.load_state_dict(ckpt["state_dict"])
        opt.load_state_dict(ckpt["optimizer"])
        sched.load_state_dict(ckpt["scheduler"])
        start_epoch = int(ckpt["epoch"]) + 1
        torch.set_rng_state(ckpt["torch_rng"])
        logger.info("resuming from %s at epoch %d", checkpoint_path(out_path), start_epoch)
    data = _data(setup, data_dir, mcfg, tcfg)
    run = TrainingRun(net, mcfg, tcfg, device, DiceLoss(sigmoid=True, batch=True))
    gen = torch.Generator().manual_seed(tcfg.seed)
    if not resume and log_path(out_path).exists():
        log_path(out_path).unlink()
    logger.info(
        "training on %d samples (%d val), %d trainable parameters, device %s",
        len(data.train), len(data.val), count_parameters(net), device,
    )  # fmt: skip
    metrics: dict[str, float] = {}
    for epoch in range(start_epoch, tcfg.epochs):
        metrics = _epoch(setup, run, data, opt, sched, gen, epoch, progress=progress)
        _save_epoch(
            out_path, setup, run, data, opt, sched, epoch, metrics, init=init, keep_decoding=keep_decoding
        )
    return metrics
