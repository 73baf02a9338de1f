"""The training losses of the detector's stages.

View stages (coarse, fine; :func:`stage_loss`): MONAI ``DiceLoss`` (sigmoid, batch-wise, so that negatives'
false positives count) on the segmentation logit, plus by default a binary cross-entropy term (the paper, Gao
et al., IEEE TBME 69(1), 2022, uses Dice alone, which converges much more slowly from random weights), plus
the heatmap loss: the cross-entropy of spatial-softmax heatmaps
(:func:`~fluoronav.detection.heatmaps.heatmap_cross_entropy`), or for peak-1 Gaussian heatmaps the paper's L2
error ``Σ (1 + fg·t)(h − t)² / (B · 2 · π σ²)``, a sum of squares scaled by the Gaussian's energy πσ² so that
it stays comparable to the Dice term, with pixels near the landmark weighted up (fg) so the peaks are learned
before the network settles on predicting zeros. Refinement (:func:`refine_loss`): the cross-entropy of its
heatmaps. Patch-mask stages (:func:`ends_loss`): binary cross-entropy + Dice on the patch masks.
"""

from __future__ import annotations

import math

import torch
from monai.losses import DiceLoss
from torch import nn
from torch.nn import functional as tnf

from fluoronav.detection.config import DetectorConfig
from fluoronav.detection.heatmaps import gaussian_heatmaps, heatmap_cross_entropy
from fluoronav.detection.model import DetectorNet

__all__ = ["detector_loss", "ends_loss", "ends_outputs", "refine_loss", "refine_outputs", "stage_loss"]


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
    """Segmentation + heatmap loss of one view stage: out (B, 3, S, S), mask (B, 1, S, S), landmarks
    (B, 2, 2) view px (NaN: absent) → the loss and its parts (``dice_loss``, ``heatmap_loss``).

    Heatmaps: cross-entropy of the spatial softmax (``heatmap_mode="softmax"``) or the weighted L2 of
    peak-1 Gaussians (``"gaussian"``).
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
    *,
    dice: DiceLoss,
    heatmap_weight: float,
    fg_weight: float = 0.0,
    bce_weight: float = 0.0,
) -> torch.Tensor:
    """Sum of the :func:`stage_loss` of each view stage in ``outputs`` (stage name → (B, 3, S, S)) on
    a batch (``<stage>_mask`` (B, 1, S, S), ``<stage>_landmarks`` (B, 2, 2)), each with its own
    decoder's heatmap kind and σ."""
    total = next(iter(outputs.values())).new_zeros(())
    for stage, out in outputs.items():
        decoder = cfg.coarse.decoder if stage == "coarse" else cfg.fine.decoder
        loss, _ = stage_loss(
            out,
            batch[f"{stage}_mask"].to(device),
            batch[f"{stage}_landmarks"].to(device),
            sigma_px=decoder.sigma_px,
            heatmap_weight=heatmap_weight,
            dice=dice,
            fg_weight=fg_weight,
            bce_weight=bce_weight,
            heatmap_mode=decoder.heatmap,
        )
        total = total + loss
    return total


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
    assert cfg.refine is not None
    sel, target = refine_outputs(net, batch, device)
    return heatmap_cross_entropy(sel, target, sigma_px=cfg.refine.decoder.sigma_px)


def ends_outputs(
    stage: nn.Module, batch: dict[str, torch.Tensor], device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """Patch mask logits (N, 1, rows, cols) of a patch-mask ``stage`` network and true patch masks
    (N, 1, rows, cols) of the patches that exist (N ≤ 2 × the batch)."""
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
