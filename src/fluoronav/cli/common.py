"""Options and helpers shared by the commands."""

from __future__ import annotations

import typer

SEED_OPTION = typer.Option(0, "--seed", help="Random seed; the same seed gives the same output.")
DEVICE_OPTION = typer.Option("auto", "--device", help="cpu, cuda or auto (CUDA when available).")
PRECISION_OPTION = typer.Option(
    "float32",
    "--precision",
    help=(
        "Detector networks: float32; bfloat16 (the model's bf16_stages, faster on a CPU with native "
        "bfloat16, slightly different results); auto (bfloat16 where the CPU has it, else float32)."
    ),
)
