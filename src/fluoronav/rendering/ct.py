"""Digitally reconstructed radiographs (DRRs) of a CT: line integrals ∫ μ dl through a voxel volume.

The volume holds μ (1/mm) at voxel centres, interpolated trilinearly with 0 outside the grid (the
interpolant's support is the open index box ``(-1, n)`` per axis). A ray from the X-ray source (camera origin,
OpenCV pinhole) through a pixel centre is clipped to that box and integrated with the midpoint rule at an even
step no longer than ``step_mm``, weighted in mm: the result is the dimensionless ∫ μ dl, and an axis-aligned
integral equals the voxel sum times the spacing. Backends: ``"numba"`` (a parallel CPU kernel,
:mod:`fluoronav.rendering._ct_numba`) and ``"torch"`` (a batched :func:`torch.nn.functional.grid_sample`
march, used on CUDA). With ``mipmap=True`` a camera whose pixel footprint at the volume's nearest point is at
least two voxels along an axis renders the volume box-downsampled 2× along it (the box average keeps every
line integral along the grid axes), which removes the aliasing of coarse pixels on a fine volume.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812

from fluoronav.anatomy.volume import MU_WATER_PER_MM, Volume, hu_to_mu
from fluoronav.device import resolve_device
from fluoronav.geometry.camera import Camera
from fluoronav.rendering._ct_numba import (
    CHESSBOARD_ARGS,
    MARCH_RAYS_ARGS,
    _chessboard_passes,
    empty_space_distance,
    march_rays,
)

__all__ = [
    "DEFAULT_STEP_VOXELS",
    "QUANTISED_LEVELS",
    "CTRenderer",
    "compile_kernels",
    "mipmap_factors",
    "quantise_uint16",
    "render_line_integrals",
]

logger = logging.getLogger(__name__)

#: Default step along the ray in units of the smallest voxel spacing of the grid being sampled.
#: A finer step changes the DRR far less than the voxelisation's own error, at 2-4× the cost
#: (docs/validation.md).
DEFAULT_STEP_VOXELS = 1.0

#: The numba kernel's "no empty-space skipping" argument.
_NO_SKIP = np.zeros(0, np.uint8)

#: Samples per torch chunk (bounds the (rays, samples, 3) grid to ~100 MB in float32).
_TORCH_CHUNK_SAMPLES = 8_000_000

#: The largest value of a quantised (uint16) volume.
QUANTISED_LEVELS = 65535

#: Voxels quantised at a time (bounds :func:`quantise_uint16`'s float64 temporaries to ~32 MB).
_QUANTISE_CHUNK_VOXELS = 1 << 22

Factors = tuple[int, int, int]


# ----- geometry helpers -------------------------------------------------------------------------
def _as_f64(x: torch.Tensor | np.ndarray, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    arr = x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, np.float64)
    if arr.shape == shape_tail:
        arr = arr[None]
    if arr.shape[1:] != shape_tail:
        raise ValueError(f"{name} must have shape (V, {', '.join(map(str, shape_tail))}), got {arr.shape}")
    return arr


def _spacing_from(world_from_index: np.ndarray) -> np.ndarray:
    """(3,) voxel size along i, j, k (column norms of the linear part)."""
    return np.linalg.norm(world_from_index[:3, :3], axis=0)


def mipmap_factors(
    world_from_index: np.ndarray,
    shape_zyx: tuple[int, int, int],
    K: np.ndarray,
    camera_from_world: np.ndarray,
) -> Factors:
    """Per-axis downsampling factors (fi, fj, fk) ∈ {1, 2} for one camera.

    An axis is halved when the pixel footprint at the volume corner nearest to the source
    (depth / focal length, mm) covers at least two voxels along it. A source inside or beside the
    volume (a corner at depth ≤ 0) gets no downsampling.
    """
    nz, ny, nx = shape_zyx
    corners = np.array(
        [[i, j, k, 1.0] for i in (-0.5, nx - 0.5) for j in (-0.5, ny - 0.5) for k in (-0.5, nz - 0.5)]
    )
    depth = (corners @ (camera_from_world @ world_from_index).T)[:, 2]
    if depth.min() <= 0.0:
        return (1, 1, 1)
    footprint_mm = depth.min() / max(K[0, 0], K[1, 1])
    spacing = _spacing_from(world_from_index)
    f = [2 if footprint_mm >= 2.0 * s and n > 1 else 1 for s, n in zip(spacing, (nx, ny, nz), strict=True)]
    return (f[0], f[1], f[2])


def _downsample(
    mu: torch.Tensor, world_from_index: np.ndarray, factors: Factors
) -> tuple[torch.Tensor, np.ndarray]:
    """Box-average ``mu`` by (fi, fj, fk); odd sizes are padded with the zero outside the grid."""
    fi, fj, fk = factors
    nz, ny, nx = mu.shape
    pad = (0, (-nx) % fi, 0, (-ny) % fj, 0, (-nz) % fk)
    x = F.pad(mu[None, None], pad) if any(pad) else mu[None, None]
    small = F.avg_pool3d(x, kernel_size=(fk, fj, fi), stride=(fk, fj, fi))[0, 0].contiguous()
    # new voxel centre i' sits at old index f·i' + (f − 1)/2
    S = np.diag([fi, fj, fk, 1.0])
    S[:3, 3] = [(fi - 1) / 2.0, (fj - 1) / 2.0, (fk - 1) / 2.0]
    return small, world_from_index @ S


def _ray_setup(
    world_from_index: np.ndarray, K: np.ndarray, camera_from_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per camera: index_from_pixel (V,3,3), mm_from_pixel (V,3,3), source_index (V,3)."""
    index_from_world = np.linalg.inv(world_from_index)
    R = camera_from_world[:, :3, :3]
    t = camera_from_world[:, :3, 3]
    Rt = np.transpose(R, (0, 2, 1))
    mm_from_pixel = Rt @ np.linalg.inv(K)  # world direction of (u, v, 1)
    index_from_pixel = index_from_world[:3, :3] @ mm_from_pixel
    source_world = -np.einsum("vij,vj->vi", Rt, t)
    source_index = source_world @ index_from_world[:3, :3].T + index_from_world[:3, 3]
    return index_from_pixel, mm_from_pixel, source_index


def quantise_uint16(
    values: np.ndarray, scale: float | None = None, *, out: np.ndarray | None = None
) -> tuple[np.ndarray, float]:
    """``values`` (any shape, ≥ 0) as uint16 multiples of ``scale``, ``round(values / scale)``, and the
    scale; a ray march is linear in the voxels, so the quantised volume's integral times the scale
    is the float one's to within half a step per sample. Default scale: the maximum over
    :data:`QUANTISED_LEVELS` (1.0 for an all-zero volume), the finest step that represents every
    value; values above ``QUANTISED_LEVELS · scale`` are clipped. Done in chunks, into ``out`` if
    given (uint16, the shape of ``values``), so a fine volume needs no float temporary of its size.
    """
    flat = np.asarray(values).reshape(-1)
    if flat.size and float(flat.min()) < 0.0:
        raise ValueError("quantise_uint16 needs non-negative values")
    if scale is None:
        top = float(flat.max()) if flat.size else 0.0
        scale = top / QUANTISED_LEVELS if top > 0.0 else 1.0
    if not scale > 0.0 or not math.isfinite(scale):
        raise ValueError(f"scale must be positive, got {scale}")
    q = np.empty(np.shape(values), np.uint16) if out is None else out
    if q.dtype != np.uint16 or q.shape != np.shape(values) or not q.flags.c_contiguous:
        raise ValueError("out must be a C-contiguous uint16 array of the values' shape")
    q_flat = q.reshape(-1)
    for lo in range(0, flat.size, _QUANTISE_CHUNK_VOXELS):
        part = np.rint(flat[lo : lo + _QUANTISE_CHUNK_VOXELS].astype(np.float64) / scale)
        q_flat[lo : lo + _QUANTISE_CHUNK_VOXELS] = np.minimum(part, QUANTISED_LEVELS)
    return q, float(scale)


# ----- backends ---------------------------------------------------------------------------------
def _march_numba(
    mu: torch.Tensor,
    index_from_pixel: np.ndarray,
    mm_from_pixel: np.ndarray,
    source_index: np.ndarray,
    step_mm: float,
    out: torch.Tensor,
    skip: np.ndarray | None = None,
) -> None:
    vol = mu.detach()
    if vol.dtype not in (torch.float32, torch.float64, torch.uint16):
        vol = vol.float()
    vol_np = np.ascontiguousarray(vol.cpu().numpy())
    image_dtype = torch.float32 if vol.dtype == torch.uint16 else vol.dtype  # uint16 is read as float32
    dist = _NO_SKIP if skip is None else skip
    if out.is_contiguous() and out.device.type == "cpu" and out.dtype == image_dtype:
        march_rays(vol_np, index_from_pixel, mm_from_pixel, source_index, float(step_mm), out.numpy(), dist)
    else:
        tmp = np.empty(tuple(out.shape), dtype=np.float32 if vol.dtype == torch.uint16 else vol_np.dtype)
        march_rays(vol_np, index_from_pixel, mm_from_pixel, source_index, float(step_mm), tmp, dist)
        out.copy_(torch.from_numpy(tmp))


def _march_torch(
    mu: torch.Tensor,
    index_from_pixel: np.ndarray,
    mm_from_pixel: np.ndarray,
    source_index: np.ndarray,
    step_mm: float,
    out: torch.Tensor,
    *,
    chunk_samples: int = _TORCH_CHUNK_SAMPLES,
) -> None:
    """grid_sample ray march: the same clipping, midpoint samples and weights as the numba kernel."""
    dev = mu.device
    dtype = mu.dtype if mu.dtype in (torch.float32, torch.float64) else torch.float32
    vol = mu.to(dtype)
    shift = 0.0
    if min(vol.shape) < 2:  # grid_sample cannot interpolate a 1-voxel axis against the zero outside
        vol = F.pad(vol[None, None], (1, 1, 1, 1, 1, 1))[0, 0]
        shift = 1.0
    nz, ny, nx = mu.shape
    pz, py, px = vol.shape
    V, rows, cols = out.shape
    vv, uu = torch.meshgrid(
        torch.arange(rows, device=dev, dtype=torch.float64),
        torch.arange(cols, device=dev, dtype=torch.float64),
        indexing="ij",
    )
    pix = torch.stack([uu.reshape(-1), vv.reshape(-1), torch.ones_like(uu).reshape(-1)], dim=-1)  # (P, 3)
    hi = torch.tensor([nx, ny, nz], device=dev, dtype=torch.float64)
    # align_corners=True normalisation of padded index coordinates
    scale = torch.tensor(
        [2.0 / max(px - 1, 1), 2.0 / max(py - 1, 1), 2.0 / max(pz - 1, 1)], device=dev, dtype=torch.float64
    )
    vol5 = vol[None, None]
    for c in range(V):
        A = torch.as_tensor(index_from_pixel[c], device=dev)
        W = torch.as_tensor(mm_from_pixel[c], device=dev)
        s = torch.as_tensor(source_index[c], device=dev)
        d = (pix @ A.T) / torch.linalg.norm(pix @ W.T, dim=-1, keepdim=True)  # index units per mm
        safe = torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
        ta = (-1.0 - s) / safe
        tb = (hi - s) / safe
        tlo = torch.minimum(ta, tb)
        thi = torch.maximum(ta, tb)
        parallel = d.abs() < 1e-12
        outside = parallel & ((s <= -1.0) | (s >= hi))
        tlo = torch.where(parallel, torch.full_like(tlo, -1e30), tlo)
        thi = torch.where(parallel, torch.full_like(thi, 1e30), thi)
        t0 = tlo.amax(dim=-1).clamp_min(0.0)
        t1 = thi.amin(dim=-1)
        valid = (t1 > t0) & ~outside.any(dim=-1)
        length = torch.where(valid, t1 - t0, torch.zeros_like(t0))
        n = torch.ceil(length / step_mm).clamp_min(1).to(torch.int64)
        h = length / n
        img = torch.zeros(rows * cols, device=dev, dtype=dtype)
        idx = torch.nonzero(valid).squeeze(-1)
        if idx.numel():
            n_max = int(n[idx].max())
            chunk = max(1, chunk_samples // n_max)
            # per ray in float64: normalised grid position of the first sample and the increment;
            # the (R, M, 3) sample grid itself is built in the volume's dtype
            g0 = ((s + d * (t0 + 0.5 * h)[:, None] + shift) * scale - 1.0).to(dtype)
            g_step = (d * h[:, None] * scale).to(dtype)
            m = torch.arange(n_max, device=dev, dtype=dtype)
            for lo in range(0, idx.numel(), chunk):
                r = idx[lo : lo + chunk]
                g = g0[r, None, :] + m[None, :, None] * g_step[r, None, :]  # (R, M, 3) as (i, j, k)
                val = F.grid_sample(
                    vol5, g[None, :, :, None, :], mode="bilinear", padding_mode="zeros", align_corners=True
                )[0, 0, :, :, 0]  # (R, M)
                val = torch.where(m[None, :] < n[r, None], val, torch.zeros_like(val))
                img[r] = (val.sum(dim=-1, dtype=torch.float64) * h[r]).to(dtype)
        out[c] = img.reshape(rows, cols)


# ----- public API -------------------------------------------------------------------------------
def compile_kernels() -> None:
    """Compile the CPU ray march for the argument types this module passes into numba's on-disk
    cache, so that a new process's first render loads the machine code instead of compiling it."""
    for args in MARCH_RAYS_ARGS:
        march_rays.compile(args)
    _chessboard_passes.compile(CHESSBOARD_ARGS)


class _Pyramid:
    """The volume and its lazily built 2× box-downsampled versions, keyed by per-axis factors, with
    each one's empty-space distance (numba backend) when ``skip_empty``; a quantised volume's
    rendered values are its integrals times ``scale`` (None: the volume holds the values)."""

    def __init__(
        self,
        mu: torch.Tensor,
        world_from_index: np.ndarray,
        *,
        skip_empty: bool = False,
        scale: float | None = None,
    ) -> None:
        self.levels: dict[Factors, tuple[torch.Tensor, np.ndarray]] = {(1, 1, 1): (mu, world_from_index)}
        self.skip_empty = skip_empty
        self.scale = scale
        self._skip: dict[Factors, np.ndarray] = {}

    def get(self, factors: Factors) -> tuple[torch.Tensor, np.ndarray]:
        if factors not in self.levels:
            mu, w = self.levels[(1, 1, 1)]
            # a uint16 level is averaged in float32, in the same units
            self.levels[factors] = _downsample(mu if mu.is_floating_point() else mu.float(), w, factors)
            logger.debug("built mipmap level %s: shape %s", factors, tuple(self.levels[factors][0].shape))
        return self.levels[factors]

    def skip(self, factors: Factors) -> np.ndarray | None:
        """The empty-space distance of a level, or None without skipping."""
        if not self.skip_empty:
            return None
        if factors not in self._skip:
            self._skip[factors] = empty_space_distance(self.get(factors)[0].detach().cpu().numpy())
        return self._skip[factors]


def _render(
    pyramid: _Pyramid,
    K: np.ndarray,
    camera_from_world: np.ndarray,
    rows: int,
    cols: int,
    *,
    step_mm: float | None,
    backend: str,
    mipmap: bool,
    out: torch.Tensor | None,
) -> torch.Tensor:
    mu, w = pyramid.levels[(1, 1, 1)]
    V = K.shape[0]
    if camera_from_world.shape[0] != V:
        raise ValueError(f"K has {V} cameras but camera_from_world has {camera_from_world.shape[0]}")
    dtype = mu.dtype if mu.dtype in (torch.float32, torch.float64) else torch.float32
    if out is None:
        out = torch.empty((V, rows, cols), dtype=dtype, device=mu.device)
    elif tuple(out.shape) != (V, rows, cols):
        raise ValueError(f"out must have shape {(V, rows, cols)}, got {tuple(out.shape)}")
    if backend == "auto":
        backend = "numba" if mu.device.type == "cpu" else "torch"
    if backend not in ("numba", "torch"):
        raise ValueError(f"unknown backend {backend!r}; use auto, numba or torch")
    shape = tuple(mu.shape)
    groups: dict[Factors, list[int]] = {}
    for c in range(V):
        f = mipmap_factors(w, shape, K[c], camera_from_world[c]) if mipmap else (1, 1, 1)  # type: ignore[arg-type]
        groups.setdefault(f, []).append(c)
    for f, cams in groups.items():
        vol, w_level = pyramid.get(f)
        step = (
            float(step_mm)
            if step_mm is not None
            else DEFAULT_STEP_VOXELS * float(_spacing_from(w_level).min())
        )
        if step <= 0 or not math.isfinite(step):
            raise ValueError(f"step_mm must be positive, got {step_mm}")
        A, W, s = _ray_setup(w_level, K[cams], camera_from_world[cams])
        sel = out[cams[0] : cams[-1] + 1] if cams == list(range(cams[0], cams[-1] + 1)) else None
        target = (
            sel
            if sel is not None
            else torch.empty((len(cams), rows, cols), dtype=out.dtype, device=out.device)
        )
        if backend == "numba":
            _march_numba(vol, A, W, s, step, target, pyramid.skip(f))
        else:
            _march_torch(vol, A, W, s, step, target)
        if pyramid.scale is not None:
            target.mul_(pyramid.scale)
        if sel is None:
            out[cams] = target
    return out


def render_line_integrals(
    mu: torch.Tensor,
    world_from_index: torch.Tensor | np.ndarray,
    K: torch.Tensor | np.ndarray,
    camera_from_world: torch.Tensor | np.ndarray,
    rows: int,
    cols: int,
    *,
    step_mm: float | None = None,
    backend: str = "auto",
    mipmap: bool = True,
    out: torch.Tensor | None = None,
) -> torch.Tensor:
    """Line integrals ∫ μ dl through a voxel volume for V pinhole cameras.

    Args:
        mu: (nz, ny, nx) attenuation in 1/mm, SimpleITK array order (float32 or float64; the
            device of ``mu`` is where the rendering runs).
        world_from_index: (4, 4) continuous index (i, j, k, 1) → world mm (any direction cosines,
            anisotropic spacing).
        K: (V, 3, 3) or (3, 3) intrinsics in pixels (OpenCV).
        camera_from_world: (V, 4, 4) or (4, 4) rigid poses; the source is the camera origin.
        rows, cols: image size shared by the V cameras.
        step_mm: largest sample spacing along a ray, mm; default ``DEFAULT_STEP_VOXELS`` times the
            smallest voxel spacing of the grid sampled (after mipmapping).
        backend: ``"auto"`` (numba on CPU, torch elsewhere), ``"numba"`` or ``"torch"``.
        mipmap: render a 2× box-downsampled volume along axes where the pixel footprint covers
            ≥ 2 voxels (anti-aliasing; see the module docstring). Each call rebuilds the
            downsampled volume; use :class:`CTRenderer` to keep it across calls.
        out: optional (V, rows, cols) tensor to write into.

    Returns:
        (V, rows, cols) dimensionless line integrals, dtype of ``mu`` (float32 unless float64).
    """
    if mu.ndim != 3:
        raise ValueError(f"mu must be (nz, ny, nx), got shape {tuple(mu.shape)}")
    w = _as_f64(world_from_index, (4, 4), "world_from_index")[0]
    Ks = _as_f64(K, (3, 3), "K")
    Ts = _as_f64(camera_from_world, (4, 4), "camera_from_world")
    if Ks.shape[0] == 1 and Ts.shape[0] > 1:
        Ks = np.repeat(Ks, Ts.shape[0], axis=0)
    if Ts.shape[0] == 1 and Ks.shape[0] > 1:
        Ts = np.repeat(Ts, Ks.shape[0], axis=0)
    return _render(
        _Pyramid(mu, w),
        Ks,
        Ts,
        int(rows),
        int(cols),
        step_mm=step_mm,
        backend=backend,
        mipmap=mipmap,
        out=out,
    )


class CTRenderer:
    """DRRs of one μ volume for any number of cameras.

    The volume is converted once to a contiguous tensor on ``device``; mipmap levels are built on
    first use and kept.

    Args:
        volume_mu: a :class:`~fluoronav.anatomy.Volume` whose ``data`` is μ in 1/mm (use
            :meth:`from_hu` for a CT in HU).
        device: ``"cpu"``, ``"cuda"``, ``"auto"`` or a torch device.
        dtype: torch.float32 (default) or torch.float64.
        step_mm, backend, mipmap: see :func:`render_line_integrals`.
        skip_empty: skip the empty space of the volume (numba backend; the same integrals, see
            :mod:`fluoronav.rendering._ct_numba`); each level's distance map is built on first use.

    Attributes:
        mu: the stored volume (nz, ny, nx): float, or uint16 in units of ``scale``
            (:meth:`from_tensor`'s ``quantise``).
        scale: a uint16 ``mu``'s value per unit, or None (``mu`` holds the values).
    """

    def __init__(
        self,
        volume_mu: Volume,
        *,
        device: str | torch.device = "auto",
        dtype: torch.dtype = torch.float32,
        step_mm: float | None = None,
        backend: str = "auto",
        mipmap: bool = True,
        skip_empty: bool = True,
    ) -> None:
        data = np.ascontiguousarray(
            np.asarray(volume_mu.data), dtype=np.float32 if dtype == torch.float32 else np.float64
        )
        self._setup(
            torch.from_numpy(data).to(resolve_device(device)),
            np.asarray(volume_mu.world_from_index, dtype=np.float64),
            step_mm=step_mm,
            backend=backend,
            mipmap=mipmap,
            skip_empty=skip_empty,
        )

    def _setup(
        self,
        mu: torch.Tensor,
        world_from_index: np.ndarray,
        *,
        step_mm: float | None,
        backend: str,
        mipmap: bool,
        skip_empty: bool,
        scale: float | None = None,
    ) -> None:
        self.mu = mu
        self.scale = scale
        self.device = mu.device
        self.world_from_index = world_from_index
        self.step_mm = step_mm
        self.backend = backend
        self.mipmap = mipmap
        self._pyramid = _Pyramid(self.mu, self.world_from_index, skip_empty=skip_empty, scale=scale)

    @classmethod
    def from_tensor(
        cls,
        mu: torch.Tensor,
        world_from_index: np.ndarray,
        *,
        step_mm: float | None = None,
        backend: str = "auto",
        mipmap: bool = True,
        skip_empty: bool = True,
        quantise: bool = False,
        scale: float | None = None,
    ) -> CTRenderer:
        """Renderer of a (nz, ny, nx) μ tensor (1/mm, rendered on its device) with its (4, 4)
        ``world_from_index``; the tensor is used as it is, not copied.

        With ``quantise``, a float ``mu`` on the CPU is stored as uint16 (:func:`quantise_uint16`,
        a half or a quarter of its memory; the integrals change by at most half a step per sample
        and stay float32); on another device (the torch march) ``mu`` is kept as it is. A uint16
        ``mu`` is taken as quantised already, ``scale`` (default 1) per unit.
        """
        if mu.ndim != 3:
            raise ValueError(f"mu must be (nz, ny, nx), got shape {tuple(mu.shape)}")
        if scale is not None and mu.dtype != torch.uint16:
            raise ValueError(f"scale is for a uint16 volume, got {mu.dtype}")
        if quantise and mu.is_floating_point() and mu.device.type == "cpu":
            q, scale = quantise_uint16(mu.detach().numpy())
            mu = torch.from_numpy(q)
        elif mu.dtype == torch.uint16 and scale is None:
            scale = 1.0
        self = cls.__new__(cls)
        self._setup(
            mu.contiguous(),
            np.asarray(world_from_index, np.float64),
            step_mm=step_mm,
            backend=backend,
            mipmap=mipmap,
            skip_empty=skip_empty,
            scale=scale,
        )
        return self

    def mu_values(self) -> torch.Tensor:
        """The volume the renderer integrates (nz, ny, nx): ``mu``, or a quantised one's values as
        float32 (a new tensor, ``mu`` times ``scale``)."""
        return self.mu if self.scale is None else self.mu.float() * self.scale

    @classmethod
    def from_hu(
        cls, volume_hu: Volume, *, mu_water_per_mm: float = MU_WATER_PER_MM, **kwargs: object
    ) -> CTRenderer:
        """Renderer of a CT in HU, with ``μ = mu_water_per_mm · max(0, 1 + HU/1000)``."""
        mu = volume_hu.replace(data=hu_to_mu(volume_hu.data, mu_water_per_mm), labels=None)
        return cls(mu, **kwargs)  # type: ignore[arg-type]

    def render(self, cameras: Sequence[Camera], *, out: torch.Tensor | None = None) -> torch.Tensor:
        """Line integrals (V, rows, cols) for cameras of the same image size (any K and pose)."""
        cams = list(cameras)
        if not cams:
            raise ValueError("no cameras given")
        rows, cols = cams[0].rows, cams[0].cols
        if any((c.rows, c.cols) != (rows, cols) for c in cams):
            raise ValueError("cameras passed together must share rows and cols; render them separately")
        K = np.stack([c.K for c in cams])
        T = np.stack([c.camera_from_world for c in cams])
        return _render(
            self._pyramid,
            K,
            T,
            rows,
            cols,
            step_mm=self.step_mm,
            backend=self.backend,
            mipmap=self.mipmap,
            out=out,
        )

    def render_poses(
        self,
        K: np.ndarray,
        camera_from_world: np.ndarray,
        rows: int,
        cols: int,
        *,
        out: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Line integrals (V, rows, cols) for intrinsics ``K`` (V, 3, 3) and poses
        ``camera_from_world`` (V, 4, 4) (either may be a single (3, 3) / (4, 4))."""
        Ks = _as_f64(K, (3, 3), "K")
        Ts = _as_f64(camera_from_world, (4, 4), "camera_from_world")
        if Ks.shape[0] == 1 and Ts.shape[0] > 1:
            Ks = np.repeat(Ks, Ts.shape[0], axis=0)
        return _render(
            self._pyramid,
            Ks,
            Ts,
            int(rows),
            int(cols),
            step_mm=self.step_mm,
            backend=self.backend,
            mipmap=self.mipmap,
            out=out,
        )

    def render_one(self, camera: Camera) -> torch.Tensor:
        """Line integrals (rows, cols) for one camera."""
        return self.render([camera])[0]
