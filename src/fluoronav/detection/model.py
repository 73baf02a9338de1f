"""The detector's networks and its model files.

Every network stage is a 2-D MONAI ``UNet``: the coarse and fine stages output 3 channels (a segmentation
logit of the CM's notched region and the heatmaps of A = CM base origin and B = distal end of the last notch,
as in Gao et al., IEEE TBME 69(1), 2022), the refinement stage 2 (heatmaps of A and B on tube-aligned
patches), the tube-mask, mask-end and shaft stages 1 (a mask logit). :class:`DetectorNet` holds the networks
of a :class:`~fluoronav.detection.config.DetectorConfig`'s stages; for inference each float32 network gets its
batch norms folded into its convolutions (:func:`fold_batch_norm`) and, on a CPU, each convolution and its
activation packed into one oneDNN call (:func:`pack_for_cpu`). A model file (``torch.save`` of a dict) holds
``format_version``, ``config``, ``normalization``, ``parameters``, the training record and ``state_dict``; its
JSON sidecar holds the same without the weights.
"""

from __future__ import annotations

import copy
import json
from importlib import resources
from pathlib import Path
from typing import Any

import torch
from monai.networks.nets import UNet
from torch import nn
from torch.nn import functional as tnf
from torch.nn.utils import fuse_conv_bn_eval

from fluoronav import __version__
from fluoronav.detection.config import NETWORK_STAGES, DetectorConfig, NetworkConfig
from fluoronav.errors import FluoronavError, InputError

__all__ = [
    "MODEL_FORMAT_VERSION",
    "DetectorConfig",
    "DetectorNet",
    "PackedConvolution",
    "build_unet",
    "count_parameters",
    "fold_batch_norm",
    "load_net",
    "pack_for_cpu",
    "save_model",
    "shipped_model_path",
    "sidecar_path",
]

#: version of the model file layout: 2 holds the declared configuration; 1 held a flat one, read no
#: longer (``tools/convert_flat_detector.py`` converts it)
MODEL_FORMAT_VERSION = 2

SHIPPED_MODEL_NAME = "detector.pt"

#: each network stage's output channels
OUT_CHANNELS = {"coarse": 3, "fine": 3, "refine": 2, "ends": 1, "tube": 1, "shaft": 1}


def shipped_model_path() -> Path:
    """Where the shipped weights live inside the installed package."""
    return Path(str(resources.files("fluoronav") / "data" / SHIPPED_MODEL_NAME))


def sidecar_path(model_path: Path) -> Path:
    """The JSON sidecar of a model file: the file without its weights."""
    return model_path.with_suffix(".json")


def build_unet(network: NetworkConfig, *, out_channels: int = 3) -> nn.Module:
    """2-D MONAI U-Net of ``network``'s levels, 1 input channel → ``out_channels``.

    Input (B, 1, H, W) with H, W divisible by ``network.divisor``; output (B, out_channels, H, W).
    """
    return UNet(
        spatial_dims=2,
        in_channels=1,
        out_channels=out_channels,
        channels=tuple(network.channels),
        strides=(2,) * (len(network.channels) - 1),
        num_res_units=network.num_res_units,
        norm="batch",
    )


class DetectorNet(nn.Module):
    """The networks of a configuration's stages, as attributes named after them (None for a network
    stage not listed): ``coarse`` and ``fine`` (B, 1, S, S) → (B, 3, S, S), ``refine`` (B, 1, rows,
    cols) → (B, 2, rows, cols), ``ends``, ``tube`` and ``shaft`` (B, 1, rows, cols) → (B, 1, rows,
    cols)."""

    coarse: nn.Module
    fine: nn.Module
    refine: nn.Module | None
    ends: nn.Module | None
    tube: nn.Module | None
    shaft: nn.Module | None

    def __init__(self, config: DetectorConfig | None = None) -> None:
        super().__init__()
        self.config = config or DetectorConfig()
        listed = self.config.network_stages
        for name in NETWORK_STAGES:  # in this order: the random initialisation follows it
            net = None
            if name in listed:
                net = build_unet(self.config.network(name), out_channels=OUT_CHANNELS[name])
                if name in ("coarse", "fine"):
                    _init_head(net)
            setattr(self, name, net)

    def forward(self, coarse: torch.Tensor, fine: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 1, S_coarse²), (B, 1, S_fine²) → their (B, 3, ·, ·) outputs."""
        return self.coarse(coarse), self.fine(fine)


def fold_batch_norm(module: nn.Module) -> nn.Module:
    """Fold each batch norm that directly follows a convolution (MONAI ``Convolution`` blocks,
    ``conv`` then ``adn`` with the norm first) into that convolution's weights and bias, in place;
    returns ``module``. For inference only: ``module`` must be in eval mode (running statistics).

    The folded network computes the same function to float32 rounding (logits within ~1e-5 of
    the unfolded ones) without a separate pass over the activations per batch norm (the gain:
    docs/validation.md, "Speed"). Its ``state_dict`` has no batch-norm entries, so it cannot be
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
    the activation as a separate pass; here neither (docs/validation.md, "Speed"). The
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


def load_net(path: str | Path | None = None) -> DetectorNet:
    """The networks of a model file written by ``fluoronav train`` (None: the shipped weights), as
    trained (batch norms unfolded, train mode), validated: a missing, damaged or foreign file raises
    :class:`~fluoronav.errors.InputError` naming it, and so does a file of format 1 (the flat
    configuration; ``tools/convert_flat_detector.py`` converts it). The weights of networks that the
    configuration does not list are left aside."""
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
    if int(blob.get("format_version", 0)) < MODEL_FORMAT_VERSION:
        raise InputError(
            path,
            f"model format {blob.get('format_version', 0)} (a flat configuration) is read no longer; "
            "convert it with tools/convert_flat_detector.py",
        )
    try:
        net = DetectorNet(DetectorConfig.from_dict(blob["config"]))
        listed = net.config.network_stages
        state = {k: v for k, v in blob["state_dict"].items() if k.split(".", 1)[0] in listed}
        net.load_state_dict(state)
    except (RuntimeError, TypeError, ValueError) as exc:
        raise InputError(
            path, f"weights do not match the model configuration ({exc.__class__.__name__})"
        ) from exc
    return net


def save_model(path: Path, net: DetectorNet, *, extra: dict[str, Any]) -> None:
    """Write the model file (state_dict + declared config + normalisation + version) and its JSON
    sidecar (:func:`sidecar_path`)."""
    cfg = net.config
    sampler = cfg.coarse.sampler
    meta = {
        "format_version": MODEL_FORMAT_VERSION,
        "fluoronav_version": __version__,
        "config": cfg.to_dict(),
        "normalization": {"method": "percentile", "low_pct": sampler.low_pct, "high_pct": sampler.high_pct},
        # the whole model's size, also when one stage was frozen for this run
        "parameters": count_parameters(net, trainable_only=False),
        **extra,
    }
    state = {k: v.detach().cpu() for k, v in net.state_dict().items()}
    tmp = path.with_name(path.name + ".tmp")
    torch.save({**meta, "state_dict": state}, tmp)
    tmp.replace(path)
    sidecar_path(path).write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
