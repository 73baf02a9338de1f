"""Similarity costs against an explicit-loop float64 reference (numpy + scipy.ndimage)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from fluoronav.registration.similarity import (
    NCC,
    GradNCC,
    PatchGradNCC,
    edge_ncc,
    grad_ncc,
    ncc,
    patch_grad_ncc,
    smoothed_sobel,
)


def tube_image(rows: int, cols: int, shift_px: float = 0.0, *, seed: int = 0) -> np.ndarray:
    """Rendered-like test image: two soft tubes, a blob and mild texture; ``shift_px`` moves it in u."""
    v, u = np.mgrid[0:rows, 0:cols].astype(np.float64)
    u = u - shift_px
    img = np.exp(-0.5 * ((u - 0.45 * cols - 0.2 * (v - rows / 2)) / 3.0) ** 2)
    img += 0.7 * np.exp(-0.5 * ((v - 0.3 * rows) / 2.5) ** 2) * (u > 0.2 * cols)
    img += 1.5 * np.exp(-0.5 * (((u - 0.7 * cols) / 5.0) ** 2 + ((v - 0.7 * rows) / 4.0) ** 2))
    rng = np.random.default_rng(seed)
    tex = ndimage.gaussian_filter(rng.standard_normal((rows, cols + 40)), 3.0)
    shift_int = round(shift_px)
    img += 0.05 * tex[:, 20 - shift_int : 20 - shift_int + cols]
    return img


def reference_patch_grad_ncc(
    fixed: np.ndarray,
    moving: np.ndarray,
    r: int,
    stride: int,
    sigma: float,
    mask: np.ndarray | None = None,
    eps_rel: float = 1e-10,
) -> float:
    """Direct per-patch loops, float64; scipy filters (mode='nearest', truncate=3)."""

    def grads(img: np.ndarray) -> list[np.ndarray]:
        img = img.astype(np.float64)
        if sigma > 0:
            img = ndimage.gaussian_filter(img, sigma, mode="nearest", truncate=3.0)
        return [ndimage.sobel(img, axis=1, mode="nearest"), ndimage.sobel(img, axis=0, mode="nearest")]

    H, W = fixed.shape
    m = np.ones((H, W)) if mask is None else mask.astype(np.float64)
    gf, gm = grads(fixed), grads(moving)
    side = 2 * r + 1
    terms = []  # (direction, weight, var_f, var_m, ncc)
    for d in range(2):
        for r0 in range(0, H - 2 * r, stride):
            for c0 in range(0, W - 2 * r, stride):
                sl = (slice(r0, r0 + side), slice(c0, c0 + side))
                sel = m[sl] > 0
                a, b = gf[d][sl][sel], gm[d][sl][sel]
                n = a.size
                va = ((a - a.mean()) ** 2).sum() if n else 0.0
                vb = ((b - b.mean()) ** 2).sum() if n else 0.0
                cov = ((a - a.mean()) * (b - b.mean())).sum() if n else 0.0
                terms.append((d, n, va, vb, cov))
    total = 0.0
    wsum = 0.0
    for d in range(2):
        td = [t for t in terms if t[0] == d]
        vmax_f = max(t[2] for t in td)
        vmax_m = max(t[3] for t in td)
        for _, n, va, vb, cov in td:
            if n < 2 or vmax_f <= 0 or va <= eps_rel * vmax_f:
                continue
            r_ = cov / np.sqrt(va * vb) if (vb > eps_rel * vmax_m and vmax_m > 0) else 0.0
            total += n * (1.0 - r_)
            wsum += n
    return total / wsum if wsum > 0 else 1.0


@pytest.mark.parametrize("r,stride,sigma", [(3, 1, 1.0), (5, 3, 0.0), (7, 4, 1.5)])
def test_patch_grad_ncc_matches_loop_reference_float64(r: int, stride: int, sigma: float) -> None:
    fixed = tube_image(40, 48)
    moving = tube_image(40, 48, shift_px=2.0, seed=1) * 0.8 + 0.1
    ref = reference_patch_grad_ncc(fixed, moving, r, stride, sigma)
    got = patch_grad_ncc(
        torch.from_numpy(fixed), torch.from_numpy(moving)[None], patch_radius=r, stride=stride, sigma_px=sigma
    )
    assert got.dtype == torch.float64 and got.shape == (1,)
    assert abs(float(got[0]) - ref) < 1e-4
    assert 0.01 < ref < 1.5  # the pair is neither identical nor unrelated


def test_patch_grad_ncc_matches_reference_with_mask_and_float32() -> None:
    fixed = tube_image(36, 36)
    moving = tube_image(36, 36, shift_px=-3.0, seed=2)
    mask = np.ones((36, 36), dtype=bool)
    mask[:, :10] = False
    mask[20:25, 20:30] = False
    ref = reference_patch_grad_ncc(fixed, moving, 4, 2, 1.0, mask)
    got64 = patch_grad_ncc(
        torch.from_numpy(fixed),
        torch.from_numpy(moving)[None],
        patch_radius=4,
        stride=2,
        mask=torch.from_numpy(mask),
    )
    got32 = patch_grad_ncc(
        torch.from_numpy(fixed).float(),
        torch.from_numpy(moving).float()[None],
        patch_radius=4,
        stride=2,
        mask=torch.from_numpy(mask),
    )
    assert abs(float(got64[0]) - ref) < 1e-4
    assert got32.dtype == torch.float32
    assert abs(float(got32[0]) - ref) < 1e-3
    unmasked = reference_patch_grad_ncc(fixed, moving, 4, 2, 1.0)
    assert abs(unmasked - ref) > 1e-3  # the mask matters


def test_float32_sums_match_float64_at_registration_scale() -> None:
    # the CM level: 125² ROI, r = 10, stride 5; smooth DRR-like moving images against a noisy fixed one
    rng = np.random.default_rng(3)
    fixed = tube_image(125, 125) + 0.02 * rng.standard_normal((125, 125))
    moving = np.stack([tube_image(125, 125, shift_px=s, seed=4) * 3.0 + 40.0 for s in (-4, -1, 0, 2, 6)])
    c64 = patch_grad_ncc(torch.from_numpy(fixed), torch.from_numpy(moving), patch_radius=10, stride=5)
    c32 = patch_grad_ncc(
        torch.from_numpy(fixed).float(), torch.from_numpy(moving).float(), patch_radius=10, stride=5
    )
    torch.testing.assert_close(c32.double(), c64, rtol=0, atol=2e-4)
    assert int(torch.argmin(c32)) == int(torch.argmin(c64)) == 2


def test_flat_patches_give_no_nan() -> None:
    fixed = np.zeros((30, 30))
    fixed[10:20, 10:20] = 1.0  # most patches flat in the fixed image
    moving = np.zeros((2, 30, 30))
    moving[0] = fixed
    got = patch_grad_ncc(torch.from_numpy(fixed), torch.from_numpy(moving), patch_radius=3, stride=2)
    assert torch.isfinite(got).all()
    assert float(got[0]) < 1e-9  # identical
    assert abs(float(got[1]) - 1.0) < 1e-12  # flat candidate: no correlation anywhere
    ref = reference_patch_grad_ncc(fixed, moving[1], 3, 2, 1.0)
    assert abs(float(got[1]) - ref) < 1e-9
    # a completely flat fixed image carries no information: cost 1, not NaN
    flat = patch_grad_ncc(
        torch.zeros(20, 20, dtype=torch.float64), torch.from_numpy(moving[:, :20, :20]), patch_radius=3
    )
    assert torch.equal(flat, torch.ones(2, dtype=torch.float64))


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-10), (torch.float32, 1e-5)])
def test_identical_images_cost_zero_and_affine_invariance(dtype: torch.dtype, tol: float) -> None:
    img = torch.from_numpy(tube_image(48, 48)).to(dtype)
    moving = torch.stack(
        [img, 3.5 * img - 2.0, 0.2 * img + 10.0]
    )  # offset kept modest: float32 input itself quantises
    for cost in (
        patch_grad_ncc(img, moving, patch_radius=5, stride=2),
        grad_ncc(img, moving),
        ncc(img, moving),
    ):
        assert cost.dtype == dtype
        assert torch.all(cost.abs() < (10 * tol if dtype == torch.float32 else tol)), cost
    # a negative gain inverts the gradients: NCC = −1, cost 2
    assert abs(float(ncc(img, -img[None])[0]) - 2.0) < tol


@pytest.mark.parametrize("cost_name", ["patch", "grad", "ncc"])
def test_shift_sweep_minimum_at_zero(cost_name: str) -> None:
    fixed = torch.from_numpy(tube_image(64, 64))
    shifts = np.arange(-6, 7)
    moving = torch.stack([torch.from_numpy(tube_image(64, 64, float(s))) for s in shifts])
    if cost_name == "patch":
        c = PatchGradNCC(fixed, patch_radius=6, stride=3)(moving)
    elif cost_name == "grad":
        c = GradNCC(fixed)(moving)
    else:
        c = NCC(fixed)(moving)
    c = c.numpy()
    assert shifts[np.argmin(c)] == 0
    # monotone increase away from zero over the first few pixels
    i0 = int(np.where(shifts == 0)[0][0])
    assert np.all(np.diff(c[i0 : i0 + 4]) > 0) and np.all(np.diff(c[i0 - 3 : i0 + 1]) < 0)


def test_batch_equals_loop_and_views() -> None:
    rng = np.random.default_rng(3)
    fixed = torch.from_numpy(np.stack([tube_image(32, 40), tube_image(32, 40, 1.5, seed=5)]))
    moving = torch.from_numpy(
        np.stack(
            [
                np.stack([tube_image(32, 40, float(s)), tube_image(32, 40, float(s) + 1, seed=5)])
                for s in rng.uniform(-3, 3, size=5)
            ]
        )
    )
    mod = PatchGradNCC(fixed, patch_radius=4, stride=2)
    batched = mod(moving)
    assert batched.shape == (5, 2)
    looped = torch.stack([mod(moving[i : i + 1])[0] for i in range(5)])
    torch.testing.assert_close(batched, looped, rtol=0, atol=1e-12)
    # each view equals the single-view (H, W) form
    for v in range(2):
        single = PatchGradNCC(fixed[v], patch_radius=4, stride=2)(moving[:, v])
        torch.testing.assert_close(batched[:, v], single, rtol=0, atol=1e-12)


def test_patch_grid_reported() -> None:
    # the module reports the patch grid it uses: centres r, r+stride, … inside the image
    mod = PatchGradNCC(torch.zeros(30, 41, dtype=torch.float64), patch_radius=5, stride=4)
    assert mod.n_patches == (len(range(5, 25, 4)), len(range(5, 36, 4)))
    with pytest.raises(ValueError):
        PatchGradNCC(torch.zeros(10, 10), patch_radius=5)


def test_smoothed_sobel_matches_scipy() -> None:
    img = tube_image(25, 30)
    gx, gy = smoothed_sobel(torch.from_numpy(img), sigma_px=1.3)
    sm = ndimage.gaussian_filter(img, 1.3, mode="nearest", truncate=3.0)
    np.testing.assert_allclose(gx.numpy() * 8, ndimage.sobel(sm, axis=1, mode="nearest"), atol=1e-12)
    np.testing.assert_allclose(gy.numpy() * 8, ndimage.sobel(sm, axis=0, mode="nearest"), atol=1e-12)


def test_nonfinite_moving_gives_nan_cost() -> None:
    fixed = torch.from_numpy(tube_image(32, 32))
    moving = torch.stack([fixed, fixed.clone()])
    moving[1, 5, 7] = float("nan")
    for mod in (PatchGradNCC(fixed, patch_radius=4, stride=2), GradNCC(fixed), NCC(fixed)):
        c = mod(moving)
        assert float(c[0]) < 1e-9 and torch.isnan(c[1])


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_patch_grad_ncc_cuda_matches_cpu() -> None:
    fixed = torch.from_numpy(tube_image(64, 72)).float()
    moving = torch.stack([torch.from_numpy(tube_image(64, 72, float(s))).float() for s in range(-3, 4)])
    cpu = PatchGradNCC(fixed, patch_radius=6, stride=2)(moving)
    gpu = PatchGradNCC(fixed.cuda(), patch_radius=6, stride=2)(moving.cuda())
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=0, atol=1e-5)


@pytest.mark.parametrize(
    ("r", "stride", "sigma", "masked"),
    [(10, 5, 1.0, True), (3, 1, 2.0, False), (2, 7, 0.0, True), (4, 2, 1.0, False)],
)
def test_numba_kernel_matches_torch_ops_at_registration_scale(
    r: int, stride: int, sigma: float, masked: bool
) -> None:
    """The fused CPU kernel (the default on the CPU) against the torch ops: float32 images as the
    renderers give them, overlapping and disjoint (stride > side) patches, with and without mask."""
    rows, cols = 90, 104
    fixed = torch.from_numpy(tube_image(rows, cols)).float()
    moving = torch.stack(
        [torch.from_numpy(tube_image(rows, cols, s, seed=1)).float() for s in (0.0, 0.7, 2.5, -4.0)]
    )
    mask = torch.from_numpy(np.random.default_rng(3).random((rows, cols)) > 0.3) if masked else None
    kw = dict(patch_radius=r, stride=stride, sigma_px=sigma, mask=mask)
    fast = PatchGradNCC(fixed, **kw)(moving)
    ops = PatchGradNCC(fixed, backend="torch", **kw)(moving)
    assert fast.dtype == torch.float32 and fast.shape == (4,)
    # the kernel sums patches in float64, the torch ops in float32
    torch.testing.assert_close(fast, ops, rtol=0, atol=1e-5)
    ref = reference_patch_grad_ncc(
        fixed.double().numpy(),
        moving[2].double().numpy(),
        r,
        stride,
        sigma,
        None if mask is None else mask.numpy(),
    )
    assert abs(float(fast[2]) - ref) < 1e-5


def test_torch_backend_is_used_where_a_gradient_is_needed() -> None:
    fixed = torch.from_numpy(tube_image(40, 44))
    moving = torch.from_numpy(tube_image(40, 44, 1.0))[None].requires_grad_(True)
    cost = PatchGradNCC(fixed, patch_radius=4, stride=2)(moving)
    cost.sum().backward()
    assert moving.grad is not None and float(moving.grad.abs().sum()) > 0
    with pytest.raises(ValueError, match="backend"):
        PatchGradNCC(fixed, patch_radius=4, backend="cuda")  # type: ignore[arg-type]


def test_edge_ncc_compares_only_the_drrs_outline() -> None:
    yy, xx = np.mgrid[0:64, 0:64]
    disc = ((yy - 32) ** 2 + (xx - 32) ** 2 < 15**2).astype(np.float64)
    assert edge_ncc(disc, disc) == pytest.approx(1.0, abs=1e-9)
    # what lies away from the outline does not count: a far blob added to the image
    blob = disc + 3.0 * (((yy - 5) ** 2 + (xx - 5) ** 2) < 9)
    assert edge_ncc(blob, disc) == pytest.approx(1.0, abs=1e-6)
    assert edge_ncc(-disc, disc) == pytest.approx(-1.0, abs=1e-9)
    assert edge_ncc(disc, np.zeros_like(disc)) == 0.0  # a DRR without edges
    none = torch.zeros(64, 64, dtype=torch.bool)
    assert edge_ncc(disc, disc, mask=none) == 0.0  # no pixel left to compare
