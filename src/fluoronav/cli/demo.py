"""``fluoronav demo``: the main job on the built-in phantom, no files needed.

Current scope (foundations): builds the hip phantom, places the CM in the femur as for core
decompression, renders three C-arm views (AP and two orbit rotations) of the anatomy with the CM,
and writes the DRRs (PNG and .npy), the cameras and the scene.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np
import typer

from fluoronav.cli.common import DEVICE_OPTION, SEED_OPTION

log = logging.getLogger(__name__)


def _to_png(image: np.ndarray, path: Path) -> None:
    import matplotlib.pyplot as plt

    lo, hi = np.percentile(image, [0.5, 99.8])
    plt.imsave(path, np.clip((image - lo) / max(hi - lo, 1e-9), 0, 1), cmap="gray", vmin=0, vmax=1)


def run_render_demo(out: Path, *, seed: int, device: str) -> dict[str, object]:
    """Render the phantom with a CM in three views; returns a summary dict (also written as JSON)."""
    import torch
    from rich.console import Console
    from rich.table import Table

    from fluoronav.anatomy.io import resolve_ct
    from fluoronav.geometry import orbit_camera
    from fluoronav.manipulator import CMConfig, CMKinematics
    from fluoronav.rendering.cm import CMRenderer
    from fluoronav.rendering.ct import CTRenderer
    from fluoronav.simulation.scene import SceneSampling, place_cm_in_bone

    out.mkdir(parents=True, exist_ok=True)
    console = Console(stderr=True)
    timings: dict[str, float] = {}
    rng = np.random.default_rng(seed)

    t0 = time.perf_counter()
    volume = resolve_ct("phantom", seed=seed)
    timings["phantom_s"] = time.perf_counter() - t0

    config = CMConfig()
    world_from_cm, side = place_cm_in_bone(volume, rng, SceneSampling())
    cp = rng.uniform(-4.0, 4.0, size=5)
    kin = CMKinematics(config)
    mid = (world_from_cm @ np.array([0.0, 0.0, config.tip_z_mm / 2, 1.0]))[:3]

    from fluoronav.geometry import carm_camera

    ap = carm_camera(source_to_isocenter_mm=450.0, isocenter_world=mid)
    views = {
        "ap": ap,
        "orbit_p20": orbit_camera(ap, angle_deg=20.0, isocenter_world=mid),
        "orbit_m15": orbit_camera(ap, angle_deg=-15.0, isocenter_world=mid),
    }
    mu_water = 0.02
    t0 = time.perf_counter()
    ct = CTRenderer.from_hu(volume, mu_water_per_mm=mu_water, device=device)
    cm = CMRenderer(config, mu_per_mm=mu_water * (1.0 + config.hu_value / 1000.0), device=device)
    timings["setup_s"] = time.perf_counter() - t0

    table = Table(title="fluoronav demo: DRRs of the hip phantom with a CM")
    for col in ("view", "full DRR ms", "ROI DRR ms", "CM ms"):
        table.add_column(col)
    cp_t = torch.as_tensor(cp, dtype=torch.float32)[None]
    for name, cam in views.items():
        full = cam.scaled_to(384, 384)
        t0 = time.perf_counter()
        drr_full = ct.render([full])[0]
        t_full = (time.perf_counter() - t0) * 1e3
        # region of interest around the CM at half resolution (0.388 mm pixels)
        centre_uv = cam.project(mid)
        roi, _ = cam.crop_around(centre_uv, 600)
        roi = roi.downsample(2)
        t0 = time.perf_counter()
        drr_roi = ct.render([roi])[0]
        t_roi = (time.perf_counter() - t0) * 1e3
        K = torch.as_tensor(roi.K, dtype=torch.float32)[None]
        T = torch.as_tensor(roi.camera_from_world @ world_from_cm, dtype=torch.float32)[None, None]
        t0 = time.perf_counter()
        drr_cm = cm.render(T, cp_t, K, roi.rows, roi.cols)[0, 0]
        t_cm = (time.perf_counter() - t0) * 1e3
        T_full = torch.as_tensor(full.camera_from_world @ world_from_cm, dtype=torch.float32)[None, None]
        cm_full = cm.render(
            T_full, cp_t, torch.as_tensor(full.K, dtype=torch.float32)[None], full.rows, full.cols
        )[0, 0]
        img_full = (drr_full + cm_full).cpu().numpy()
        img_roi = (drr_roi + drr_cm).cpu().numpy()
        np.save(out / f"{name}_drr.npy", img_full.astype(np.float32))
        _to_png(img_full, out / f"{name}_drr.png")
        _to_png(img_roi, out / f"{name}_roi.png")
        full.save(out / f"{name}_camera.json")
        table.add_row(name, f"{t_full:.1f}", f"{t_roi:.1f}", f"{t_cm:.1f}")
    console.print(table)
    lm = kin.landmarks_cm(torch.as_tensor(cp)[None].double())[0].numpy()
    summary = {
        "seed": seed,
        "volume": volume.name,
        "femur_side": side,
        "world_from_cm": world_from_cm.tolist(),
        "control_points_deg": cp.tolist(),
        "landmarks_cm_mm": lm.tolist(),
        "timings": timings,
        "views": list(views),
    }
    (out / "scene.json").write_text(json.dumps(summary, indent=2), encoding="utf-8")
    return summary


def register(app: typer.Typer) -> None:
    @app.command("demo")
    def demo(
        out: Path = typer.Option(Path("demo_out"), "--out", help="Output directory."),
        seed: int = SEED_OPTION,
        device: str = DEVICE_OPTION,
    ) -> None:
        """Run the main job on the built-in phantom (no files needed) and write the results to --out."""
        run_render_demo(out, seed=seed, device=device)
        typer.echo(f"wrote {out}/")
