"""``fluoronav deepfluoro``: one image of the user's DeepFluoro file registered, with files to see it."""

from __future__ import annotations

from pathlib import Path

import typer

from fluoronav.cli.common import DEVICE_OPTION, SEED_OPTION


def register(app: typer.Typer) -> None:
    @app.command("deepfluoro")
    def deepfluoro(
        data: Path = typer.Option(
            ..., "--data", help="The DeepFluoro HDF5 file (your download; docs/real-data.md)."
        ),
        specimen: str = typer.Option(None, "--specimen", help="Specimen ID or the paper's number 1–6."),
        projection: int = typer.Option(None, "--projection", min=0, help="Image number within the specimen."),
        out: Path = typer.Option(Path("deepfluoro_out"), "--out", help="Output directory."),
        femurs: bool = typer.Option(
            True, "--femurs/--no-femurs", help="Also register the femurs after the pelvis."
        ),
        xreg_gt_correction: bool = typer.Option(
            False,
            "--xreg-gt-correction",
            help="Shift the ground truth by −0.5 mm per CT axis, as xReg's samples do.",
        ),
        seed: int = SEED_OPTION,
        device: str = DEVICE_OPTION,
    ) -> None:
        """Register the pelvis and femurs in one DeepFluoro image; write registration.json, overlay.png
        and slicer/. Without --specimen and --projection: list what the file holds."""
        from fluoronav.anatomy.deepfluoro import DeepFluoroFile  # lazy: fast --help

        if specimen is None or projection is None:
            with DeepFluoroFile(data) as f:
                for s in f.specimens:
                    idx = f.projection_indices(s)
                    typer.echo(
                        f"{s}: {len(idx)} projections ({idx[0]:03d}–{idx[-1]:03d})" if idx else f"{s}: none"
                    )
            return
        from fluoronav.device import resolve_device  # heavy: torch
        from fluoronav.studies.deepfluoro_view import register_projection, write_projection_outputs

        reg = register_projection(
            data,
            specimen,
            projection,
            seed=seed,
            device=str(resolve_device(device)),
            femurs=femurs,
            xreg_texture_correction=xreg_gt_correction,
        )
        write_projection_outputs(reg, out)
        e = reg.errors
        femur = "".join(f", femur {s} {e[f'femur_{s}_rotation_deg']:.2f}°" for s in reg.world_from_femur)
        typer.echo(
            f"{reg.specimen}/{reg.index:03d}: pelvis rotation {e['rotation_deg']:.2f}°, "
            f"mTRE {e['mtre_mm']:.2f} mm{femur}; wrote {out}"
        )
