"""Realistic X-ray images of a scene: CT material decomposition + voxelised CM + physics.

For each scene the simulator (docs/simulation.md, "Image assembly") integrates the CT's per-material partial
densities along every detector ray (g/cm³·mm → g/cm²); removes the CT inside the CM's envelope (the drilled
path: a solid cylinder of the CM's outer radius along its bent axis, sampled on a ``drill_voxel_mm`` grid);
voxelises the bent CM at ``cm_voxel_mm`` (partial volumes) as nitinol (or the authors' 2000 HU material),
integrates it at ``cm_oversample``× the stored resolution inside its projected box and area-bins it; and forms
the detector image with :class:`~fluoronav.simulation.physics.XrayPhysics`. The registration's analytic CM
renderer is *not* used for the image (no inverse crime); it only gives the label mask, the projection of the
CM envelope between landmarks A and B. A scene with an instrument as built (``Scene.built_cm``) is drawn,
drilled and labelled with that instrument's notches, joint angles and diameters.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from scipy.ndimage import map_coordinates

from fluoronav.anatomy.volume import Volume
from fluoronav.device import resolve_device
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.geometry import VoxelizedCM, voxelize_cm, voxelize_cm_links
from fluoronav.rendering.cm import CMRenderer
from fluoronav.rendering.ct import CTRenderer, render_line_integrals
from fluoronav.simulation._tube_numba import BINNED_TUBE_CHORDS_ARGS, binned_tube_chords
from fluoronav.simulation.instrument import BuiltCM, built_landmarks_cm, built_link_transforms
from fluoronav.simulation.materials import MM_PER_CM, decompose_hu, get_material
from fluoronav.simulation.physics import XrayPhysics
from fluoronav.simulation.scene import Scene

log = logging.getLogger(__name__)

__all__ = [
    "SimulatedImage",
    "SimulationConfig",
    "XraySimulator",
    "built_labels",
    "compile_kernels",
    "envelope_config",
]

#: CT materials rendered (air is left out: outside the body it is not in the CT, inside it is < 1 %)
RENDERED_CT_MATERIALS = ("adipose", "soft_tissue", "bone_cortical")
#: HU the drilled path samples outside the CT (air)
_AIR_HU = -1000.0


def envelope_config(config: CMConfig) -> CMConfig:
    """The CM's envelope (solid cylinder, no lumen, no notches) with the same axis and landmarks."""
    return config.model_copy(update={"inner_diameter_mm": 0.0, "notch_depth_mm": 1e-9})


@dataclass(frozen=True)
class SimulationConfig:
    """Settings of the image simulation.

    Attributes:
        physics: spectrum, detector, scatter and noise model.
        image_size: stored image rows = cols; the detector (e.g. 1536²) is binned to it.
        cm_oversample: the CM is integrated at ``image_size · cm_oversample`` and area-binned.
        cm_voxel_mm: voxel size of the CM voxelisation, mm.
        cm_material: ``"nitinol"`` (6.45 g/cm³) or ``"hu2000"`` (the authors' 2000 HU voxels).
        drill: remove the CT inside the CM envelope.
        drill_voxel_mm: voxel size of the envelope used to remove the CT, mm.
        shaft_length_mm: length of the rigid tube the CM's base is mounted on (the robot's shaft,
            same outer and inner diameter and material as the CM), behind the base along −z of the
            CM frame; 0: the bare CM. Real images show it, and it is what tells the CM's base end
            (landmark A) from its tip end (B): the bare CM is nearly symmetric end to end.
    """

    physics: XrayPhysics = field(
        default_factory=lambda: XrayPhysics(energy_bin_keV=3.0, scatter_downsample=4)
    )
    image_size: int = 512
    cm_oversample: int = 3
    cm_voxel_mm: float = 0.1
    cm_material: str = "nitinol"
    drill: bool = True
    drill_voxel_mm: float = 0.5
    shaft_length_mm: float = 50.0


def tube_chord_mm(
    origin: torch.Tensor, directions: torch.Tensor, radius_mm: float, z0_mm: float, z1_mm: float
) -> torch.Tensor:
    """Length of each ray inside the solid cylinder x² + y² ≤ r², z0 ≤ z ≤ z1 (analytic).

    Args:
        origin: (3,) ray origin; directions: (N, 3) unit directions (the cylinder's frame).
        radius_mm, z0_mm, z1_mm: the cylinder.

    Returns:
        (N,) chord lengths in mm (0 for rays that miss).
    """
    ox, oy, oz = origin[0], origin[1], origin[2]
    dx, dy, dz = directions[:, 0], directions[:, 1], directions[:, 2]
    a = dx * dx + dy * dy
    b = 2.0 * (ox * dx + oy * dy)
    c = ox * ox + oy * oy - radius_mm**2
    disc = b * b - 4.0 * a * c
    hit = (disc > 0) & (a > 1e-15)
    sq = disc.clamp_min(0.0).sqrt()
    a_safe = torch.where(hit, a, torch.ones_like(a))
    t1, t2 = (-b - sq) / (2.0 * a_safe), (-b + sq) / (2.0 * a_safe)
    dz_safe = torch.where(dz.abs() > 1e-15, dz, torch.full_like(dz, 1e-15))
    s1, s2 = (z0_mm - oz) / dz_safe, (z1_mm - oz) / dz_safe
    lo = torch.maximum(torch.minimum(s1, s2), t1)
    hi = torch.minimum(torch.maximum(s1, s2), t2)
    return torch.where(hit, (hi - lo).clamp_min(0.0), torch.zeros_like(a))


def compile_kernels() -> None:
    """Compile the shaft's CPU chord kernel for the argument types this module passes into numba's
    on-disk cache, so that a new process's first image loads the machine code instead of compiling it."""
    for args in BINNED_TUBE_CHORDS_ARGS:
        binned_tube_chords.compile(args)


@dataclass(frozen=True, eq=False)
class ImageVariation:
    """What a sample varies beyond its scene, decided once its labels are known (domain randomisation).

    Attributes:
        physics: the detector-pixel physics instead of the simulator's, scaled to the stored pixels
            as the simulator's is; None: the simulator's.
        densities: material → (H, W) areal densities in g/cm² at the stored camera, added to the
            scene's before the physics (collimator blades, a wedge, distractor metal).
    """

    physics: XrayPhysics | None = None
    densities: Mapping[str, torch.Tensor] = field(default_factory=dict)


#: a sample's variation from its stored camera and its landmarks (2, 2) (None without a CM)
VaryImage = Callable[[Camera, "np.ndarray | None"], ImageVariation]


def imaged(
    densities: Mapping[str, torch.Tensor],
    physics: XrayPhysics,
    variation: ImageVariation | None,
    *,
    pixel_scale: float,
    seed: int,
) -> np.ndarray:
    """The stored image (H, W) float32 of areal densities (g/cm²): ``physics`` (or the variation's)
    at ``pixel_scale`` detector pixels per stored pixel, the variation's densities added first."""
    dens = dict(densities)
    if variation is not None:
        ref = next(iter(dens.values()))
        for m, extra in variation.densities.items():
            extra = extra.to(device=ref.device, dtype=ref.dtype)
            dens[m] = dens[m] + extra if m in dens else extra
        physics = variation.physics or physics
    return physics.with_pixel_scale(pixel_scale).apply(dens, seed=seed).float().cpu().numpy()


@dataclass(frozen=True, eq=False)
class SimulatedImage:
    """One simulated X-ray with its labels (all at the stored resolution).

    Attributes:
        image: (H, W) float32, −ln(I/I0) (bone and metal bright).
        mask: (H, W) uint8, 1 on the notched CM region (zeros without a CM).
        landmarks_px: (2, 2) [[uA, vA], [uB, vB]] or None without a CM.
        camera: the camera of the stored image (world = CT frame).
        scene: the scene simulated.
    """

    image: np.ndarray
    mask: np.ndarray
    landmarks_px: np.ndarray | None
    camera: Camera
    scene: Scene


def _projected_box(
    camera: Camera, world_from_index: np.ndarray, shape_zyx: tuple[int, ...]
) -> tuple[int, int, int, int] | None:
    """(row0, col0, row1, col1) pixel box (clipped to the image) covering a voxel grid's projection."""
    nz, ny, nx = shape_zyx
    corners = np.array([[i, j, k, 1.0] for i in (0, nx) for j in (0, ny) for k in (0, nz)])
    corners[:, :3] -= 0.5
    uv = camera.project((corners @ np.asarray(world_from_index).T)[:, :3])
    c0, r0 = np.floor(uv.min(0)).astype(int) - 1
    c1, r1 = np.ceil(uv.max(0)).astype(int) + 2
    c0, r0 = max(int(c0), 0), max(int(r0), 0)
    c1, r1 = min(int(c1), camera.cols), min(int(r1), camera.rows)
    if c1 <= c0 or r1 <= r0:
        return None
    return r0, c0, r1, c1


class XraySimulator:
    """Physics-based X-ray simulation of scenes in one CT (CPU or CUDA).

    Args:
        volume: CT in HU.
        config: simulation settings.
        device: torch device for rendering and physics.
    """

    def __init__(
        self, volume: Volume, *, config: SimulationConfig | None = None, device: str | torch.device = "cpu"
    ) -> None:
        self.volume = volume
        self.config = config or SimulationConfig()
        self.device = resolve_device(device)
        parts = decompose_hu(volume.data, RENDERED_CT_MATERIALS)
        self._renderers = {
            m: CTRenderer(volume.replace(data=parts[m], labels=None), device=self.device, mipmap=False)
            for m in RENDERED_CT_MATERIALS
        }
        self._hu = volume.data

    # ----- geometry ------------------------------------------------------------------------
    def stored_camera(self, scene: Scene) -> Camera:
        """The camera of the stored image: the scene's detector binned to ``image_size``."""
        n = self.config.image_size
        return scene.camera.scaled_to(n, n)

    def _cm_material_densities(self, cm: CMConfig) -> dict[str, float]:
        if self.config.cm_material == "nitinol":
            return {"nitinol": get_material("nitinol").density_g_cm3}
        if self.config.cm_material == "hu2000":
            parts = decompose_hu(np.array([cm.hu_value], dtype=np.float32))
            return {k: float(v[0]) for k, v in parts.items() if k in RENDERED_CT_MATERIALS and v[0] > 0}
        raise ValueError(f"unknown cm_material {self.config.cm_material!r}; use 'nitinol' or 'hu2000'")

    def _hu_box(self, box: tuple[slice, ...]) -> np.ndarray:
        """The CT's HU (z, y, x) in ``box``, as the drilled path samples it."""
        return np.asarray(self._hu[box])

    def _sample_hu(self, zyx: np.ndarray) -> np.ndarray:
        """Trilinear HU at (3, n) voxel coordinates (z, y, x), air outside the CT.

        Only the box of voxels the points need is read (:meth:`_hu_box`): the same values as
        sampling the whole CT, as the box is shifted by whole voxels and keeps the CT's faces."""
        shape = np.asarray(np.shape(self._hu))
        lo = np.clip(np.floor(zyx.min(axis=1)).astype(np.int64) - 1, 0, shape)
        hi = np.clip(np.floor(zyx.max(axis=1)).astype(np.int64) + 2, 0, shape)
        if np.any(hi <= lo):  # every point beyond one of the CT's faces
            return np.full(zyx.shape[1], _AIR_HU, dtype=np.float64)
        box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
        shifted = zyx - lo[:, None].astype(np.float64)
        return map_coordinates(self._hu_box(box), shifted, order=1, mode="constant", cval=_AIR_HU)

    def _drilled_densities(self, scene: Scene, camera: Camera) -> dict[str, torch.Tensor]:
        """Line integrals (g/cm³·mm) of the CT removed by the drilled path, per material.

        The envelope (solid cylinder along the bent axis) is voxelised in the CM frame at
        ``drill_voxel_mm``; the CT is sampled trilinearly at those voxels, decomposed, weighted by
        the envelope fraction and integrated like the CT itself.
        """
        if scene.built_cm is None:
            env = voxelize_cm(
                envelope_config(scene.cm_config),
                np.asarray(scene.control_points_deg, np.float64),
                spacing_mm=self.config.drill_voxel_mm,
                supersample=2,
            )
        else:
            env = _voxelize_built(
                scene.built_cm, scene.control_points_deg, self.config.drill_voxel_mm, envelope=True
            )
        occ = env.occupancy
        nz_idx = np.nonzero(occ)
        if len(nz_idx[0]) == 0:
            return {}
        world_from_index = scene.world_from_cm @ env.world_from_index
        ijk = np.stack([nz_idx[2], nz_idx[1], nz_idx[0], np.ones(len(nz_idx[0]))], axis=1).astype(np.float64)
        ct_index = (ijk @ world_from_index.T) @ self.volume.index_from_world.T  # (n, 4) as (i, j, k, 1)
        hu = self._sample_hu(np.stack([ct_index[:, 2], ct_index[:, 1], ct_index[:, 0]]))
        parts = decompose_hu(hu.astype(np.float32))
        out: dict[str, torch.Tensor] = {}
        box = _projected_box(camera, world_from_index, occ.shape)
        if box is None:
            return out
        r0, c0, r1, c1 = box  # only rays through the envelope's box are integrated
        crop = camera.crop(row0=r0, col0=c0, rows=r1 - r0, cols=c1 - c0)
        K = torch.as_tensor(crop.K)[None]
        T = torch.as_tensor(crop.camera_from_world)[None]
        for m in RENDERED_CT_MATERIALS:
            if not np.any(parts[m] > 0):
                continue
            data = np.zeros_like(occ)
            data[nz_idx] = parts[m] * occ[nz_idx]
            full = torch.zeros(camera.rows, camera.cols, dtype=torch.float32, device=self.device)
            full[r0:r1, c0:c1] = render_line_integrals(
                torch.as_tensor(data, device=self.device),
                world_from_index,
                K,
                T,
                crop.rows,
                crop.cols,
                mipmap=False,
            )[0]
            out[m] = full
        return out

    def _cm_integral(self, scene: Scene, camera: Camera) -> torch.Tensor:
        """∫ occupancy dl (mm) of the voxelised CM at the stored resolution (area-binned)."""
        if scene.built_cm is None:
            vox = voxelize_cm(
                scene.cm_config,
                np.asarray(scene.control_points_deg, dtype=np.float64),
                spacing_mm=self.config.cm_voxel_mm,
                supersample=2,
            )
        else:
            vox = _voxelize_built(scene.built_cm, scene.control_points_deg, self.config.cm_voxel_mm)
        f = self.config.cm_oversample
        fine = scene.camera.scaled_to(camera.rows * f, camera.cols * f)
        world_from_index = scene.world_from_cm @ vox.world_from_index
        out = torch.zeros(camera.rows, camera.cols, dtype=torch.float32, device=self.device)
        box = _projected_box(camera, world_from_index, vox.occupancy.shape)
        if box is None:
            return out
        r0, c0, r1, c1 = box
        crop = fine.crop(row0=r0 * f, col0=c0 * f, rows=(r1 - r0) * f, cols=(c1 - c0) * f)
        occ = torch.as_tensor(vox.occupancy, device=self.device)
        img = render_line_integrals(
            occ,
            world_from_index,
            torch.as_tensor(crop.K)[None],
            torch.as_tensor(crop.camera_from_world)[None],
            crop.rows,
            crop.cols,
            mipmap=False,
        )[0]
        binned = torch.nn.functional.avg_pool2d(img[None, None], f)[0, 0]
        out[r0:r1, c0:c1] = binned
        if self.config.shaft_length_mm > 0:
            out = out + self._shaft_integral(scene, camera)
        return out

    def _shaft_integral(self, scene: Scene, camera: Camera) -> torch.Tensor:
        """∫ dl (mm) through the hollow shaft tube (analytic chords), area-binned like the CM."""
        cm = scene.cm_config if scene.built_cm is None else scene.built_cm.config  # the same tube
        z1 = -float(cm.base_length_mm)
        z0 = z1 - float(self.config.shaft_length_mm)
        r_out, r_in = cm.outer_diameter_mm / 2.0, cm.inner_diameter_mm / 2.0
        out = torch.zeros(camera.rows, camera.cols, dtype=torch.float32, device=self.device)
        corners = np.array([[x, y, z] for x in (-r_out, r_out) for y in (-r_out, r_out) for z in (z0, z1)])
        world = corners @ scene.world_from_cm[:3, :3].T + scene.world_from_cm[:3, 3]
        cam_pts = camera.to_camera(world)
        if np.any(cam_pts[:, 2] <= 1.0):
            return out
        uv = camera.project(world)
        c0, r0 = np.floor(uv.min(axis=0)).astype(int) - 1
        c1, r1 = np.ceil(uv.max(axis=0)).astype(int) + 2
        c0, r0, c1, r1 = max(c0, 0), max(r0, 0), min(c1, camera.cols), min(r1, camera.rows)
        if c1 <= c0 or r1 <= r0:
            return out
        f = self.config.cm_oversample
        fine = scene.camera.scaled_to(camera.rows * f, camera.cols * f)
        crop = fine.crop(row0=r0 * f, col0=c0 * f, rows=(r1 - r0) * f, cols=(c1 - c0) * f)
        cm_from_camera = np.linalg.inv(crop.camera_from_world @ scene.world_from_cm)
        binned = np.empty((r1 - r0, c1 - c0), np.float64)
        binned_tube_chords(
            np.ascontiguousarray(cm_from_camera[:3, :3] @ np.linalg.inv(crop.K)),
            np.ascontiguousarray(cm_from_camera[:3, 3]),
            r_out,
            r_in,
            z0,
            z1,
            f,
            binned,
        )
        out[r0:r1, c0:c1] = torch.from_numpy(binned).to(torch.float32).to(self.device)
        return out

    def _ct_densities(self, camera: Camera) -> dict[str, torch.Tensor]:
        """CT material line integrals (g/cm³·mm) at ``camera``."""
        return {m: r.render([camera])[0] for m, r in self._renderers.items()}

    # ----- images --------------------------------------------------------------------------
    def areal_densities(self, scene: Scene, camera: Camera | None = None) -> dict[str, torch.Tensor]:
        """Per-material areal densities (g/cm²) at the stored resolution."""
        camera = camera or self.stored_camera(scene)
        dens = self._ct_densities(camera)
        if scene.has_cm:
            if self.config.drill:
                for m, removed in self._drilled_densities(scene, camera).items():
                    dens[m] = (dens[m] - removed).clamp_min(0.0)
            occ_mm = self._cm_integral(scene, camera)
            for m, rho in self._cm_material_densities(scene.cm_config).items():
                dens[m] = dens.get(m, torch.zeros_like(occ_mm)) + rho * occ_mm
        return {m: v / MM_PER_CM for m, v in dens.items()}

    def labels(self, scene: Scene, camera: Camera) -> tuple[np.ndarray, np.ndarray | None]:
        """(mask uint8 (H, W), landmarks (2, 2) or None) at ``camera``."""
        if not scene.has_cm:
            return np.zeros((camera.rows, camera.cols), np.uint8), None
        if scene.built_cm is not None:
            return built_labels(scene.built_cm, scene.control_points_deg, scene.world_from_cm, camera)
        env = CMRenderer(envelope_config(scene.cm_config), mu_per_mm=1.0)
        T = torch.as_tensor(camera.camera_from_world @ scene.world_from_cm)[None, None]
        cp = torch.as_tensor(np.asarray(scene.control_points_deg, dtype=np.float64))[None]
        K = torch.as_tensor(camera.K)[None]
        mask = env.mask(T, cp, K, camera.rows, camera.cols)[0, 0].cpu().numpy().astype(np.uint8)
        lm = env.landmarks_px(T, cp, K)[0, 0].cpu().numpy()
        return mask, lm

    def simulate(
        self, scene: Scene, *, seed: int, camera: Camera | None = None, vary: VaryImage | None = None
    ) -> SimulatedImage:
        """A realistic image of ``scene`` (reproducible for a seed) with its labels; ``vary`` decides
        the sample's :class:`ImageVariation` from its stored camera and landmarks."""
        camera = camera or self.stored_camera(scene)
        dens = self.areal_densities(scene, camera)
        mask, lm = self.labels(scene, camera)
        variation = vary(camera, lm) if vary is not None else None
        # blur/scatter widths are given in detector pixels: scale them to the stored pixels
        image = imaged(
            dens, self.config.physics, variation, pixel_scale=scene.camera.cols / camera.cols, seed=seed
        )
        return SimulatedImage(image=image, mask=mask, landmarks_px=lm, camera=camera, scene=scene)


def _voxelize_built(
    built: BuiltCM, control_points_deg: np.ndarray, spacing_mm: float, *, envelope: bool = False
) -> VoxelizedCM:
    """The built instrument (or its envelope: no lumen, no notches) voxelised at its joint angles."""
    T = built_link_transforms(built, control_points_deg).numpy()
    if not envelope:
        return voxelize_cm_links(built.config, T, notches=built.notches, spacing_mm=spacing_mm, supersample=2)
    env = envelope_config(built.config)
    notches = replace(built.notches, depth_mm=(env.notch_depth_mm,) * env.n_notches)
    return voxelize_cm_links(env, T, notches=notches, spacing_mm=spacing_mm, supersample=2)


def built_labels(
    built: BuiltCM, control_points_deg: np.ndarray, world_from_cm: np.ndarray, camera: Camera
) -> tuple[np.ndarray, np.ndarray]:
    """Labels of a built instrument: (mask uint8 (H, W), landmarks (2, 2) pixels) at ``camera``.

    The mask has the definition of :meth:`XraySimulator.labels`' (pixels whose ray crosses the
    envelope between A and B), from the built link poses: per link, the chord through its solid
    cylinder of the true outer radius, clipped to the link's axial slab within A–B.
    """
    T = built_link_transforms(built, control_points_deg).numpy()  # (L, 4, 4) cm_from_link
    centres = np.asarray(built.notches.z_mm)
    bounds = np.concatenate([[-built.config.base_length_mm], centres, [built.config.tip_z_mm]])
    z0 = np.maximum(bounds[:-1], 0.0)
    z1 = np.minimum(bounds[1:], built.notches.distal_plane_mm)
    r = built.config.outer_radius_mm
    camera_from_link = camera.camera_from_world @ np.asarray(world_from_cm, np.float64) @ T
    mask = np.zeros((camera.rows, camera.cols), np.uint8)
    live = np.nonzero(z1 > z0)[0]
    pts = np.concatenate(
        [
            np.array(
                [[sx * r, sy * r, z] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0) for z in (z0[k], z1[k])]
            )
            @ T[k, :3, :3].T
            + T[k, :3, 3]
            for k in live
        ]
    )
    uv = camera.project(pts @ world_from_cm[:3, :3].T + world_from_cm[:3, 3])
    c0, r0 = np.maximum(np.floor(uv.min(axis=0)).astype(int) - 1, 0)
    c1 = min(int(np.ceil(uv[:, 0].max())) + 2, camera.cols)
    r1 = min(int(np.ceil(uv[:, 1].max())) + 2, camera.rows)
    if c1 > c0 and r1 > r0:
        rows, cols = np.mgrid[r0:r1, c0:c1]
        pix = np.stack([cols.ravel(), rows.ravel(), np.ones(cols.size)], axis=1).astype(np.float64)
        rays = pix @ np.linalg.inv(camera.K).T
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        chord = torch.zeros(len(rays), dtype=torch.float64)
        for k in live:
            R, t = camera_from_link[k, :3, :3], camera_from_link[k, :3, 3]
            origin = torch.as_tensor(-R.T @ t)
            dirs = torch.as_tensor(rays @ R)  # rows: R^T · ray
            chord += tube_chord_mm(origin, dirs, r, float(z0[k]), float(z1[k]))
        mask[r0:r1, c0:c1] = (chord > 0).numpy().reshape(rows.shape).astype(np.uint8)
    ab = built_landmarks_cm(built, control_points_deg).numpy()
    w = np.asarray(world_from_cm, np.float64)
    landmarks = camera.project(ab @ w[:3, :3].T + w[:3, 3])
    return mask, landmarks
