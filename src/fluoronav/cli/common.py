"""Options and helpers shared by the commands."""

from __future__ import annotations

import typer

SEED_OPTION = typer.Option(0, "--seed", help="Random seed; the same seed gives the same output.")
DEVICE_OPTION = typer.Option("auto", "--device", help="cpu, cuda or auto (CUDA when available).")
