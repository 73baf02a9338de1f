"""``fluoronav render``: the line-integral image (DRR) of a CT, optionally with the CM, for one camera."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import numpy as np
import typer

from fluoronav.anatomy.volume import MU_WATER_PER_MM, Volume, hu_to_mu
from fluoronav.cli.common import DEVICE_OPTION, SEED_OPTION
from fluoronav.errors import FluoronavError, InputError

__all__ = ["load_cm_pose", "register", "render_command", "write_png"]

logger = logging.getLogger(__name__)


def load_ct_spec(spec: str, seed: int) -> Volume:
    """The CT named on the command line: ``phantom`` or a path; raises InputError naming it."""
    from fluoronav.anatomy.io import resolve_ct  # lazy: SimpleITK, scipy

    if spec != "phantom" and not Path(spec).exists():
        raise InputError(spec, "CT file or directory not found")
    try:
        volume = resolve_ct(spec, seed=seed)
    except ValueError as exc:  # e.g. a 2D image rejected by Volume
        raise InputError(spec, f"cannot be used as a CT ({exc})") from None
    if volume.data.ndim != 3 or min(volume.data.shape) < 2:
        raise InputError(spec, f"is a 2D image (array shape {volume.data.shape}); a 3D CT volume is needed")
    if not np.all(np.isfinite(volume.spacing_mm)) or min(volume.spacing_mm) <= 0:
        raise InputError(spec, f"has no valid voxel spacing ({volume.spacing_mm})")
    return volume


def load_cm_pose(path: Path, n_control_points: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """Read CM.json: ``world_from_cm`` (4, 4) rigid and ``control_points_deg`` (n,)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read CM file ({exc.__class__.__name__})") from None
    try:
        d: Any = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(path, f"CM file is not valid JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(d, dict):
        raise InputError(path, "CM file must hold a JSON object")
    missing = [k for k in ("world_from_cm", "control_points_deg") if k not in d]
    if missing:
        raise InputError(path, f"CM file is missing {', '.join(missing)}")
    try:
        T = np.asarray(d["world_from_cm"], dtype=np.float64)
        cp = np.asarray(d["control_points_deg"], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, "world_from_cm and control_points_deg must be numeric") from None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(path, f"world_from_cm must be a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if (
        not np.allclose(R @ R.T, np.eye(3), atol=1e-5)
        or np.linalg.det(R) < 0.99
        or not np.allclose(T[3], [0, 0, 0, 1], atol=1e-9)
    ):
        raise InputError(path, "world_from_cm is not a rigid transform")
    if cp.shape != (n_control_points,) or not np.all(np.isfinite(cp)):
        raise InputError(
            path, f"control_points_deg must be {n_control_points} finite numbers, got shape {cp.shape}"
        )
    return T, cp


def write_png(path: Path, image: np.ndarray) -> None:
    """Min-max normalised 8-bit grayscale PNG (a constant image is written black)."""
    from PIL import Image  # lazy: only for --png

    lo, hi = float(np.min(image)), float(np.max(image))
    scaled = (image - lo) / (hi - lo) if hi > lo else np.zeros_like(image)
    Image.fromarray(np.clip(np.rint(scaled * 255.0), 0, 255).astype(np.uint8), mode="L").save(path)


def render_command(
    ct: str = typer.Option(..., "--ct", help="CT file/DICOM directory, or 'phantom' for the built-in hip."),
    camera: Path = typer.Option(
        ..., "--camera", help="Camera file (JSON: rows, cols, K, camera_from_world)."
    ),
    out: Path = typer.Option(..., "--out", help="Output .npy: float32 (rows, cols) line integrals."),
    png: Path | None = typer.Option(None, "--png", help="Also write a min-max normalised 8-bit PNG."),
    mu_water: float = typer.Option(
        MU_WATER_PER_MM, "--mu-water", help="μ of water in 1/mm; μ = MU·max(0, 1 + HU/1000)."
    ),
    cm: Path | None = typer.Option(
        None, "--cm", help="CM.json with world_from_cm (4x4) and control_points_deg."
    ),
    seed: int = SEED_OPTION,
    device: str = DEVICE_OPTION,
) -> None:
    """Render the line-integral image ∫μ dl of a CT (and the CM) for one camera."""
    from fluoronav.device import resolve_device  # heavy: torch
    from fluoronav.geometry.camera import Camera  # lazy: fast --help
    from fluoronav.manipulator.config import CMConfig  # lazy: fast --help
    from fluoronav.rendering.ct import CTRenderer  # lazy: fast --help

    if not math.isfinite(mu_water) or mu_water <= 0:
        raise InputError("--mu-water", f"must be a positive number of 1/mm, got {mu_water}")
    dev = resolve_device(device)
    cam = Camera.load(camera)
    config = CMConfig.model_validate({})  # paper defaults
    cm_pose = load_cm_pose(cm, config.n_control_points) if cm is not None else None
    volume = load_ct_spec(ct, seed)
    logger.info(
        "rendering %s (%s) for a %dx%d camera on %s", volume.name, volume.data.shape, cam.rows, cam.cols, dev
    )
    image = CTRenderer.from_hu(volume, mu_water_per_mm=mu_water, device=dev).render([cam])[0]
    if cm_pose is not None:
        import torch  # heavy: torch

        try:
            from fluoronav.rendering.cm import CMRenderer  # lazy: fast --help
        except ModuleNotFoundError as exc:
            if exc.name != "fluoronav.rendering.cm":
                raise
            raise FluoronavError("CM rendering (fluoronav.rendering.cm) is not available") from None
        world_from_cm, cp = cm_pose
        mu_cm = float(hu_to_mu(np.asarray(config.hu_value), mu_water))
        camera_from_cm = cam.camera_from_world @ world_from_cm
        cm_img = CMRenderer(config, mu_per_mm=mu_cm, device=dev).render(
            torch.as_tensor(camera_from_cm, dtype=torch.float64, device=dev)[None, None],
            torch.as_tensor(cp, dtype=torch.float64, device=dev)[None],
            torch.as_tensor(cam.K, dtype=torch.float64, device=dev)[None],
            cam.rows,
            cam.cols,
        )[0, 0]
        image = image + cm_img.to(image)
    result = image.detach().cpu().numpy().astype(np.float32)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.save(out, result)
    if png is not None:
        png.parent.mkdir(parents=True, exist_ok=True)
        write_png(png, result)
    typer.echo(f"wrote {out} ({cam.rows}x{cam.cols}, max {float(result.max()):.4g})")


def register(app: typer.Typer) -> None:
    """Add ``render`` to the app."""
    app.command("render")(render_command)
