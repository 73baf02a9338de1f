"""Rendering benchmarks (``fluoronav bench``): each ``run_*`` returns figure keys with baselines.

Add a renderer's benchmark by writing ``run_<name>(quick: bool, device: str) -> dict[str, float]``
here and appending it to :data:`BENCHMARKS`; :func:`run` merges them all. Each figure and its
baseline run on the same device (``fluoronav bench --device``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from fluoronav.anatomy.volume import Volume
from fluoronav.bench.rendering_cm import run_cm
from fluoronav.bench.timing import time_ms
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.carm import carm_camera_from_world

__all__ = ["BENCHMARKS", "bench_camera", "bench_volume", "run", "run_ct"]

logger = logging.getLogger(__name__)


def bench_volume(
    *,
    seed: int = 0,
    shape_zyx: tuple[int, int, int] = (133, 512, 512),
    spacing_mm: tuple[float, float, float] = (0.7, 0.7, 2.0),
) -> Volume:
    """A smooth random μ phantom (1/mm, float32): an elliptic body of soft tissue with smooth
    random texture and a few dense ellipsoids, centred on the world origin."""
    rng = np.random.default_rng(seed)
    nz, ny, nx = shape_zyx
    sx, sy, sz = spacing_mm
    x = ((np.arange(nx) - (nx - 1) / 2) * sx).astype(np.float32)[None, None, :]
    y = ((np.arange(ny) - (ny - 1) / 2) * sy).astype(np.float32)[None, :, None]
    z = ((np.arange(nz) - (nz - 1) / 2) * sz).astype(np.float32)[:, None, None]
    ax, ay = 0.45 * nx * sx, 0.35 * ny * sy
    body = ((x / ax) ** 2 + (y / ay) ** 2 <= 1.0).astype(np.float32)
    texture = np.ones((1, 1, 1), np.float32)
    for _ in range(3):
        k = rng.uniform(0.01, 0.05, size=3).astype(np.float32)
        ph = rng.uniform(0, 2 * np.pi, size=3).astype(np.float32)
        texture = texture + np.float32(0.1) * np.sin(k[0] * x + ph[0]) * np.sin(k[1] * y + ph[1]) * np.sin(
            k[2] * z + ph[2]
        )
    data = np.float32(0.02) * body * texture
    for _ in range(4):
        c = rng.uniform(-0.5, 0.5, size=3) * np.array([ax, ay, 0.4 * nz * sz])
        r = rng.uniform(15.0, 40.0, size=3)
        inside = ((x - c[0]) / r[0]) ** 2 + ((y - c[1]) / r[1]) ** 2 + ((z - c[2]) / r[2]) ** 2 <= 1.0
        data = data + np.float32(0.03) * inside
    origin = -np.array([(nx - 1) * sx, (ny - 1) * sy, (nz - 1) * sz]) / 2
    return Volume(
        np.ascontiguousarray(data, dtype=np.float32),
        spacing_mm=(sx, sy, sz),
        origin_mm=tuple(origin),
        name=f"bench-{seed}",
    )


def bench_camera(
    volume: Volume, *, size: int = 128, sdd_mm: float = 1020.0, source_to_isocenter_mm: float = 700.0
) -> Camera:
    """AP C-arm view (source posterior) of ``volume`` at ``sdd_mm`` whose field of view at the
    isocentre (the volume centre) spans the volume's largest lateral extent."""
    extent = float(np.ptp(volume.corners_world(), axis=0)[:2].max())
    pixel_mm = extent * sdd_mm / source_to_isocenter_mm / size
    f = sdd_mm / pixel_mm
    K = np.array([[f, 0.0, (size - 1) / 2], [0.0, f, (size - 1) / 2], [0.0, 0.0, 1.0]])
    T = carm_camera_from_world(
        lao_rao_deg=0.0,
        cran_caud_deg=90.0,
        source_to_isocenter_mm=source_to_isocenter_mm,
        isocenter_world=volume.center_world,
    )
    return Camera(size, size, K, T, pixel_mm)


def run_ct(quick: bool, device: str = "cpu") -> dict[str, float]:
    """``ct_drr_128_ms``: 128×128 DRR of a 512×512×133 float32 volume (0.7×0.7×2 mm) on ``device``
    (the renderer's default backend there: numba on the CPU, torch on CUDA; default step and
    mipmap, volume and mipmap prepared beforehand), median after warm-up/compilation;
    ``ct_drr_128_ms_baseline``: the plain torch grid_sample ray march at 1-voxel (0.7 mm) steps on
    the full-resolution volume, same camera, same device, same run. ``ct_drr_128_ms_nomipmap`` is
    the default backend at its default step without the mipmap."""
    from fluoronav.rendering.ct import CTRenderer

    volume = bench_volume()
    camera = bench_camera(volume)
    repeats = 5 if quick else 15
    fast = CTRenderer(volume, device=device)
    full = CTRenderer(volume, device=device, mipmap=False)
    base = CTRenderer(volume, device=device, backend="torch", mipmap=False, step_mm=min(volume.spacing_mm))
    ms = time_ms(lambda: fast.render([camera]), repeats=repeats, warmup=2, device=device)
    ms_full = time_ms(lambda: full.render([camera]), repeats=repeats, warmup=1, device=device)
    ms_base = time_ms(lambda: base.render([camera]), repeats=1 if quick else 3, warmup=1, device=device)
    # the two renders agree (sanity, not timed): mipmapping preserves the line integrals
    a, b = fast.render([camera]), base.render([camera])
    rel = float((a - b).abs().max() / b.abs().max())
    logger.info(
        "ct_drr_128: %.1f ms (no mipmap %.1f ms), baseline %.1f ms, max rel diff %.3g",
        ms,
        ms_full,
        ms_base,
        rel,
    )
    return {
        "ct_drr_128_ms": ms,
        "ct_drr_128_ms_baseline": ms_base,
        "ct_drr_128_ms_speedup": ms_base / ms,
        "ct_drr_128_ms_nomipmap": ms_full,
        "ct_drr_128_max_rel_diff_vs_baseline": rel,
    }


#: every rendering benchmark; :func:`run` calls each in turn
BENCHMARKS: list[Callable[[bool, str], dict[str, float]]] = [run_ct, run_cm]


def run(quick: bool, device: str = "cpu") -> dict[str, float]:
    """All rendering benchmarks on ``device`` merged into one dict (each benchmark function runs once)."""
    results: dict[str, float] = {}
    for bench in dict.fromkeys(BENCHMARKS):  # each function once, in order
        results.update(bench(quick, device))
    return results
