"""Solid geometry of the notched CM: point membership and partial-volume voxelisation.

The solid (straight configuration, CM base frame; see :class:`~fluoronav.manipulator.CMConfig`) is
the annulus ``r_in ≤ r ≤ r_out``, ``−base_length ≤ z ≤ tip_z``, minus, for each notch ``j``, the
slab ``|z − z_j| ≤ width/2`` intersected with the half-space ``side_j · y > notch_cut_level``.
Link ``k`` owns the material with ``z`` in ``link_z_ranges_mm()[k]`` and moves rigidly with
``cm_from_link[k]``, so the bent solid is the union of the transformed link pieces.
``region="notched"`` restricts everything to the straight-frame slab ``0 ≤ z ≤ distal_notch_plane``
(between landmarks A and B), which is what the 2D segmentation labels mark. An as-built instrument
(:class:`NotchGeometry`: each notch where it was really cut, with its own width and depth) is
voxelised by :func:`voxelize_cm_links` from explicit link transforms.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from numba import njit, prange, types

from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics

__all__ = [
    "LinkTable",
    "NotchGeometry",
    "VoxelizedCM",
    "compile_kernels",
    "inside_cm",
    "inside_cm_straight",
    "link_table",
    "region_z_range_mm",
    "voxelize_cm",
    "voxelize_cm_links",
]

logger = logging.getLogger(__name__)

Region = Literal["solid", "notched"]


@dataclass(frozen=True)
class LinkTable:
    """Per-link description of the straight solid, shared by voxeliser, mesher and renderers.

    Attributes:
        z_range_mm: (L, 2) axial extent of each link's material.
        notches: (L, 2, 3) up to two half-notches per link as ``(z_lo, z_hi, side)``; an unused
            entry has ``z_lo == z_hi``.
        r_in_mm, r_out_mm: tube radii.
        cut_mm: a notch removes ``side · y > cut_mm``.
        notch_cut_mm: (L, 2) cut level of each half-notch where the notches differ in depth (an
            as-built instrument; only the voxeliser reads it); None: every notch at ``cut_mm``.
    """

    z_range_mm: np.ndarray
    notches: np.ndarray
    r_in_mm: float
    r_out_mm: float
    cut_mm: float
    notch_cut_mm: np.ndarray | None = None

    def half_notch_cuts(self) -> np.ndarray:
        """(L, 2) cut level of every half-notch entry, mm."""
        if self.notch_cut_mm is not None:
            return self.notch_cut_mm
        return np.full(self.notches.shape[:2], self.cut_mm)


@dataclass(frozen=True)
class NotchGeometry:
    """Per-notch dimensions of one instrument (straight frame, mm), replacing the config's uniform ones.

    Attributes:
        z_mm: (N,) axial centre of each notch (its joint's rotation centre), mm.
        width_mm: (N,) axial width of each notch, mm.
        depth_mm: (N,) depth of each notch from the outer surface, mm.

    Tuples, so that the geometry is hashable (the link table is cached per geometry).
    """

    z_mm: tuple[float, ...]
    width_mm: tuple[float, ...]
    depth_mm: tuple[float, ...]

    def __post_init__(self) -> None:
        n = len(self.z_mm)
        if len(self.width_mm) != n or len(self.depth_mm) != n:
            raise ValueError("z_mm, width_mm and depth_mm must have one value per notch")
        if n > 1 and not all(b > a for a, b in zip(self.z_mm[:-1], self.z_mm[1:], strict=True)):
            raise ValueError("notch centres z_mm must increase")
        if min(self.width_mm) <= 0 or min(self.depth_mm) <= 0:
            raise ValueError("notch widths and depths must be positive")

    @classmethod
    def nominal(cls, config: CMConfig) -> NotchGeometry:
        """The config's uniform notches."""
        n = config.n_notches
        return cls(
            z_mm=tuple(config.notch_z_mm(j) for j in range(n)),
            width_mm=(config.notch_width_mm,) * n,
            depth_mm=(config.notch_depth_mm,) * n,
        )

    @property
    def distal_plane_mm(self) -> float:
        """Axial position of the last notch's distal plane (landmark B when straight), mm."""
        return self.z_mm[-1] + self.width_mm[-1] / 2.0


@functools.lru_cache(maxsize=16)
def link_table(config: CMConfig, notches: NotchGeometry | None = None) -> LinkTable:
    """Split every notch between the two links that own its halves (cached per config and notches).

    Args:
        config: CM geometry (radii, base and tip, notch sides).
        notches: per-notch centres, widths and depths of an as-built instrument; None: the config's.
    """
    if notches is None:
        return _nominal_link_table(config)
    if len(notches.z_mm) != config.n_notches:
        raise ValueError(f"notches must describe {config.n_notches} notches, got {len(notches.z_mm)}")
    centres = np.asarray(notches.z_mm, dtype=np.float64)
    zr = _z_ranges(config, centres)
    table, cuts = _split_notches(
        config,
        zr,
        centres,
        [w / 2.0 for w in notches.width_mm],
        [config.outer_radius_mm - d for d in notches.depth_mm],
    )
    return LinkTable(
        z_range_mm=zr,
        notches=table,
        r_in_mm=config.inner_radius_mm,
        r_out_mm=config.outer_radius_mm,
        cut_mm=config.notch_cut_level_mm,
        notch_cut_mm=cuts,
    )


def _z_ranges(config: CMConfig, centres: np.ndarray) -> np.ndarray:
    """(N+1, 2) straight axial extent of each link's material for joint centres ``centres``."""
    bounds = np.concatenate([[-config.base_length_mm], centres, [config.tip_z_mm]])
    return np.stack([bounds[:-1], bounds[1:]], axis=1)


def _split_notches(
    config: CMConfig,
    zr: np.ndarray,
    centres: Sequence[float] | np.ndarray,
    half_widths_mm: Sequence[float],
    cuts_mm: Sequence[float],
) -> tuple[np.ndarray, np.ndarray]:
    """Each notch's part within each link's axial extent ``zr`` (L, 2): ``(notches (L, 2, 3) of
    (z_lo, z_hi, side), cut levels (L, 2))``."""
    L = zr.shape[0]
    table = np.zeros((L, 2, 3))
    cuts = np.zeros((L, 2))
    count = np.zeros(L, dtype=int)
    for j in range(config.n_notches):
        zc, hw = centres[j], half_widths_mm[j]
        for k in range(L):
            lo, hi = max(zc - hw, zr[k, 0]), min(zc + hw, zr[k, 1])
            if hi > lo:
                table[k, count[k]] = (lo, hi, float(config.notch_side(j)))
                cuts[k, count[k]] = cuts_mm[j]
                count[k] += 1
    return table, cuts


def _nominal_link_table(config: CMConfig) -> LinkTable:
    zr = CMKinematics(config).link_z_ranges_mm()
    n = config.n_notches
    notches, _ = _split_notches(
        config,
        zr,
        [config.notch_z_mm(j) for j in range(n)],
        [config.notch_width_mm / 2.0] * n,
        [config.notch_cut_level_mm] * n,
    )
    return LinkTable(
        z_range_mm=zr,
        notches=notches,
        r_in_mm=config.inner_radius_mm,
        r_out_mm=config.outer_radius_mm,
        cut_mm=config.notch_cut_level_mm,
    )


def region_z_range_mm(
    config: CMConfig, region: Region, notches: NotchGeometry | None = None
) -> tuple[float, float]:
    """Straight-frame axial clip of a region: the whole tube or the notched part A–B (B at the
    distal plane of ``notches``' last notch where given)."""
    if region == "solid":
        return (-math.inf, math.inf)
    if region == "notched":
        return (0.0, config.distal_notch_plane_mm if notches is None else notches.distal_plane_mm)
    raise ValueError(f"unknown region {region!r}; use 'solid' or 'notched'")


def inside_cm_straight(
    points_cm_straight: np.ndarray, config: CMConfig, *, region: Region = "solid"
) -> np.ndarray:
    """Membership of points in the straight CM solid.

    Args:
        points_cm_straight: (..., 3) points in straight-configuration CM coordinates, mm.
        config: CM geometry.
        region: ``"solid"`` (whole tube) or ``"notched"`` (only ``0 ≤ z ≤ distal_notch_plane``).

    Returns:
        (...,) bool mask.
    """
    p = np.asarray(points_cm_straight, dtype=np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    r2 = x * x + y * y
    zlo, zhi = region_z_range_mm(config, region)
    inside = (r2 >= config.inner_radius_mm**2) & (r2 <= config.outer_radius_mm**2)
    inside &= (z >= max(-config.base_length_mm, zlo)) & (z <= min(config.tip_z_mm, zhi))
    hw = config.notch_width_mm / 2.0
    cut = config.notch_cut_level_mm
    for j in range(config.n_notches):
        zc = config.notch_z_mm(j)
        inside &= ~((np.abs(z - zc) <= hw) & (config.notch_side(j) * y > cut))
    return inside


def _links_np(config: CMConfig, control_points_deg: np.ndarray | torch.Tensor) -> np.ndarray:
    cp = torch.as_tensor(np.asarray(control_points_deg, dtype=np.float64))
    if cp.shape != (config.n_control_points,):
        raise ValueError(
            f"control_points_deg must have shape ({config.n_control_points},), got {tuple(cp.shape)}"
        )
    return CMKinematics(config).link_transforms(cp).numpy()  # (L, 4, 4) cm_from_link


def inside_cm(
    points_cm: np.ndarray,
    control_points_deg: np.ndarray | torch.Tensor,
    config: CMConfig | None = None,
    *,
    region: Region = "solid",
) -> np.ndarray:
    """Membership of points in the bent CM.

    Each point is mapped into every link's straight frame with the inverse link transform and
    tested against the straight solid restricted to that link's axial range.

    Args:
        points_cm: (P, 3) points in the CM base frame, mm.
        control_points_deg: (n,) control points.
        config: CM geometry (paper defaults if None).
        region: ``"solid"`` or ``"notched"`` (A–B part only).

    Returns:
        (P,) bool mask.
    """
    config = config or CMConfig()
    pts = np.ascontiguousarray(np.asarray(points_cm, dtype=np.float64).reshape(-1, 3))
    T = _links_np(config, control_points_deg)
    table = link_table(config)
    zlo, zhi = region_z_range_mm(config, region)
    zr = table.z_range_mm.copy()
    zr[:, 0] = np.maximum(zr[:, 0], zlo)
    zr[:, 1] = np.minimum(zr[:, 1], zhi)
    link_from_cm = np.zeros_like(T)
    link_from_cm[:, :3, :3] = T[:, :3, :3].transpose(0, 2, 1)
    link_from_cm[:, :3, 3] = -np.einsum("kji,kj->ki", T[:, :3, :3], T[:, :3, 3])
    link_from_cm[:, 3, 3] = 1.0
    out = np.zeros(pts.shape[0], dtype=np.bool_)
    _inside_links(
        out,
        pts,
        link_from_cm,
        zr,
        np.ascontiguousarray(table.notches),
        np.ascontiguousarray(table.half_notch_cuts()),
        table.r_in_mm**2,
        table.r_out_mm**2,
    )
    return out


@dataclass(frozen=True)
class VoxelizedCM:
    """Partial-volume voxelisation of the bent CM.

    Attributes:
        occupancy: (nz, ny, nx) float32 fraction of each voxel inside the solid (SimpleITK order).
        world_from_index: (4, 4) maps (i, j, k) = (x, y, z) voxel indices to the CM base frame, mm.
        spacing_mm: isotropic voxel size, mm.
    """

    occupancy: np.ndarray
    world_from_index: np.ndarray
    spacing_mm: float


@njit(cache=True, fastmath=True, inline="always")
def _inside_link(
    x: float,
    y: float,
    z: float,
    z0: float,
    z1: float,
    notches: np.ndarray,  # pragma: no cover
    cuts: np.ndarray,
    r_in2: float,
    r_out2: float,
) -> bool:
    if z < z0 or z > z1:
        return False
    r2 = x * x + y * y
    if r2 < r_in2 or r2 > r_out2:
        return False
    for m in range(notches.shape[0]):
        if (
            notches[m, 1] > notches[m, 0]
            and notches[m, 0] <= z <= notches[m, 1]
            and notches[m, 2] * y > cuts[m]
        ):
            return False
    return True


@njit(parallel=True, cache=True, fastmath=True)
def _inside_links(  # pragma: no cover - jitted
    out: np.ndarray,
    pts: np.ndarray,
    link_from_cm: np.ndarray,
    z_range: np.ndarray,
    notches: np.ndarray,
    cuts: np.ndarray,
    r_in2: float,
    r_out2: float,
) -> None:
    for p in prange(pts.shape[0]):
        x, y, z = pts[p, 0], pts[p, 1], pts[p, 2]
        for k in range(link_from_cm.shape[0]):
            R = link_from_cm[k]
            qx = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + R[0, 3]
            qy = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + R[1, 3]
            qz = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + R[2, 3]
            if _inside_link(qx, qy, qz, z_range[k, 0], z_range[k, 1], notches[k], cuts[k], r_in2, r_out2):
                out[p] = True
                break


@njit(parallel=True, cache=True, fastmath=True)
def _voxelize_link(  # pragma: no cover - jitted
    counts: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    origin: np.ndarray,
    spacing: float,
    ss: int,
    link_from_cm: np.ndarray,
    z0: float,
    z1: float,
    notches: np.ndarray,
    cuts: np.ndarray,
    r_in2: float,
    r_out2: float,
) -> None:
    """Add, for one link, the number of inside sub-samples of each voxel in the index box [lo, hi)."""
    R = link_from_cm[:3, :3]
    t = link_from_cm[:3, 3]
    h = spacing / ss
    off0 = -0.5 * spacing + 0.5 * h
    for kk in prange(hi[2] - lo[2]):
        k = lo[2] + kk
        for j in range(lo[1], hi[1]):
            for i in range(lo[0], hi[0]):
                cx = origin[0] + i * spacing + off0
                cy = origin[1] + j * spacing + off0
                cz = origin[2] + k * spacing + off0
                n = 0
                for a in range(ss):
                    pz = cz + a * h
                    for b in range(ss):
                        py = cy + b * h
                        for c in range(ss):
                            px = cx + c * h
                            qx = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
                            qy = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
                            qz = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
                            if _inside_link(qx, qy, qz, z0, z1, notches, cuts, r_in2, r_out2):
                                n += 1
                counts[k, j, i] += n


def _link_corners(table: LinkTable, k: int) -> np.ndarray:
    """(8, 3) corners of link ``k``'s straight bounding box."""
    r = table.r_out_mm
    z0, z1 = table.z_range_mm[k]
    return np.array([[sx * r, sy * r, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (z0, z1)])


_F64 = types.float64
_I64 = types.int64

#: the argument types :func:`voxelize_cm` passes to :func:`_voxelize_link`
_VOXELIZE_LINK_ARGS = (
    (
        types.Array(types.int32, 3, "C"),
        types.Array(_I64, 1, "C"),
        types.Array(_I64, 1, "C"),
        types.Array(_F64, 1, "C"),
        _F64,
        _I64,
        types.Array(_F64, 2, "C"),
        _F64,
        _F64,
        types.Array(_F64, 2, "C"),
        types.Array(_F64, 1, "C"),
        _F64,
        _F64,
    ),
)


def compile_kernels() -> None:
    """Compile the CPU voxeliser for the argument types :func:`voxelize_cm` passes into numba's
    on-disk cache, so that a new process's first voxelisation loads the machine code instead of
    compiling it."""
    for args in _VOXELIZE_LINK_ARGS:
        _voxelize_link.compile(args)


def voxelize_cm(
    config: CMConfig | None,
    control_points_deg: np.ndarray | torch.Tensor,
    *,
    spacing_mm: float = 0.05,
    supersample: int = 2,
    margin_mm: float = 0.5,
    region: Region = "solid",
) -> VoxelizedCM:
    """Voxelise the bent CM with partial-volume supersampling.

    Each voxel's occupancy is the fraction of its ``supersample³`` regular sub-samples inside the
    solid. Links are processed one at a time inside the voxel box covering the link's oriented
    bounding box, so the cost scales with the CM's volume, not its bounding box. Where two links'
    material overlaps (the spine wedge at a bent joint) the counts add and are clipped at 1.

    Args:
        config: CM geometry (paper defaults if None).
        control_points_deg: (n,) control points.
        spacing_mm: isotropic voxel size, mm.
        supersample: sub-samples per voxel and axis (1 = centre sampling, a binary mask).
        margin_mm: empty border around the CM's bounding box, mm.
        region: ``"solid"`` or ``"notched"`` (only material between A and B, for mask labels).

    Returns:
        :class:`VoxelizedCM` in the CM base frame (axis-aligned grid).
    """
    config = config or CMConfig()
    if spacing_mm <= 0 or supersample < 1:
        raise ValueError("spacing_mm must be positive and supersample ≥ 1")
    T = _links_np(config, control_points_deg)
    table = link_table(config)
    zclip = region_z_range_mm(config, region)
    return _voxelize(T, table, zclip, float(spacing_mm), int(supersample), margin_mm)


def voxelize_cm_links(
    config: CMConfig,
    cm_from_link: np.ndarray,
    *,
    notches: NotchGeometry | None = None,
    spacing_mm: float = 0.05,
    supersample: int = 2,
    margin_mm: float = 0.5,
    region: Region = "solid",
) -> VoxelizedCM:
    """Voxelise a CM posed by explicit link transforms, with its own notches (an as-built instrument).

    Same grid and partial volumes as :func:`voxelize_cm`, which it equals for the config's notches
    and the spline's link transforms.

    Args:
        config: CM geometry (radii, base and tip, notch sides).
        cm_from_link: (N+1, 4, 4) link poses, e.g.
            :meth:`~fluoronav.manipulator.kinematics.CMKinematics.link_transforms_from_angles`.
        notches: per-notch centres, widths and depths; None: the config's.
        spacing_mm, supersample, margin_mm, region: as for :func:`voxelize_cm` (``"notched"`` ends at
            the distal plane of ``notches``' last notch).

    Returns:
        :class:`VoxelizedCM` in the CM base frame (axis-aligned grid).
    """
    if spacing_mm <= 0 or supersample < 1:
        raise ValueError("spacing_mm must be positive and supersample ≥ 1")
    T = np.asarray(cm_from_link, dtype=np.float64)
    if T.shape != (config.n_notches + 1, 4, 4):
        raise ValueError(f"cm_from_link must have shape ({config.n_notches + 1}, 4, 4), got {T.shape}")
    table = link_table(config, notches)
    zclip = region_z_range_mm(config, region, notches)
    return _voxelize(T, table, zclip, float(spacing_mm), int(supersample), margin_mm)


def _voxelize(
    T: np.ndarray,
    table: LinkTable,
    zclip: tuple[float, float],
    spacing_mm: float,
    supersample: int,
    margin_mm: float,
) -> VoxelizedCM:
    """Partial-volume voxelisation of the links ``T`` (L, 4, 4) of ``table``, clipped to ``zclip``."""
    L = T.shape[0]
    cuts = table.half_notch_cuts()
    corners = np.stack([_link_corners(table, k) @ T[k, :3, :3].T + T[k, :3, 3] for k in range(L)])
    lo_w = corners.reshape(-1, 3).min(axis=0) - margin_mm
    hi_w = corners.reshape(-1, 3).max(axis=0) + margin_mm
    shape_xyz = np.ceil((hi_w - lo_w) / spacing_mm).astype(int) + 1
    origin = lo_w  # centre of voxel (0, 0, 0)
    counts = np.zeros((shape_xyz[2], shape_xyz[1], shape_xyz[0]), dtype=np.int32)
    logger.debug("voxelising CM on a %s grid at %.3f mm", tuple(counts.shape), spacing_mm)
    for k in range(L):
        z0 = max(table.z_range_mm[k, 0], zclip[0])
        z1 = min(table.z_range_mm[k, 1], zclip[1])
        if z1 <= z0:
            continue
        c = corners[k]
        lo = np.clip(np.floor((c.min(axis=0) - origin) / spacing_mm).astype(np.int64) - 1, 0, shape_xyz)
        hi = np.clip(np.ceil((c.max(axis=0) - origin) / spacing_mm).astype(np.int64) + 2, 0, shape_xyz)
        R, t = T[k, :3, :3], T[k, :3, 3]
        link_from_cm = np.eye(4)
        link_from_cm[:3, :3] = R.T
        link_from_cm[:3, 3] = -R.T @ t
        _voxelize_link(
            counts,
            lo,
            hi,
            origin,
            float(spacing_mm),
            int(supersample),
            link_from_cm,
            float(z0),
            float(z1),
            np.ascontiguousarray(table.notches[k]),
            np.ascontiguousarray(cuts[k]),
            table.r_in_mm**2,
            table.r_out_mm**2,
        )
    occupancy = np.minimum(counts.astype(np.float32) / np.float32(supersample**3), np.float32(1.0))
    world_from_index = np.eye(4)
    world_from_index[:3, :3] *= spacing_mm
    world_from_index[:3, 3] = origin
    return VoxelizedCM(occupancy=occupancy, world_from_index=world_from_index, spacing_mm=float(spacing_mm))
