"""Image similarity costs for intensity-based 2D/3D registration (torch, batched).

Every function here returns a *cost* (lower is better), ``1 − NCC`` in [0, 2]. The main cost is the
patch-based gradient NCC of the authors' xReg fork: both images smoothed with a Gaussian,
differentiated with 3×3 Sobel kernels in x (columns) and y (rows), NCC computed per square patch of
each gradient image, the two directions averaged and the patches combined by a weighted mean (a
patch weighs its unmasked pixels, and nothing where the *fixed* gradient is flat). A flat *moving*
patch against a structured fixed one costs 1; a moving image with a non-finite pixel costs NaN. On
the CPU :class:`PatchGradNCC` runs a fused numba kernel with the same thresholds. The conventions
(padding, patch grid, sums, flatness), tested against an explicit-loop reference:
docs/registration.md ("The similarity: patch gradient NCC").
"""

from __future__ import annotations

import math
from typing import Any, Literal

import numpy as np
import torch
from scipy import ndimage
from torch.nn import functional as tnf

__all__ = [
    "NCC",
    "GradNCC",
    "PatchGradNCC",
    "compile_kernels",
    "edge_ncc",
    "grad_ncc",
    "ncc",
    "patch_grad_ncc",
    "smoothed_sobel",
]

_EPS_REL = 1e-10


def compile_kernels() -> None:
    """Compile the CPU patch gradient NCC for the argument types :class:`PatchGradNCC` passes into
    numba's on-disk cache, so that a new process's first cost loads the machine code instead of
    compiling it."""
    from fluoronav.registration._similarity_numba import PATCH_GRAD_NCC_ARGS, patch_grad_ncc_cost

    for args in PATCH_GRAD_NCC_ARGS:
        patch_grad_ncc_cost.compile(args)


# ----- filtering ----------------------------------------------------------------------------------
def _gaussian_kernel1d(sigma_px: float) -> list[float]:
    radius = int(3.0 * sigma_px + 0.5)
    k = [math.exp(-0.5 * (i / sigma_px) ** 2) for i in range(-radius, radius + 1)]
    total = math.fsum(k)
    return [v / total for v in k]


def _corr1d(x: torch.Tensor, k: list[float], dim: int) -> torch.Tensor:
    """Correlation of (N, 1, H, W) with a short odd kernel along ``dim`` (-2 rows, -1 cols), replicate pad.

    Written as a weighted sum of shifted slices: for the 3–7 tap kernels used here this beats
    single-channel ``conv2d`` by a wide margin on CPU, and kernels as Python floats avoid device syncs.
    """
    r = (len(k) - 1) // 2
    pad = (r, r, 0, 0) if dim == -1 else (0, 0, r, r)
    xp = tnf.pad(x, pad, mode="replicate")
    n = x.shape[dim]
    out = xp.narrow(dim, 0, n) * k[0]
    for i in range(1, len(k)):  # loop over kernel taps only (≤ 7), never over pixels or patches
        if k[i] != 0.0:
            out.add_(xp.narrow(dim, i, n), alpha=k[i])  # fused, no temporaries
    return out


def _conv_sep(img: torch.Tensor, k_row: list[float], k_col: list[float]) -> torch.Tensor:
    """Separable correlation of (N, 1, H, W) with kernels along rows (vertical) and columns."""
    return _corr1d(_corr1d(img, k_row, -2), k_col, -1)


def smoothed_sobel(images: torch.Tensor, *, sigma_px: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Gaussian smoothing then 3×3 Sobel derivatives, replicate padding.

    Args:
        images: (..., H, W) images.
        sigma_px: Gaussian standard deviation in pixels; 0 disables smoothing.

    Returns:
        (gx, gy): (..., H, W) derivatives along columns (u) and rows (v), in intensity per pixel
        (kernels normalised by 1/8).
    """
    shape = images.shape
    x = images.reshape(-1, 1, shape[-2], shape[-1])
    if sigma_px > 0:
        g = _gaussian_kernel1d(sigma_px)
        x = _conv_sep(x, g, g)
    smooth, diff = [0.25, 0.5, 0.25], [-0.5, 0.0, 0.5]
    gx = _conv_sep(x, smooth, diff)
    gy = _conv_sep(x, diff, smooth)
    return gx.reshape(shape), gy.reshape(shape)


# ----- patch sums over strided windows -----------------------------------------------------------
def _patch_grid(n: int, radius: int, stride: int) -> torch.Tensor:
    """Start indices of patches of side 2r+1 with centres r, r+stride, … ≤ n−1−r."""
    if 2 * radius + 1 > n:
        raise ValueError(f"patch side {2 * radius + 1} exceeds image size {n}")
    return torch.arange(0, n - 2 * radius, stride)


class _PatchSummer:
    """Sums of images over a fixed patch grid (the windows of :func:`_patch_grid`).

    ``__call__((..., H, W)) -> (..., Pr, Pc)`` in ``accum_dtype``.
    """

    def __init__(
        self, rows: int, cols: int, radius: int, stride: int, device: torch.device, accum_dtype: torch.dtype
    ) -> None:
        if radius < 0 or stride < 1:
            raise ValueError(f"need patch_radius ≥ 0 and stride ≥ 1, got {radius}, {stride}")
        self.side, self.stride = 2 * radius + 1, stride
        self.accum_dtype = accum_dtype
        self.shape = (
            int(_patch_grid(rows, radius, stride).numel()),
            int(_patch_grid(cols, radius, stride).numel()),
        )

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        x = x.to(self.accum_dtype)
        rows = x.unfold(-2, self.side, self.stride).sum(-1)  # (..., Pr, W): windows are views, no copy
        return rows.unfold(-1, self.side, self.stride).sum(-1)


def _as_views(fixed: torch.Tensor, moving: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """Normalise to fixed (V, H, W), moving (B, V, H, W); flag whether the view axis was given."""
    if fixed.dim() == 2:
        if moving.dim() != 3:
            raise ValueError(f"fixed (H, W) needs moving (B, H, W), got {tuple(moving.shape)}")
        return fixed.unsqueeze(0), moving.unsqueeze(1), False
    if fixed.dim() == 3:
        if moving.dim() != 4:
            raise ValueError(f"fixed (V, H, W) needs moving (B, V, H, W), got {tuple(moving.shape)}")
        return fixed, moving, True
    raise ValueError(f"fixed must be (H, W) or (V, H, W), got {tuple(fixed.shape)}")


def _mask_views(mask: torch.Tensor | None, fixed: torch.Tensor) -> torch.Tensor:
    """Mask as float (V, H, W) (ones when None)."""
    if mask is None:
        return torch.ones_like(fixed)
    m = mask.to(device=fixed.device, dtype=fixed.dtype)
    if m.dim() == 2:
        m = m.expand_as(fixed)
    if m.shape != fixed.shape:
        raise ValueError(f"mask shape {tuple(mask.shape)} does not match fixed {tuple(fixed.shape)}")
    return m


def _nan_if_nonfinite(cost: torch.Tensor, moving: torch.Tensor) -> torch.Tensor:
    """NaN cost (B, V) where a moving image (B, V, H, W) has a non-finite pixel: a failed render
    must be visible to the optimiser, not read as "no correlation"."""
    bad = ~torch.isfinite(moving.sum(dim=(-2, -1)))  # a sum keeps any NaN/inf, and is cheaper
    return torch.where(bad, torch.full_like(cost, float("nan")), cost)


# ----- modules (fixed image precomputed once) ------------------------------------------------------
class PatchGradNCC(torch.nn.Module):
    """Patch-based gradient NCC cost against a fixed image, precomputed once.

    Args:
        fixed: (H, W) or (V, H, W) fixed (intra-operative) images.
        patch_radius: patch half side r (patch side 2r + 1), pixels.
        stride: spacing of patch centres, pixels.
        sigma_px: Gaussian smoothing before Sobel, pixels.
        mask: optional (H, W) or (V, H, W) bool/float mask of fixed pixels to use.
        accum_dtype: dtype of the moving images' patch sums; None: float64 for float64 ``fixed``,
            else float32 (fast; NCC within ~1e-4 of float64). The fixed image's statistics are
            always computed in float64.
        eps_rel: flat-patch threshold relative to the largest fixed patch variance.
        flat_rel: a moving patch with centred variance ≤ ``flat_rel`` × its energy Σg² counts as flat
            (NCC 0); None: 1e-5 for float32, 1e-12 for float64 sums (their rounding level).
        backend: ``"auto"``: on the CPU, for moving images that need no gradient, the fused numba
            kernel (:mod:`~fluoronav.registration._similarity_numba`: the same cost with float64 patch
            sums, faster), else torch; ``"torch"``: always torch (autograd, CUDA).

    ``forward(moving (B, V, H, W) or (B, H, W)) -> (B, V) or (B,)`` cost, dtype of ``moving``.
    """

    mask: torch.Tensor
    grad_fixed: torch.Tensor
    n: torch.Tensor
    sum_f: torch.Tensor
    std_f: torch.Tensor
    weight: torch.Tensor
    weight_total: torch.Tensor

    def __init__(
        self,
        fixed: torch.Tensor,
        *,
        patch_radius: int,
        stride: int = 1,
        sigma_px: float = 1.0,
        mask: torch.Tensor | None = None,
        accum_dtype: torch.dtype | None = None,
        eps_rel: float = _EPS_REL,
        flat_rel: float | None = None,
        backend: Literal["auto", "torch"] = "auto",
    ) -> None:
        super().__init__()
        if backend not in ("auto", "torch"):
            raise ValueError(f"backend must be 'auto' or 'torch', got {backend!r}")
        self.backend = backend
        self.has_views = fixed.dim() == 3
        f = fixed if self.has_views else fixed.unsqueeze(0)
        if f.dim() != 3:
            raise ValueError(f"fixed must be (H, W) or (V, H, W), got {tuple(fixed.shape)}")
        self.sigma_px = float(sigma_px)
        self.eps_rel = float(eps_rel)
        self.patch_radius, self.stride = int(patch_radius), int(stride)
        m = _mask_views(mask, f)
        if accum_dtype is None:
            accum_dtype = torch.float64 if fixed.dtype == torch.float64 else torch.float32
        if accum_dtype not in (torch.float32, torch.float64):
            raise ValueError(f"accum_dtype must be float32 or float64, got {accum_dtype}")
        default_flat = 1e-5 if accum_dtype == torch.float32 else 1e-12
        self.flat_rel = float(flat_rel if flat_rel is not None else default_flat)
        self._summer = _PatchSummer(
            f.shape[-2], f.shape[-1], self.patch_radius, self.stride, f.device, accum_dtype
        )
        fixed_summer = _PatchSummer(
            f.shape[-2], f.shape[-1], self.patch_radius, self.stride, f.device, torch.float64
        )
        g = torch.stack(smoothed_sobel(f, sigma_px=self.sigma_px), dim=1) * m.unsqueeze(1)  # (V, 2, H, W)
        n = fixed_summer(m).unsqueeze(1)  # (V, 1, Pr, Pc)
        sf = fixed_summer(g)
        var_f = (fixed_summer(g.double() ** 2) - sf * sf / n.clamp_min(1.0)).clamp_min(0.0)
        vmax = var_f.amax(dim=(-2, -1), keepdim=True)
        informative = (n >= 2) & (var_f > self.eps_rel * vmax) & (vmax > 0)
        weight = torch.where(informative, n.expand_as(var_f), torch.zeros_like(var_f))
        self.register_buffer("mask", m)
        self.register_buffer("grad_fixed", g)  # masked gradients (V, 2, H, W)
        acc = accum_dtype
        self.register_buffer("n", n.to(acc))
        self.register_buffer("sum_f", sf.to(acc))
        self.register_buffer("std_f", var_f.sqrt().to(acc))  # sqrt of the centred sum of squares
        self.register_buffer("weight", weight)  # (V, 2, Pr, Pc) float64
        self.register_buffer("weight_total", weight.sum(dim=(1, 2, 3)))  # (V,)
        # the numba kernel's inputs (float64 fixed statistics), made on its first use
        self._sum_f64, self._std_f64 = sf, var_f.sqrt()
        self._kernel_args: tuple[np.ndarray, ...] | None = None

    @property
    def n_patches(self) -> tuple[int, int]:
        """Patch grid size (rows, cols)."""
        return self._summer.shape

    def patch_ncc(self, moving: torch.Tensor) -> torch.Tensor:
        """Per-patch NCC (B, V, 2, Pr, Pc) for moving (B, V, H, W), 0 where undefined."""
        gm = torch.stack(smoothed_sobel(moving, sigma_px=self.sigma_px), dim=2) * self.mask[:, None]
        n = self.n.clamp_min(1.0)
        sm = self._summer(gm)
        cov = self._summer(gm * self.grad_fixed) - self.sum_f * sm / n
        energy = self._summer(gm * gm)
        var_m = (energy - sm * sm / n).clamp_min(0.0)
        vmax = var_m.amax(dim=(-2, -1), keepdim=True)
        ok = (self.weight > 0) & (var_m > self.eps_rel * vmax) & (var_m > self.flat_rel * energy) & (vmax > 0)
        denom = torch.where(ok, self.std_f * var_m.sqrt(), torch.ones_like(var_m))
        return torch.where(ok, cov / denom, torch.zeros_like(cov)).clamp(-1.0, 1.0)

    def forward(self, moving: torch.Tensor) -> torch.Tensor:
        mv = moving if self.has_views else moving.unsqueeze(1)
        if mv.dim() != 4 or mv.shape[1:] != self.mask.shape:
            raise ValueError(
                f"moving shape {tuple(moving.shape)} does not match fixed {tuple(self.mask.shape)}"
            )
        needs_grad = mv.requires_grad and torch.is_grad_enabled()
        if self.backend == "auto" and mv.device.type == "cpu" and not needs_grad:
            return self._forward_numba(mv, moving)
        r = self.patch_ncc(mv)
        wsum = (self.weight * (1.0 - r.double())).sum(dim=(2, 3, 4))
        total = self.weight_total
        cost = torch.where(total > 0, wsum / total.clamp_min(1e-300), torch.ones_like(wsum))
        cost = _nan_if_nonfinite(cost, mv).to(moving.dtype)
        return cost if self.has_views else cost[:, 0]

    def _forward_numba(self, mv: torch.Tensor, moving: torch.Tensor) -> torch.Tensor:
        from fluoronav.registration._similarity_numba import patch_grad_ncc_cost

        kernel: Any = patch_grad_ncc_cost  # a numba dispatcher
        x = mv.detach().contiguous().numpy()
        if self._kernel_args is None or self._kernel_args[0].dtype != x.dtype:
            g = _gaussian_kernel1d(self.sigma_px) if self.sigma_px > 0 else [1.0]
            self._kernel_args = (
                self.mask.cpu().numpy().astype(x.dtype),
                self.grad_fixed.cpu().numpy().astype(x.dtype),
                self._sum_f64.cpu().numpy(),
                self._std_f64.cpu().numpy(),
                self.n[:, 0].double().cpu().numpy(),
                self.weight.double().cpu().numpy(),
                self.weight_total.double().cpu().numpy(),
                np.asarray(g, dtype=x.dtype),
            )
        cost = kernel(x, *self._kernel_args, self.patch_radius, self.stride, self.eps_rel, self.flat_rel)
        c = torch.from_numpy(cost).to(moving.dtype)
        return c if self.has_views else c[:, 0]


def _global_ncc(f: torch.Tensor, m: torch.Tensor, w: torch.Tensor, eps_rel: float) -> torch.Tensor:
    """NCC over the last two dims with weights w; f, w (..., H, W) broadcast with m; 0 when flat."""
    dt = torch.float64
    f, m, w = f.to(dt), m.to(dt), w.to(dt)
    n = w.sum(dim=(-2, -1)).clamp_min(1e-300)
    fc = f - (w * f).sum(dim=(-2, -1), keepdim=True) / n[..., None, None]
    mc = m - (w * m).sum(dim=(-2, -1), keepdim=True) / n[..., None, None]
    cov = (w * fc * mc).sum(dim=(-2, -1))
    vf = (w * fc * fc).sum(dim=(-2, -1))
    vm = (w * mc * mc).sum(dim=(-2, -1))
    scale_f = (w * f * f).sum(dim=(-2, -1))
    scale_m = (w * m * m).sum(dim=(-2, -1))
    ok = (vf > eps_rel * scale_f) & (vm > eps_rel * scale_m) & (vf > 0) & (vm > 0)
    return torch.where(
        ok, cov / torch.where(ok, (vf * vm).sqrt(), torch.ones_like(vf)), torch.zeros_like(cov)
    )


class NCC(torch.nn.Module):
    """Global NCC cost ``1 − NCC`` over (masked) pixels; a flat image gives cost 1.

    ``forward(moving (B, V, H, W) or (B, H, W)) -> (B, V) or (B,)``.
    """

    fixed: torch.Tensor
    mask: torch.Tensor

    def __init__(
        self, fixed: torch.Tensor, *, mask: torch.Tensor | None = None, eps_rel: float = _EPS_REL
    ) -> None:
        super().__init__()
        self.has_views = fixed.dim() == 3
        f = fixed if self.has_views else fixed.unsqueeze(0)
        self.eps_rel = float(eps_rel)
        self.register_buffer("fixed", f)
        self.register_buffer("mask", _mask_views(mask, f))

    def forward(self, moving: torch.Tensor) -> torch.Tensor:
        _, mv, _ = _as_views(self.fixed, moving if self.has_views else moving.unsqueeze(1))
        c = 1.0 - _global_ncc(self.fixed, mv, self.mask, self.eps_rel)
        c = _nan_if_nonfinite(c, mv).to(moving.dtype)
        return c if self.has_views else c[:, 0]


class GradNCC(torch.nn.Module):
    """Global gradient NCC cost: ``1 − (NCC(gx) + NCC(gy)) / 2`` after Gaussian + Sobel.

    ``forward(moving (B, V, H, W) or (B, H, W)) -> (B, V) or (B,)``.
    """

    grad_fixed: torch.Tensor
    mask: torch.Tensor

    def __init__(
        self,
        fixed: torch.Tensor,
        *,
        sigma_px: float = 1.0,
        mask: torch.Tensor | None = None,
        eps_rel: float = _EPS_REL,
    ) -> None:
        super().__init__()
        self.has_views = fixed.dim() == 3
        f = fixed if self.has_views else fixed.unsqueeze(0)
        self.sigma_px, self.eps_rel = float(sigma_px), float(eps_rel)
        self.register_buffer("grad_fixed", torch.stack(smoothed_sobel(f, sigma_px=self.sigma_px), dim=1))
        self.register_buffer("mask", _mask_views(mask, f))

    def forward(self, moving: torch.Tensor) -> torch.Tensor:
        mv = moving if self.has_views else moving.unsqueeze(1)
        gm = torch.stack(smoothed_sobel(mv, sigma_px=self.sigma_px), dim=2)
        r = _global_ncc(self.grad_fixed, gm, self.mask[:, None], self.eps_rel)  # (B, V, 2)
        c = _nan_if_nonfinite(1.0 - r.mean(dim=-1), mv).to(moving.dtype)
        return c if self.has_views else c[:, 0]


# ----- functional forms ---------------------------------------------------------------------------
def patch_grad_ncc(
    fixed: torch.Tensor,
    moving: torch.Tensor,
    *,
    patch_radius: int,
    stride: int = 1,
    sigma_px: float = 1.0,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Patch-based gradient NCC cost (see module docstring for the exact definition).

    Args:
        fixed: (H, W) or (V, H, W).
        moving: (B, H, W) or (B, V, H, W) respectively.
        patch_radius: r, patch side 2r + 1 pixels.
        stride: spacing of patch centres, pixels.
        sigma_px: Gaussian smoothing before Sobel, pixels (0 = none).
        mask: optional (H, W) or (V, H, W) mask of fixed-image pixels to use.

    Returns:
        (B,) or (B, V) cost in [0, 2], lower is better.
    """
    _as_views(fixed, moving)
    return PatchGradNCC(fixed, patch_radius=patch_radius, stride=stride, sigma_px=sigma_px, mask=mask).to(
        moving.device
    )(moving)


def grad_ncc(
    fixed: torch.Tensor, moving: torch.Tensor, *, sigma_px: float = 1.0, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """Global gradient NCC cost; shapes as :func:`patch_grad_ncc`."""
    _as_views(fixed, moving)
    return GradNCC(fixed, sigma_px=sigma_px, mask=mask)(moving)


def ncc(fixed: torch.Tensor, moving: torch.Tensor, *, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Global intensity NCC cost ``1 − NCC``; shapes as :func:`patch_grad_ncc`."""
    _as_views(fixed, moving)
    return NCC(fixed, mask=mask)(moving)


def edge_ncc(
    image: np.ndarray | torch.Tensor,
    drr: np.ndarray,
    *,
    mask: torch.Tensor | None = None,
    dilate_px: int = 2,
    sigma_px: float = 1.0,
) -> float:
    """Gradient NCC (−1 … 1) of ``image`` and ``drr`` (both (h, w)) on the DRR's edges; 0 where it
    has none.

    The edge pixels are those whose smoothed DRR gradient magnitude exceeds a tenth of its maximum,
    dilated by ``dilate_px`` (and within ``mask`` where given): the comparison is about where the
    registered object's outline lies, not about what surrounds it. Both arrays are used in the
    precision they come in.
    """
    d = np.asarray(drr)
    gy, gx = np.gradient(ndimage.gaussian_filter(d, sigma_px))
    mag = np.hypot(gx, gy)
    if not np.isfinite(mag).all() or mag.max() <= 0:
        return 0.0
    edges = torch.as_tensor(ndimage.binary_dilation(mag > 0.1 * mag.max(), iterations=dilate_px))
    if mask is not None:
        edges = edges & mask
    fixed = image if isinstance(image, torch.Tensor) else torch.as_tensor(np.asarray(image))
    cost = float(grad_ncc(fixed, torch.as_tensor(d)[None], sigma_px=sigma_px, mask=edges)[0])
    return 1.0 - cost if np.isfinite(cost) else 0.0
