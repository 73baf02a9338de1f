"""Simulated data sets (``fluoronav simulate``): resumable, parallel, reproducible per seed.

Layout (docs/simulation.md, "Data set format"): ``DIR/manifest.jsonl`` (one object per sample,
appended as samples finish), ``DIR/samples/<id>.npz`` (``image``, ``mask``, ``landmarks_px``),
``DIR/dataset.json`` (the run's configuration) and ``DIR/contact_sheet.png``. Sample ``i``
depends only on the run seed and ``i``: its seed picks the anatomy (phantom seed or CT) and the
scene, so the same seed gives the same samples for any number of workers, and a rerun skips
finished samples.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from fluoronav import __version__
from fluoronav.anatomy.io import resolve_ct
from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError
from fluoronav.geometry.camera import Camera
from fluoronav.runner import JsonlLog, run_tasks
from fluoronav.simulation.scene import SceneSampling, sample_scene
from fluoronav.simulation.xray import SimulatedImage, SimulationConfig, XraySimulator

log = logging.getLogger(__name__)

__all__ = [
    "MANIFEST_KEYS",
    "DatasetSpec",
    "check_dataset",
    "contact_sheet",
    "simulate_dataset",
    "write_sample",
]


@dataclasses.dataclass(frozen=True)
class DatasetSpec:
    """What to simulate.

    Attributes:
        cts: CT specs (``"phantom"`` or paths); samples cycle through anatomies deterministically.
        n_phantoms: distinct phantom anatomies (phantom seeds) per ``"phantom"`` spec.
        with_cm: False makes negatives (same scenes, no CM).
        image_size: stored rows = cols.
        seed: run seed.
        device: torch device name for rendering.
        phantom_spacing_mm: voxel size of the procedural phantoms (1 mm; coarser only for fast tests).
        max_projected_ab_mm: keep only foreshortened views, whose landmarks A and B project at most
            this far apart on the detector (mm); None: the paper's distribution as it is.
        max_projected_shaft_mm: keep only views whose mounting shaft projects at most this long on
            the detector (mm; a shaft seen nearly along its axis); None: every view.
        max_shaft_angle_deg: keep only views where the CM's chord A → B and its mounting shaft meet
            at A at most this angle on the detector (degrees; ~180 where the shaft goes on behind
            the CM, 20–70 a V, under 35 the CM over its shaft); None: every view.
        shaft_length_mm: length of the rigid tube the CM is mounted on
            (:attr:`SimulationConfig.shaft_length_mm`; 0: the bare CM). The default 50 mm tube ends
            in the field; a robot's shaft that runs out of the field is ~200 mm or more.
    """

    cts: tuple[str, ...] = ("phantom",)
    n_phantoms: int = 4
    with_cm: bool = True
    image_size: int = 512
    seed: int = 0
    device: str = "cpu"
    phantom_spacing_mm: float = 1.0
    max_projected_ab_mm: float | None = None
    shaft_length_mm: float = 50.0
    max_projected_shaft_mm: float | None = None
    max_shaft_angle_deg: float | None = None

    def __post_init__(self) -> None:
        if not self.shaft_length_mm >= 0.0:
            raise ValueError(f"shaft_length_mm must be >= 0, got {self.shaft_length_mm}")
        _ = self.sampling  # SceneSampling validates the limits: fail here, before any worker starts

    @property
    def sampling(self) -> SceneSampling:
        """The scene sampler of this data set."""
        return SceneSampling(
            max_projected_ab_mm=self.max_projected_ab_mm,
            max_projected_shaft_mm=self.max_projected_shaft_mm,
            max_shaft_angle_deg=self.max_shaft_angle_deg,
            shaft_length_mm=self.shaft_length_mm,
        )

    def anatomies(self) -> list[tuple[str, int]]:
        """(ct spec, phantom seed) pairs; the phantom seeds come from the run seed."""
        out: list[tuple[str, int]] = []
        for ct in self.cts:
            if ct == "phantom":
                out += [("phantom", 1000 * self.seed + k) for k in range(self.n_phantoms)]
            else:
                out.append((ct, 0))
        return out


@functools.lru_cache(maxsize=4)
def _simulator(
    ct: str,
    phantom_seed: int,
    image_size: int,
    device: str,
    phantom_spacing_mm: float = 1.0,
    shaft_length_mm: float = 50.0,
) -> XraySimulator:
    """One simulator per anatomy and worker process (building one costs seconds; kept for reuse)."""
    if ct == "phantom":
        volume = hip_phantom(seed=phantom_seed, spacing_mm=phantom_spacing_mm)
    else:
        volume = resolve_ct(ct, seed=phantom_seed)
    config = SimulationConfig(image_size=image_size, shaft_length_mm=shaft_length_mm)
    return XraySimulator(volume, config=config, device=device)


def _volume_name(volume: Volume, ct: str) -> str:
    return volume.name if ct == "phantom" else Path(ct).name


def write_sample(
    out_dir: Path, sample_id: int, sim: SimulatedImage, *, seed: int, ct_name: str
) -> dict[str, Any]:
    """Write one sample's npz and return its manifest row."""
    rel = f"samples/{sample_id:06d}.npz"
    path = out_dir / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    lm = sim.landmarks_px
    lm_arr = np.full((2, 2), np.nan) if lm is None else lm
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(
        tmp,
        image=sim.image.astype(np.float32),
        mask=sim.mask.astype(np.uint8),
        landmarks_px=lm_arr.astype(np.float64),
    )
    os.replace(tmp, path)  # a crash never leaves a half-written sample under its final name
    scene = sim.scene
    return {
        "id": sample_id,
        "file": rel,
        "rows": sim.camera.rows,
        "cols": sim.camera.cols,
        "pixel_spacing_mm": sim.camera.pixel_spacing_mm,
        "landmarks_px": None if lm is None else lm.tolist(),
        "has_cm": scene.has_cm,
        "control_points_deg": np.asarray(scene.control_points_deg).tolist(),
        "camera": sim.camera.to_dict(),
        "world_from_cm": np.asarray(scene.world_from_cm).tolist(),
        "ct": ct_name,
        "femur_side": scene.side,
        "lao_rao_deg": scene.lao_rao_deg,
        "cran_caud_deg": scene.cran_caud_deg,
        "source_to_isocenter_mm": scene.source_to_isocenter_mm,
        "seed": seed,
    }


def _make_sample(sample_id: int, seed: int, *, spec: DatasetSpec, out_dir: str) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    anatomies = spec.anatomies()
    ct, phantom_seed = anatomies[int(rng.integers(len(anatomies)))]
    sim = _simulator(
        ct, phantom_seed, spec.image_size, spec.device, spec.phantom_spacing_mm, spec.shaft_length_mm
    )
    scene = sample_scene(sim.volume, rng, sampling=spec.sampling, with_cm=spec.with_cm)
    image = sim.simulate(scene, seed=int(rng.integers(2**62)))
    return write_sample(Path(out_dir), sample_id, image, seed=seed, ct_name=_volume_name(sim.volume, ct))


def simulate_dataset(
    out_dir: Path,
    n: int,
    spec: DatasetSpec,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    on_result: Callable[[dict[str, Any]], None] | None = None,
    contact_sheet_png: bool = True,
) -> list[dict[str, Any]]:
    """Simulate samples ``0..n−1`` into ``out_dir`` (resuming), then write the contact sheet.

    Args:
        out_dir: data set directory (created; an existing one made with other settings is refused).
        n: number of samples of the whole data set.
        spec: what to simulate.
        scheduler: address of an existing Dask scheduler (default: a LocalCluster).
        workers: LocalCluster worker processes (default up to 2); 0 runs in this process.
        on_result: called with each new manifest row as it is written.
        contact_sheet_png: write ``contact_sheet.png`` (the first 16 samples) at the end.

    Returns:
        The manifest rows written by this call (not those of an earlier, resumed run).
    """
    # validate every CT up front, in this process: a bad file fails before anything is written
    for ct in spec.cts:
        if ct != "phantom":
            resolve_ct(ct)
    out_dir.mkdir(parents=True, exist_ok=True)
    meta_path = out_dir / "dataset.json"
    sampling = spec.sampling
    sim_config = SimulationConfig(image_size=spec.image_size, shaft_length_mm=spec.shaft_length_mm)
    binning = sampling.detector.cols / spec.image_size
    meta = {
        "version": __version__,
        "n": n,
        "spec": dataclasses.asdict(spec),
        "simulation": repr(sim_config),
        "detector": dataclasses.asdict(sampling.detector),
        "sdd_mm": sampling.detector.sdd_mm,
        "storage": {
            "rows": spec.image_size,
            "cols": spec.image_size,
            "binning": binning,
            "pixel_spacing_mm": sampling.detector.pixel_spacing_mm * sampling.detector.cols / spec.image_size,
            # flat-field photons per stored pixel: the detector pixels' N0 summed over the binning
            "photons_per_pixel": sim_config.physics.with_pixel_scale(binning).photons_per_pixel,
        },
    }
    if meta_path.exists():
        old = json.loads(meta_path.read_text(encoding="utf-8"))
        # fields added later take their defaults in a data set written before them
        old_spec = {**json.loads(json.dumps(dataclasses.asdict(DatasetSpec()))), **old.get("spec", {})}
        if old_spec != json.loads(json.dumps(meta["spec"])):  # tuples come back as lists
            raise InputError(
                meta_path,
                "this directory holds a data set made with other settings "
                "(seed, CTs, size, shaft or --no-cm); use another --out",
            )
    meta_path.write_text(json.dumps(meta, indent=2), encoding="utf-8")
    task = functools.partial(_make_sample, spec=spec, out_dir=str(out_dir))
    rows = run_tasks(
        task,
        n,
        spec.seed,
        JsonlLog(out_dir / "manifest.jsonl"),
        scheduler=scheduler,
        workers=workers,
        description="simulate",
        on_result=on_result,
    )
    all_rows = JsonlLog(out_dir / "manifest.jsonl").read()
    if all_rows and contact_sheet_png:
        contact_sheet(out_dir, sorted(all_rows, key=lambda r: r["id"])[:16], out_dir / "contact_sheet.png")
    return rows


def contact_sheet(data_dir: Path, rows: list[dict[str, Any]], path: Path) -> None:
    """A 4×4 sheet of samples with the mask outline and landmarks A (green) and B (red)."""
    import matplotlib  # heavy: matplotlib, for the contact sheet only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after use("Agg")

    n = len(rows)
    cols = 4
    nrows = max(1, (n + cols - 1) // cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(3 * cols, 3 * nrows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, row in zip(axes.flat, rows, strict=False):
        with np.load(data_dir / row["file"]) as z:
            img, mask = z["image"], z["mask"]
        lo, hi = np.percentile(img, [1, 99.5])
        ax.imshow(img, cmap="gray", vmin=lo, vmax=hi)
        if mask.any():
            ax.contour(mask, levels=[0.5], colors="y", linewidths=0.6)
        if row.get("landmarks_px"):
            (ua, va), (ub, vb) = row["landmarks_px"]
            ax.plot(ua, va, "g+", ms=8)
            ax.plot(ub, vb, "r+", ms=8)
        ax.set_title(f"#{row['id']} {row['ct']}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


#: manifest keys every sample has (docs/simulation.md, "Data set format")
MANIFEST_KEYS = (
    "id",
    "file",
    "rows",
    "cols",
    "pixel_spacing_mm",
    "landmarks_px",
    "control_points_deg",
    "camera",
    "world_from_cm",
    "ct",
)


def check_dataset(data_dir: Path, *, n: int | None = None) -> list[str]:
    """Problems of a data set against the contract (empty list = conforms).

    Checks: manifest keys, ids 0..n−1 exactly once, npz keys/dtypes/shapes at (rows, cols), the
    camera's size and ``fx = sdd / pixel_spacing`` consistent with the row, landmarks inside the
    image and equal to the npz's, empty mask and no landmarks for negatives.
    """
    data_dir = Path(data_dir)
    problems: list[str] = []
    rows_ = JsonlLog(data_dir / "manifest.jsonl").read()
    ids = sorted(int(r.get("id", -1)) for r in rows_)
    if n is not None and ids != list(range(n)):
        problems.append(f"manifest ids are not 0..{n - 1} exactly once")
    sdd = None
    meta = data_dir / "dataset.json"
    if meta.exists():
        sdd = json.loads(meta.read_text(encoding="utf-8")).get("sdd_mm")
    for r in rows_:
        tag = f"sample {r.get('id')}"
        missing = [k for k in MANIFEST_KEYS if k not in r]
        if missing:
            problems.append(f"{tag}: missing {missing}")
            continue
        cam = Camera.from_dict(r["camera"])
        h, w = int(r["rows"]), int(r["cols"])
        if (cam.rows, cam.cols) != (h, w):
            problems.append(f"{tag}: camera size differs from rows/cols")
        if sdd is not None and not np.isclose(cam.K[0, 0], sdd / r["pixel_spacing_mm"], rtol=1e-6):
            problems.append(f"{tag}: fx != sdd / pixel_spacing_mm")
        with np.load(data_dir / r["file"]) as z:
            keys = set(z.files)
            if not {"image", "mask", "landmarks_px"} <= keys:
                problems.append(f"{tag}: npz lacks image/mask/landmarks_px")
                continue
            img, mask, lm = z["image"], z["mask"], z["landmarks_px"]
        if img.dtype != np.float32 or img.shape != (h, w) or not np.all(np.isfinite(img)):
            problems.append(f"{tag}: image must be finite float32 ({h}, {w})")
        if mask.dtype != np.uint8 or mask.shape != (h, w) or not set(np.unique(mask)) <= {0, 1}:
            problems.append(f"{tag}: mask must be uint8 0/1 ({h}, {w})")
        if r["landmarks_px"] is None:
            if mask.any() or not np.all(np.isnan(lm)):
                problems.append(f"{tag}: a negative has mask pixels or landmarks")
            continue
        lm_row = np.asarray(r["landmarks_px"], dtype=np.float64)
        if lm_row.shape != (2, 2) or not np.allclose(lm_row, lm):
            problems.append(f"{tag}: landmarks_px differ between manifest and npz")
        elif not np.all((lm_row >= -0.5) & (lm_row <= np.array([w, h]) - 0.5)):
            problems.append(f"{tag}: landmarks outside the image")
        if not mask.any():
            problems.append(f"{tag}: a positive has an empty mask")
    return problems
