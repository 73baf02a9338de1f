"""Device selection shared by every command that can use a GPU (``--device cpu|cuda|auto``)."""

from __future__ import annotations

import torch

from fluoronav.errors import InputError


def resolve_device(name: str | torch.device = "auto") -> torch.device:
    """Return the torch device for ``cpu``, ``cuda`` or ``auto`` (CUDA when available, else CPU)."""
    if isinstance(name, torch.device):
        return name
    key = str(name).lower()
    if key == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if key == "cpu":
        return torch.device("cpu")
    if key.startswith("cuda"):
        if not torch.cuda.is_available():
            raise InputError("--device", "CUDA was requested but no CUDA device is available")
        return torch.device(key)
    raise InputError("--device", f"unknown device {name!r}; use cpu, cuda or auto")


def synchronize(device: str | torch.device) -> None:
    """Wait for the work queued on ``device`` (a no-op on the CPU): timings of CUDA work need it."""
    dev = resolve_device(device)
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)
