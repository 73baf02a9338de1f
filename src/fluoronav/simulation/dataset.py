"""Simulated data sets (``fluoronav simulate``): resumable, parallel, reproducible per seed.

Layout (docs/simulation.md, "Data set format"): ``DIR/manifest.jsonl`` (one object per sample,
appended as samples finish), ``DIR/samples/<id>.npz`` (``image``, ``mask``, ``landmarks_px``),
``DIR/dataset.json`` (the run's configuration) and ``DIR/contact_sheet.png``. Sample ``i``
depends only on the run seed and ``i``: its seed picks the anatomy (phantom seed or CT), the scene
(the paper's or the navigation's, :mod:`~fluoronav.simulation.navigation_scenes`) and the world's
errors, so the same seed gives the same samples for any number of workers, and a rerun skips
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
from fluoronav.manipulator.config import CMConfig
from fluoronav.runner import JsonlLog, run_tasks
from fluoronav.simulation.articulated import ArticulatedSimulator
from fluoronav.simulation.instrument import BuiltCM, build_instrument
from fluoronav.simulation.navigation_scenes import (
    NAVIGATION_SIDE,
    NavigationSceneSettings,
    sample_navigation_scene,
)
from fluoronav.simulation.physics import XrayPhysics
from fluoronav.simulation.sample_variation import SampleVariation, vary_after, vary_before
from fluoronav.simulation.scene import Scene, SceneSampling, sample_scene
from fluoronav.simulation.world import IDEAL, CTWorld, World, flexed_camera
from fluoronav.simulation.world_anatomy import world_anatomy
from fluoronav.simulation.xray import SimulatedImage, SimulationConfig, VaryImage, XraySimulator

log = logging.getLogger(__name__)

__all__ = [
    "SCENES",
    "DatasetSpec",
    "contact_sheet",
    "simulate_dataset",
    "write_sample",
]

#: what ``scenes`` may be: the paper's sampling, the navigation's views, or a mix of both
SCENES = ("paper", "navigation", "mixed")
#: keys of a sample's own streams beside its seed ("WRLD", "KIND"): the world's errors and a mixed
#: data set's scene kind, so that the scene's own draws stay where they are without them
_WORLD_STREAM = 0x57524C44
_KIND_STREAM = 0x4B494E44
_VARIATION_STREAM = 0x56415259


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
        world: the simulated world (:mod:`fluoronav.simulation.world`): its CT source's patient
            (``patient_spacing_mm``, for the phantom), the CM as built and the C-arm's flex reach
            the images; the labels are the true ones. The ideal world changes nothing.
        scenes: ``"paper"`` (the paper's sampling, :func:`~fluoronav.simulation.scene.sample_scene`),
            ``"navigation"`` (the navigation's views,
            :func:`~fluoronav.simulation.navigation_scenes.sample_navigation_scene`) or ``"mixed"``.
        navigation_fraction: the share of navigation scenes in a mixed data set (each sample draws
            its kind from its own stream).
        navigation: how navigation scenes are drawn.
        variation: the domain randomisation of each sample (:mod:`fluoronav.simulation.sample_variation`),
            drawn from the sample's own stream; off: the scene's image itself.
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
    world: World = IDEAL
    scenes: str = "paper"
    navigation_fraction: float = 0.5
    navigation: NavigationSceneSettings = dataclasses.field(default_factory=NavigationSceneSettings)
    variation: SampleVariation = dataclasses.field(default_factory=SampleVariation)

    def __post_init__(self) -> None:
        if not self.shaft_length_mm >= 0.0:
            raise ValueError(f"shaft_length_mm must be >= 0, got {self.shaft_length_mm}")
        _ = self.sampling  # SceneSampling validates the limits: fail here, before any worker starts
        if self.scenes not in SCENES:
            raise ValueError(f"scenes must be one of {', '.join(SCENES)}, got {self.scenes!r}")
        if not 0.0 <= self.navigation_fraction <= 1.0:
            raise ValueError(f"navigation_fraction must be in [0, 1], got {self.navigation_fraction}")
        navigation_shaft = SimulationConfig().shaft_length_mm
        if self.patient_spacing_mm("phantom") is not None and self.shaft_length_mm != navigation_shaft:
            raise ValueError(
                f"the world's patient is imaged with the navigation's simulator and its "
                f"{navigation_shaft:g} mm shaft: shaft_length_mm must be {navigation_shaft:g}"
            )

    def patient_spacing_mm(self, ct: str) -> float | None:
        """The voxel size of the world's own patient for this anatomy (a finer phantom), else None
        (the images are rendered from the data set's anatomy itself)."""
        return self.world.ct.patient_spacing_mm if ct == "phantom" and "phantom" in self.cts else None

    def scene_kind(self, sample_seed: int) -> str:
        """A sample's scene kind, ``"paper"`` or ``"navigation"`` (a mixed data set draws it from
        the sample's own stream)."""
        if self.scenes != "mixed":
            return self.scenes
        u = np.random.default_rng([_KIND_STREAM, abs(int(sample_seed))]).uniform()
        return "navigation" if u < self.navigation_fraction else "paper"

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


@functools.lru_cache(maxsize=2)
def _articulated(
    ct: str,
    phantom_seed: int,
    image_size: int,
    device: str,
    phantom_spacing_mm: float,
    shaft_length_mm: float,
) -> tuple[Volume, ArticulatedSimulator]:
    """The data set's anatomy and its articulated simulator (the navigation's; cached per process)."""
    if ct == "phantom":
        volume = hip_phantom(seed=phantom_seed, spacing_mm=phantom_spacing_mm)
    else:
        volume = resolve_ct(ct, seed=phantom_seed)
    config = SimulationConfig(image_size=image_size, shaft_length_mm=shaft_length_mm)
    return volume, ArticulatedSimulator(volume, femur_side=NAVIGATION_SIDE, config=config, device=device)


def _patient(ct: str, phantom_seed: int, spec: DatasetSpec) -> tuple[Volume, ArticulatedSimulator]:
    """The patient the images are rendered from and its articulated simulator: the world's own
    (:func:`~fluoronav.simulation.world_anatomy.world_anatomy`) where it has one, else the data set's
    anatomy."""
    spacing = spec.patient_spacing_mm(ct)
    if spacing is None:
        return _articulated(
            ct, phantom_seed, spec.image_size, spec.device, spec.phantom_spacing_mm, spec.shaft_length_mm
        )
    # the patient alone: the case's CT is not needed, so nothing is drawn from this generator
    anatomy = world_anatomy(
        ct,
        phantom_seed,
        CTWorld(patient_spacing_mm=spacing),
        image_size=spec.image_size,
        device=spec.device,
        rng=np.random.default_rng(0),
    )
    return anatomy.patient, anatomy.simulator


def _volume_name(volume: Volume, ct: str) -> str:
    return volume.name if ct == "phantom" else Path(ct).name


def write_sample(
    out_dir: Path,
    sample_id: int,
    sim: SimulatedImage,
    *,
    seed: int,
    ct_name: str,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write one sample's npz and return its manifest row (``extra`` added to it, or replacing keys)."""
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
        **(extra or {}),
    }


def _built_cm(world: World, cm_config: CMConfig, world_rng: np.random.Generator) -> BuiltCM | None:
    """The instrument as built where the world's instrument source is on (one per sample)."""
    return build_instrument(world.instrument, cm_config, world_rng) if world.instrument.enabled else None


def _scene_in_world(scene: Scene, world: World, world_rng: np.random.Generator) -> Scene:
    """The scene as the world images it: the CM as built, the camera flexed (the true imaging
    geometry, which the labels follow); the scene itself where both sources are off (nothing drawn).
    A negative draws the same, so it is taken from the same view."""
    built = _built_cm(world, scene.cm_config, world_rng)
    camera = flexed_camera(scene.camera, world.carm, world_rng)
    if built is None and camera is scene.camera:
        return scene
    return dataclasses.replace(scene, camera=camera, built_cm=built if scene.has_cm else None)


@dataclasses.dataclass
class _Variation:
    """A sample's variation stream and the record of its draws (the manifest row's ``variation``)."""

    rng: np.random.Generator
    record: dict[str, Any] = dataclasses.field(default_factory=dict)


def _vary(spec: DatasetSpec, physics: XrayPhysics, scene: Scene, variation: _Variation) -> VaryImage | None:
    """The sample's :func:`~fluoronav.simulation.sample_variation.vary_before` hook (None where the data set
    randomises nothing), drawing from the sample's variation stream into its record."""
    if not spec.variation.enabled:
        return None
    return vary_before(
        spec.variation,
        physics,
        variation.rng,
        variation.record,
        world_from_cm=scene.world_from_cm,
        tip_z_mm=scene.cm_config.tip_z_mm,
        device=spec.device,
    )


def _articulated_sample(
    ct: str,
    phantom_seed: int,
    kind: str,
    spec: DatasetSpec,
    rng: np.random.Generator,
    world_rng: np.random.Generator,
    variation: _Variation,
) -> tuple[SimulatedImage, str, dict[str, Any]]:
    """A sample of the patient posed by a navigation scene (or a paper scene, unmoved), imaged by the
    articulated simulator → (the image with its scene, the anatomy's name, the row's extra keys)."""
    patient, sim = _patient(ct, phantom_seed, spec)
    wp = wf = np.eye(4)
    extra: dict[str, Any] = {}
    if kind == "paper":
        scene = sample_scene(patient, rng, sampling=spec.sampling, with_cm=spec.with_cm)
    else:
        nav = sample_navigation_scene(patient, rng, settings=spec.navigation)
        scene = Scene(
            camera=nav.camera,
            world_from_cm=nav.world_from_cm,
            control_points_deg=nav.control_points_deg,
            has_cm=spec.with_cm,
            volume_name=patient.name,
            side=NAVIGATION_SIDE,
            cm_config=nav.cm_config,
        )
        wp, wf = nav.world_from_patient, nav.world_from_femur
        depth = None if np.isnan(nav.insertion_depth_mm) else nav.insertion_depth_mm
        extra = {"stage": nav.stage, "view": nav.view, "insertion_depth_mm": depth}
        extra.update(lao_rao_deg=None, cran_caud_deg=None, source_to_isocenter_mm=None)
    scene = _scene_in_world(scene, spec.world, world_rng)
    image = sim.simulate(
        scene.camera,
        world_from_patient=wp,
        world_from_femur=wf,
        cm=(scene.world_from_cm, scene.control_points_deg) if scene.has_cm else None,
        seed=int(rng.integers(2**62)),
        image_size=spec.image_size,
        cm_config=scene.cm_config,
        built_cm=scene.built_cm,
        vary=_vary(spec, sim.config.physics, scene, variation),
    )
    # the row records the scene as drawn (a negative's too: where its CM would be)
    return dataclasses.replace(image, scene=scene), _volume_name(patient, ct), extra


def _make_sample(sample_id: int, seed: int, *, spec: DatasetSpec, out_dir: str) -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    anatomies = spec.anatomies()
    ct, phantom_seed = anatomies[int(rng.integers(len(anatomies)))]
    kind = spec.scene_kind(seed)
    world_rng = np.random.default_rng([_WORLD_STREAM, abs(int(seed))])
    variation = _Variation(np.random.default_rng([_VARIATION_STREAM, abs(int(seed))]))
    extra: dict[str, Any] = {}
    if kind == "paper" and spec.patient_spacing_mm(ct) is None:
        # the paper's scenes of the data set's anatomy: the ideal world's exactly as without a world
        sim = _simulator(
            ct, phantom_seed, spec.image_size, spec.device, spec.phantom_spacing_mm, spec.shaft_length_mm
        )
        scene = _scene_in_world(
            sample_scene(sim.volume, rng, sampling=spec.sampling, with_cm=spec.with_cm), spec.world, world_rng
        )
        vary = _vary(spec, sim.config.physics, scene, variation)
        image = sim.simulate(scene, seed=int(rng.integers(2**62)), vary=vary)
        name = _volume_name(sim.volume, ct)
    else:
        image, name, extra = _articulated_sample(ct, phantom_seed, kind, spec, rng, world_rng, variation)
    extra = {"world": spec.world.name, "scene": kind, **extra}
    if spec.variation.enabled:
        image, camera = vary_after(image, spec.variation, variation.rng, variation.record)
        rows, cols = image.image.shape
        extra.update(
            rows=rows,
            cols=cols,
            camera=None if camera is None else camera.to_dict(),
            variation=variation.record,
        )
    return write_sample(Path(out_dir), sample_id, image, seed=seed, ct_name=name, extra=extra)


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
    _check_cts(spec)
    if spec.patient_spacing_mm("phantom") is not None and spec.n_phantoms > 1:
        log.warning(
            "the world's patient is built anew whenever a worker's next sample has another phantom "
            "seed; --phantoms 1 builds it once per worker"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    meta_path = out_dir / "dataset.json"
    sampling = spec.sampling
    sim_config = SimulationConfig(image_size=spec.image_size, shaft_length_mm=spec.shaft_length_mm)
    binning = sampling.detector.cols / spec.image_size
    meta = {
        "version": __version__,
        "n": n,
        "seed": spec.seed,
        "world": spec.world.to_dict(),
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
                "(seed, CTs, size, shaft, world, scenes or --no-cm); use another --out",
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


def _check_cts(spec: DatasetSpec) -> None:
    """Validate every CT up front, in this process: a bad file fails before anything is written.

    Navigation scenes need the navigation's labels and landmarks (its femur moves on its own).
    """
    for ct in spec.cts:
        if ct == "phantom":
            continue
        volume = resolve_ct(ct)
        if spec.scenes == "paper":
            continue
        side = NAVIGATION_SIDE
        missing = [
            f"{k}_{side}" for k in ("entry", "femoral_head") if f"{k}_{side}" not in volume.landmarks_world
        ]
        if volume.labels is None or volume.label_value(f"femur_{side}") is None:
            missing.insert(0, f"label femur_{side}")
        if missing:
            raise InputError(ct, f"navigation scenes need a labelled CT; missing {', '.join(missing)}")


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
        stage = f" {row['stage']}" if row.get("stage") else ""
        ax.set_title(f"#{row['id']} {row['ct']}{stage}", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
