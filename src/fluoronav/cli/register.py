"""``fluoronav register CASE --out DIR``: CM 2D/3D registration of a case file (docs/registration.md)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import typer

from fluoronav.cli.common import DEVICE_OPTION, SEED_OPTION


def run_case(case_path: Path, out: Path, *, seed: int = 0, device: str = "cpu") -> dict[str, Any]:
    """Register a case file and write ``result.json``, ``trace.json`` and ``overlay_<view>.png``.

    Returns:
        the ``result.json`` content.
    """
    from fluoronav.cli.register_case import load_case  # lazy: fast --help
    from fluoronav.device import resolve_device  # heavy: torch
    from fluoronav.registration.cm import cm_pose_errors, register_cm, save_overlays  # lazy: fast --help

    case = load_case(case_path)
    config = case.config.with_(device=str(resolve_device(device)))
    res = register_cm(
        case.views,
        initial_world_from_cm=case.initial_world_from_cm,
        initial_control_points_deg=case.initial_control_points_deg,
        base_from_cm=case.base_from_cm,
        config=config,
        seed=seed,
    )
    out.mkdir(parents=True, exist_ok=True)
    d = res.to_dict()
    d["case"] = str(case_path)
    d["seed"] = seed
    d["detected_landmarks_px"] = {
        v.name: (None if v.landmarks_px is None else np.asarray(v.landmarks_px).tolist()) for v in case.views
    }
    if case.world_from_cm_true is not None and case.control_points_true_deg is not None:
        errs = [
            cm_pose_errors(
                W, res.control_points_deg, Wt, case.control_points_true_deg, cm_config=config.cm_config
            )
            for W, Wt in zip(res.world_from_cm, case.world_from_cm_true, strict=True)
        ]
        d["errors"] = {k: float(np.mean([e[k] for e in errs])) for k in errs[0]}
        if len(errs) > 1:
            d["errors_per_pose"] = errs
    (out / "result.json").write_text(json.dumps(d, indent=1, allow_nan=False), encoding="utf-8")
    res.trace.to_json(out / "trace.json")
    save_overlays(res, out)
    return d


def register_command(
    case: Path = typer.Argument(..., help="Case file (JSON), see docs/registration.md."),
    out: Path = typer.Option(..., "--out", help="Output directory (result.json, trace.json, overlays)."),
    seed: int = SEED_OPTION,
    device: str = DEVICE_OPTION,
) -> None:
    """Register the CM (pose and shape) to the case's X-ray images."""
    d = run_case(case, out, seed=seed, device=device)
    msg = f"{d['workflow']}: {d['reason']} in {d['seconds']:.1f} s"
    if "errors" in d:
        msg += f"; tip error {d['errors']['tip_error_mm']:.2f} mm"
    typer.echo(f"{msg} -> {out / 'result.json'}")


def register(app: typer.Typer) -> None:
    app.command("register")(register_command)
