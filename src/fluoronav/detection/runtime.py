"""The detector's networks on one torch device, ready for inference, and how they are run.

:class:`Networks` holds a copy of a :class:`~fluoronav.detection.model.DetectorNet` in eval mode:
each float32 network with its batch norms folded into its convolutions and, on a CPU, its weights
channels-last and each convolution packed with its activation (the same function to float32
rounding, faster); the networks of the model's ``bf16_stages`` run as trained under bfloat16
autocast where the detector's precision is ``bfloat16``. Square views run through a network with a
dihedral test-time augmentation (:meth:`Networks.views`), tube-aligned patches with a mirror one
(:meth:`Networks.patches`); the decoding always runs in float32.
"""

from __future__ import annotations

import copy

import numpy as np
import torch
from torch import nn

from fluoronav.detection.model import DetectorNet, fold_batch_norm, pack_for_cpu
from fluoronav.device import resolve_device
from fluoronav.errors import InputError

__all__ = [
    "DIHEDRAL",
    "PRECISIONS",
    "Networks",
    "dihedral",
    "dihedral_inverse",
    "mirror_mean",
    "native_bf16",
    "resolve_precision",
]

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

#: the precisions a detector runs its networks in
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


def dihedral(x: torch.Tensor, quarter_turns: int, mirrored: bool) -> torch.Tensor:
    """(…, S, S) mirrored left-right (if asked), then turned by quarter turns."""
    y = torch.flip(x, dims=[-1]) if mirrored else x
    return torch.rot90(y, quarter_turns, dims=(-2, -1)) if quarter_turns else y


def dihedral_inverse(y: torch.Tensor, quarter_turns: int, mirrored: bool) -> torch.Tensor:
    """Undo :func:`dihedral`."""
    x = torch.rot90(y, -quarter_turns, dims=(-2, -1)) if quarter_turns else y
    return torch.flip(x, dims=[-1]) if mirrored else x


def mirror_mean(net: nn.Module, x: torch.Tensor, tta: int) -> torch.Tensor:
    """A patch network's output (N, C, rows, cols) on tube-aligned patches ``x`` (N, 1, rows, cols);
    with ``tta`` 2 averaged with its output on the patches mirrored about the tube's axis (rows
    flipped), both in one batch; float32 whatever precision the network ran in."""
    if tta == 1:
        return net(x).float()
    n = x.shape[0]
    out = net(torch.cat([x, x.flip(-2)])).float()
    return 0.5 * (out[:n] + out[n:].flip(-2))


class Networks:
    """A model's networks on one device, for inference.

    Args:
        net: the networks as trained; they stay as they are (the detector runs a copy).
        device: ``cpu``, ``cuda`` or ``auto``.
        precision: a name of :data:`PRECISIONS` (:func:`resolve_precision`): ``bfloat16`` runs the
            configuration's ``bf16_stages`` under bfloat16 autocast (faster on a CPU with native
            bfloat16, its logits a little off: docs/validation.md), ``float32`` every network in float32.
    """

    def __init__(
        self, net: DetectorNet, *, device: str | torch.device = "auto", precision: str = "float32"
    ) -> None:
        self.device = resolve_device(device)
        self.precision = resolve_precision(precision, self.device)
        names = net.config.bf16_stages if self.precision == "bfloat16" else ()
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
        self.bf16_stages = frozenset(n for n in names if getattr(self.net, n, None) is not None)

    def __getitem__(self, stage: str) -> nn.Module:
        net = getattr(self.net, stage, None)
        if not isinstance(net, nn.Module):
            raise KeyError(f"the model has no {stage} network")
        return net

    def autocast(self, stage: str) -> torch.autocast:
        """The autocast context a stage's network runs in: bfloat16 where it is one of the
        ``bf16_stages`` and the precision allows it, else off (float32)."""
        return torch.autocast(
            device_type=self.device.type, dtype=torch.bfloat16, enabled=stage in self.bf16_stages
        )

    @torch.no_grad()
    def views(self, stage: str, images: np.ndarray, *, tta: int = 1) -> torch.Tensor:
        """A view stage's outputs (N, C, S, S) float32 on normalised views (N, S, S), averaged over
        ``tta`` dihedral transforms of each view (:data:`DIHEDRAL`, each mapped back); all views
        and their transforms in one batch."""
        x = torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32))[:, None].to(self.device)
        transforms = DIHEDRAL[:tta]
        with self.autocast(stage):
            outs = self[stage](torch.cat([dihedral(x, k, f) for k, f in transforms]))
        outs, n = outs.float(), x.shape[0]  # the mean and the decoding in float32 (faster, too)
        return torch.stack(
            [dihedral_inverse(outs[i * n : (i + 1) * n], k, f) for i, (k, f) in enumerate(transforms)]
        ).mean(0)

    @torch.no_grad()
    def patches(self, stage: str, patches: np.ndarray, *, tta: int) -> torch.Tensor:
        """A patch stage's outputs (P, C, rows, cols) float32 on tube-aligned patches (P, rows, cols),
        with ``tta`` 2 averaged with those of the patches mirrored about the tube's axis (one
        batch)."""
        x = torch.from_numpy(patches)[:, None].to(self.device)
        with self.autocast(stage):
            return mirror_mean(self[stage], x, tta)
