"""Quantised (uint16) CT volumes: the same ray march, the float32 integrals up to the quantisation."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from fluoronav.geometry.carm import carm_camera_from_world
from fluoronav.rendering import _ct_numba, ct
from fluoronav.rendering._ct_numba import empty_space_distance
from fluoronav.rendering.ct import QUANTISED_LEVELS, CTRenderer, quantise_uint16

#: a quantised image's largest difference to the float32 one, relative to the image's maximum
REL_TOL = 1e-4


def _volume(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random μ (1/mm) inside a ball, zero (empty space) around it, on a rotated
    anisotropic grid."""
    rng = np.random.default_rng(seed)
    nz, ny, nx = 36, 40, 44
    field = ndimage.gaussian_filter(rng.normal(size=(nz, ny, nx)), 2.0)
    mu = (0.02 + 0.2 * np.clip(field, 0.0, None)).astype(np.float32)
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    mu[(i - nx / 2) ** 2 + (j - ny / 2) ** 2 + (k - nz / 2) ** 2 > 16.0**2] = 0.0
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    W = np.eye(4)
    W[:3, :3] = R @ np.diag([0.9, 1.1, 1.3])
    W[:3, 3] = -W[:3, :3] @ np.array([nx / 2, ny / 2, nz / 2])
    return mu, W


def _views(seed: int, n: int = 3) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    T = np.stack(
        [
            carm_camera_from_world(
                lao_rao_deg=float(a), cran_caud_deg=float(b), source_to_isocenter_mm=float(s)
            )
            for a, b, s in zip(
                rng.uniform(-180, 180, n), rng.uniform(0, 180, n), rng.uniform(80, 300, n), strict=True
            )
        ]
    )
    f = np.array([[400.0, 0.0, 23.5], [0.0, 400.0, 21.5], [0.0, 0.0, 1.0]])
    return np.repeat(f[None], n, axis=0), T


def test_quantise_uint16_rounds_to_the_nearest_step(monkeypatch: pytest.MonkeyPatch) -> None:
    values = np.random.default_rng(0).uniform(0.0, 3.0, (5, 7, 9)).astype(np.float32)
    values[0, 0, :3] = 0.0
    q, scale = quantise_uint16(values)
    assert q.dtype == np.uint16 and q.shape == values.shape
    assert int(q.max()) == QUANTISED_LEVELS and scale == pytest.approx(float(values.max()) / QUANTISED_LEVELS)
    assert np.all(q[0, 0, :3] == 0)  # empty space stays empty
    np.testing.assert_array_equal(q, np.rint(values.astype(np.float64) / scale).astype(np.uint16))
    assert np.abs(q * scale - values).max() <= 0.5 * scale * (1 + 1e-6)
    # chunked: the same values, into the given array; a given step clips above its range
    monkeypatch.setattr(ct, "_QUANTISE_CHUNK_VOXELS", 17)
    out = np.empty(values.shape, np.uint16)
    q2, _ = quantise_uint16(values, scale, out=out)
    assert q2 is out
    np.testing.assert_array_equal(q2, q)
    clipped, _ = quantise_uint16(values, 1e-5)
    assert int(clipped.max()) == QUANTISED_LEVELS
    assert np.all(quantise_uint16(np.zeros((2, 3, 4), np.float32))[0] == 0)
    with pytest.raises(ValueError, match="non-negative"):
        quantise_uint16(-values)


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("skip_empty", [True, False])
def test_quantised_render_equals_the_float32_render(seed: int, skip_empty: bool) -> None:
    """Within half a step per sample (the march is linear in the voxels): below REL_TOL of the
    image's maximum, and below the bound 0.5 · scale · the grid's diagonal."""
    mu, W = _volume(seed)
    K, T = _views(seed)
    ref = CTRenderer.from_tensor(torch.from_numpy(mu), W, skip_empty=skip_empty).render_poses(K, T, 44, 48)
    renderer = CTRenderer.from_tensor(torch.from_numpy(mu), W, skip_empty=skip_empty, quantise=True)
    assert renderer.mu.dtype == torch.uint16 and renderer.scale is not None
    img = renderer.render_poses(K, T, 44, 48)
    assert img.dtype == torch.float32
    err = float((img - ref).abs().max())
    top = float(ref.abs().max())
    assert top > 0.5
    diagonal_mm = float(np.linalg.norm(W[:3, :3] @ np.array(mu.shape[::-1], float)))
    assert err <= REL_TOL * top
    assert err <= 0.5 * renderer.scale * diagonal_mm + 1e-6 * top
    # the volume it integrates: the stored units times the scale, whose float render is the same
    deq = CTRenderer.from_tensor(renderer.mu_values(), W).render_poses(K, T, 44, 48)
    torch.testing.assert_close(img, deq, rtol=1e-5, atol=1e-6 * top)


def test_quantised_backends_mipmaps_and_empty_space_map() -> None:
    mu, W = _volume(3)
    K, T = _views(3, n=2)
    K[1, :2, :2] /= 6.0  # coarse pixels: a mipmapped view
    q, scale = quantise_uint16(mu)
    given = CTRenderer.from_tensor(torch.from_numpy(q), W, scale=scale)
    made = CTRenderer.from_tensor(torch.from_numpy(mu), W, quantise=True)
    assert given.scale == made.scale == scale
    a = given.render_poses(K, T, 44, 48)
    torch.testing.assert_close(a, made.render_poses(K, T, 44, 48), rtol=0, atol=0)
    b = CTRenderer.from_tensor(torch.from_numpy(q), W, scale=scale, backend="torch").render_poses(
        K, T, 44, 48
    )
    assert float((a - b).abs().max()) <= 1e-5 * float(a.abs().max())
    ref = CTRenderer.from_tensor(torch.from_numpy(mu), W).render_poses(K, T, 44, 48)
    assert float((a - ref).abs().max()) <= REL_TOL * float(ref.abs().max())
    # the empty-space map is the stored volume's (a voxel below half a step is empty)
    np.testing.assert_array_equal(given._pyramid.skip((1, 1, 1)), empty_space_distance(q))
    with pytest.raises(ValueError, match="uint16"):
        CTRenderer.from_tensor(torch.from_numpy(mu), W, scale=scale)


def test_quantise_keeps_a_volume_off_the_cpu_as_it_is() -> None:
    """The torch march (CUDA) keeps float32: ``quantise`` applies to CPU volumes only."""
    mu, W = _volume(4)
    meta = torch.from_numpy(mu).to("meta")
    renderer = CTRenderer.from_tensor(meta, W, quantise=True)
    assert renderer.mu.dtype == torch.float32 and renderer.scale is None
    assert CTRenderer.from_tensor(torch.from_numpy(mu), W).scale is None


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_renderer_is_not_quantised() -> None:
    mu, W = _volume(5)
    K, T = _views(5)
    cuda = torch.from_numpy(mu).cuda()
    renderer = CTRenderer.from_tensor(cuda, W, quantise=True)
    assert renderer.mu is cuda or renderer.mu.data_ptr() == cuda.data_ptr()
    img = renderer.render_poses(K, T, 44, 48)
    plain = CTRenderer.from_tensor(cuda, W).render_poses(K, T, 44, 48)
    assert img.dtype == torch.float32
    torch.testing.assert_close(img, plain, rtol=0, atol=0)


def test_compiled_kernels_cover_the_quantised_march() -> None:
    """The uint16 march with its empty-space map is among the signatures compiled at install."""
    ct.compile_kernels()
    before = set(_ct_numba.march_rays.signatures)
    mu, W = _volume(6)
    K, T = _views(6, n=1)
    CTRenderer.from_tensor(torch.from_numpy(mu), W, quantise=True, mipmap=False).render_poses(K, T, 44, 48)
    assert set(_ct_numba.march_rays.signatures) == before
