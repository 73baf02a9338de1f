"""CT DRR renderer against analytic chords, a pinhole projection and the float64 Siddon reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fluoronav.anatomy.volume import Volume
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.carm import carm_camera_from_world
from fluoronav.rendering.ct import CTRenderer, mipmap_factors, render_line_integrals
from fluoronav.rendering.reference import siddon_line_integrals

BACKENDS = ["numba", "torch"]


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a.ravel() - a.mean()
    b = b.ravel() - b.mean()
    return float(a @ b / math.sqrt((a @ a) * (b @ b)))


def _partial_volume(inside, world_from_index: np.ndarray, shape_zyx: tuple[int, int, int], ss: int = 4):
    """Occupancy fraction of each voxel cell, by ss³ supersampling of ``inside(x, y, z)`` (world mm)."""
    nz, ny, nx = shape_zyx
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    out = np.zeros(shape_zyx, np.float32)
    offsets = (np.arange(ss) + 0.5) / ss - 0.5
    M, t = world_from_index[:3, :3], world_from_index[:3, 3]
    for a in offsets:
        for b in offsets:
            for c in offsets:
                p = np.stack([i + a, j + b, k + c], axis=-1) @ M.T + t
                out += inside(p[..., 0], p[..., 1], p[..., 2])
    return out / ss**3


def _rays(K: np.ndarray, T: np.ndarray, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Source (3,) and unit ray directions (rows, cols, 3) in world."""
    v, u = np.mgrid[0:rows, 0:cols].astype(np.float64)
    d = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T @ T[:3, :3]
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return -T[:3, :3].T @ T[:3, 3], d


def _K(f: float, rows: int, cols: int, cx: float | None = None, cy: float | None = None) -> np.ndarray:
    cx = (cols - 1) / 2 if cx is None else cx
    cy = (rows - 1) / 2 if cy is None else cy
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def _rel_errors(img: np.ndarray, ref: np.ndarray) -> np.ndarray:
    m = ref > 0.1 * ref.max()
    return np.abs(img[m] - ref[m]) / ref[m]


@pytest.fixture(scope="module")
def sphere():
    """Unit-μ sphere of radius 30 mm centred at (5, -3, 2) mm, 1 mm voxels, partial volume."""
    r, centre = 30.0, np.array([5.0, -3.0, 2.0])
    n = 68
    W = np.eye(4)
    W[:3, 3] = centre - (n - 1) / 2 + np.array([0.3, -0.2, 0.1])  # sphere off the voxel grid's centre
    occ = _partial_volume(
        lambda x, y, z: ((x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2) <= r * r,
        W,
        (n, n, n),
    )
    return occ, W, r, centre


@pytest.mark.parametrize("backend", BACKENDS)
def test_sphere_matches_analytic_chords(sphere, backend: str) -> None:
    occ, W, r, centre = sphere
    rows, cols = 60, 72
    K = _K(900.0, rows, cols, cx=38.0, cy=27.5)
    T = carm_camera_from_world(
        lao_rao_deg=25.0,
        cran_caud_deg=78.0,
        source_to_isocenter_mm=500.0,
        isocenter_world=centre + np.array([2.0, 1.0, -1.0]),
    )
    img = render_line_integrals(torch.from_numpy(occ), W, K, T, rows, cols, backend=backend)[0].numpy()
    s, d = _rays(K, T, rows, cols)
    proj = (centre - s) @ d.reshape(-1, 3).T
    b2 = np.sum((centre - s) ** 2) - proj**2
    chord = 2.0 * np.sqrt(np.maximum(r * r - b2, 0.0)).reshape(rows, cols)
    rel = _rel_errors(img, chord)
    assert np.median(rel) < 0.01, np.median(rel)
    assert _ncc(img, chord) > 0.999
    assert np.all(img[chord == 0] < 0.05 * chord.max())  # only the partial-volume rim outside


@pytest.mark.parametrize("backend", BACKENDS)
def test_box_with_anisotropic_spacing_matches_analytic_chords(backend: str) -> None:
    lo, hi = np.array([-25.3, -18.1, -12.6]), np.array([24.7, 17.6, 13.2])
    spacing = (1.0, 0.8, 1.5)
    shape = (24, 52, 58)
    W = np.diag([*spacing, 1.0])
    W[:3, 3] = -(np.array(shape[::-1]) - 1) / 2 * spacing
    occ = _partial_volume(
        lambda x, y, z: (
            (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]) & (z >= lo[2]) & (z <= hi[2])
        ),
        W,
        shape,
    )
    rows, cols = 50, 64
    K = _K(1100.0, rows, cols)
    T = carm_camera_from_world(lao_rao_deg=40.0, cran_caud_deg=70.0, source_to_isocenter_mm=450.0)
    img = render_line_integrals(torch.from_numpy(occ), W, K, T, rows, cols, backend=backend)[0].numpy()
    s, d = _rays(K, T, rows, cols)
    with np.errstate(divide="ignore", invalid="ignore"):
        ta, tb = (lo - s) / d, (hi - s) / d
    t0 = np.minimum(ta, tb).max(axis=-1)
    t1 = np.maximum(ta, tb).min(axis=-1)
    chord = np.maximum(t1 - t0, 0.0)
    rel = _rel_errors(img, chord)
    assert np.median(rel) < 0.01, np.median(rel)
    assert _ncc(img, chord) > 0.999


def test_single_voxel_lands_at_pinhole_pixel() -> None:
    shape = (21, 19, 23)
    mu = np.zeros(shape, np.float32)
    ijk = np.array([13, 7, 9])
    mu[ijk[2], ijk[1], ijk[0]] = 1.0
    W = np.diag([1.0, 1.2, 0.9, 1.0])
    W[:3, 3] = [-11.0, -8.0, -9.5]
    rows, cols = 61, 71
    K = _K(2400.0, rows, cols, cx=33.2, cy=31.7)  # ~10 px per mm at 240 mm: the voxel spans pixels
    T = carm_camera_from_world(lao_rao_deg=10.0, cran_caud_deg=95.0, source_to_isocenter_mm=240.0)
    cam = Camera(rows, cols, K, T)
    predicted = cam.project((W @ np.append(ijk, 1.0))[:3])
    assert 5 < predicted[0] < cols - 5 and 5 < predicted[1] < rows - 5
    for backend in BACKENDS:
        img = render_line_integrals(torch.from_numpy(mu), W, K, T, rows, cols, backend=backend, step_mm=0.05)[
            0
        ].numpy()
        v, u = np.unravel_index(np.argmax(img), img.shape)
        assert abs(u - predicted[0]) <= 0.5 + 1e-9 and abs(v - predicted[1]) <= 0.5 + 1e-9
        vv, uu = np.mgrid[0:rows, 0:cols]
        centroid = np.array([(img * uu).sum(), (img * vv).sum()]) / img.sum()
        np.testing.assert_allclose(centroid, predicted, atol=0.1)


def _rotated_ct(seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random CT-like μ volume with 30° oblique direction cosines and anisotropic spacing."""
    from scipy.ndimage import gaussian_filter
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    shape = (30, 40, 36)
    axis = np.array([1.0, 2.0, -0.7])
    R = Rotation.from_rotvec(math.radians(30.0) * axis / np.linalg.norm(axis)).as_matrix()
    W = np.eye(4)
    W[:3, :3] = R @ np.diag([1.1, 0.9, 1.6])
    W[:3, 3] = [-20.0, -15.0, -22.0]
    base = gaussian_filter(rng.random(shape), 2.0)
    k, j, i = np.meshgrid(*(np.linspace(-1, 1, n) for n in shape), indexing="ij")
    body = ((i / 0.9) ** 2 + (j / 0.8) ** 2 + (k / 0.95) ** 2 < 1.0).astype(np.float64)
    mu = 0.02 * gaussian_filter(body, 1.0) * (0.5 + base / base.max())
    return mu.astype(np.float32), W


@pytest.mark.parametrize("backend", BACKENDS)
def test_rotated_direction_cosines_match_siddon_reference(backend: str) -> None:
    mu, W = _rotated_ct()
    rows, cols = 36, 44
    K = np.array([[260.0, 0.0, 23.4], [0.0, 275.0, 16.1], [0.0, 0.0, 1.0]])
    centre = (W @ np.array([17.5, 19.5, 14.5, 1.0]))[:3]
    T = carm_camera_from_world(
        lao_rao_deg=-35.0, cran_caud_deg=82.0, source_to_isocenter_mm=420.0, isocenter_world=centre
    )
    img = render_line_integrals(torch.from_numpy(mu), W, K, T, rows, cols, backend=backend)[0].numpy()
    ref = siddon_line_integrals(mu, W, K, T, rows, cols)
    assert ref.max() > 0 and (ref == 0).any()  # the volume sits inside the image with background
    assert _ncc(img, ref) >= 0.995
    assert np.median(_rel_errors(img, ref)) <= 0.01


def test_siddon_reference_exact_for_axis_aligned_ray() -> None:
    mu = np.arange(2 * 3 * 4, dtype=np.float64).reshape(2, 3, 4)
    W = np.diag([2.0, 1.0, 3.0, 1.0])
    # a camera on the -x side looking along +x through voxel row (j=1, k=1)
    T = np.eye(4)
    T[:3, :3] = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # cam z = world x
    source = np.array([-50.0, 1.0, 3.0])
    T[:3, 3] = -T[:3, :3] @ source
    ref = siddon_line_integrals(mu, W, _K(100.0, 1, 1), T, 1, 1)
    assert ref[0, 0] == pytest.approx(mu[1, 1, :].sum() * 2.0, rel=1e-12)


def test_backends_agree_multi_camera() -> None:
    mu, W = _rotated_ct(seed=5)
    rows, cols = 30, 34
    K = np.stack([_K(650.0, rows, cols), _K(800.0, rows, cols, cx=12.0, cy=20.0)])
    T = np.stack(
        [
            carm_camera_from_world(lao_rao_deg=a, cran_caud_deg=b, source_to_isocenter_mm=400.0)
            for a, b in ((15.0, 85.0), (120.0, 100.0))
        ]
    )
    a = render_line_integrals(torch.from_numpy(mu), W, K, T, rows, cols, backend="numba")
    b = render_line_integrals(torch.from_numpy(mu), W, K, T, rows, cols, backend="torch")
    assert a.shape == (2, rows, cols) and a.dtype == torch.float32
    assert float((a - b).abs().max()) <= 1e-4 * float(b.abs().max())
    a64 = render_line_integrals(torch.from_numpy(mu.astype(np.float64)), W, K, T, rows, cols, backend="numba")
    assert a64.dtype == torch.float64
    assert float((a64 - b.double()).abs().max()) <= 1e-4 * float(b.abs().max())
    # one call with two cameras equals two calls with one
    single = render_line_integrals(torch.from_numpy(mu), W, K[1], T[1], rows, cols, backend="numba")
    torch.testing.assert_close(single[0], a[1])


def test_roi_crop_equals_crop_of_full_render() -> None:
    mu, W = _rotated_ct()
    vol = Volume(mu, spacing_mm=(1.0, 1.0, 1.0))
    vol = vol.replace(
        direction=W[:3, :3] / np.linalg.norm(W[:3, :3], axis=0),
        spacing_mm=tuple(np.linalg.norm(W[:3, :3], axis=0)),
        origin_mm=tuple(W[:3, 3]),
    )
    renderer = CTRenderer(vol, device="cpu")
    T = carm_camera_from_world(
        lao_rao_deg=50.0, cran_caud_deg=88.0, source_to_isocenter_mm=380.0, isocenter_world=vol.center_world
    )
    full_cam = Camera(64, 60, _K(640.0, 64, 60), T)
    full = renderer.render([full_cam])[0]
    roi = full_cam.crop(row0=11, col0=17, rows=20, cols=25)
    torch.testing.assert_close(renderer.render([roi])[0], full[11:31, 17:42], rtol=1e-5, atol=1e-6)
    # a crop reaching past the image edge still equals the overlapping part
    edge = full_cam.crop(row0=-4, col0=50, rows=10, cols=14)
    torch.testing.assert_close(renderer.render([edge])[0][4:, :10], full[:6, 50:], rtol=1e-5, atol=1e-6)


def test_empty_rays_give_zero() -> None:
    mu = np.ones((10, 12, 14), np.float32)
    W = np.eye(4)
    rows, cols = 16, 16
    K = _K(400.0, rows, cols)
    away = carm_camera_from_world(
        lao_rao_deg=0.0, cran_caud_deg=90.0, source_to_isocenter_mm=300.0, isocenter_world=(0.0, -600.0, 0.0)
    )  # volume behind the source
    # the volume's support (x < 14 mm) fills only the right part of this view (+u is world -x)
    side = carm_camera_from_world(
        lao_rao_deg=0.0, cran_caud_deg=90.0, source_to_isocenter_mm=300.0, isocenter_world=(16.0, 6.0, 5.0)
    )
    for backend in BACKENDS:
        img = render_line_integrals(
            torch.from_numpy(mu), W, K, np.stack([away, side]), rows, cols, backend=backend
        ).numpy()
        assert np.all(img[0] == 0.0)
        u_edge = Camera(rows, cols, K, side).project(np.array([[14.0, -1.0, 5.0], [14.0, 12.0, 5.0]]))[:, 0]
        assert 3 < u_edge.min() < cols - 3
        assert np.all(img[1][:, np.arange(cols) < u_edge.min()] == 0.0)
        assert img[1][6:10, np.arange(cols) > u_edge.max() + 1].min() > 5.0  # ~12 mm of μ = 1


def test_mipmap_levels_and_integral_preservation() -> None:
    mu, W = _rotated_ct()
    rows, cols = 24, 24
    K = _K(120.0, rows, cols)  # coarse pixels: ~3 mm footprint at 400 mm
    centre = (W @ np.array([17.5, 19.5, 14.5, 1.0]))[:3]
    T = carm_camera_from_world(
        lao_rao_deg=20.0, cran_caud_deg=90.0, source_to_isocenter_mm=400.0, isocenter_world=centre
    )
    assert mipmap_factors(W, mu.shape, K, T) == (2, 2, 1)  # spacing 1.1, 0.9, 1.6 mm
    near = _K(2000.0, rows, cols)
    assert mipmap_factors(W, mu.shape, near, T) == (1, 1, 1)
    coarse = render_line_integrals(torch.from_numpy(mu), W, K, T, rows, cols, mipmap=True)[0].numpy()
    fine = render_line_integrals(torch.from_numpy(mu), W, K, T, rows, cols, mipmap=False)[0].numpy()
    assert not np.allclose(coarse, fine)  # a different grid was sampled
    assert np.median(_rel_errors(coarse, fine)) < 0.01
    assert _ncc(coarse, fine) > 0.995


def test_renderer_from_hu_and_size_check() -> None:
    hu = np.full((6, 7, 8), -1000.0, np.float32)
    hu[2:4, 3:5, 3:6] = 0.0  # water
    vol = Volume(hu, spacing_mm=(1.0, 1.0, 1.0), origin_mm=(-3.5, -3.0, -2.5))
    renderer = CTRenderer.from_hu(vol, mu_water_per_mm=0.02, device="cpu")
    T = carm_camera_from_world(lao_rao_deg=0.0, cran_caud_deg=90.0, source_to_isocenter_mm=200.0)
    cam = Camera(9, 9, _K(300.0, 9, 9), T)
    img = renderer.render_one(cam)
    # the central ray crosses 2 mm of water along world y (posterior → anterior) exactly
    assert float(img[4, 4]) == pytest.approx(0.02 * 2.0, rel=1e-4)
    assert float(img[0, 0]) == 0.0
    with pytest.raises(ValueError, match="share rows and cols"):
        renderer.render([cam, Camera(8, 9, _K(300.0, 8, 9), T)])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_renderer_matches_cpu() -> None:
    mu, W = _rotated_ct()
    spacing = np.linalg.norm(W[:3, :3], axis=0)
    vol = Volume(mu, spacing_mm=tuple(spacing), origin_mm=tuple(W[:3, 3]), direction=W[:3, :3] / spacing)
    T = carm_camera_from_world(
        lao_rao_deg=70.0, cran_caud_deg=85.0, source_to_isocenter_mm=400.0, isocenter_world=vol.center_world
    )
    cams = [Camera(40, 36, _K(300.0, 40, 36), T), Camera(40, 36, _K(90.0, 40, 36), T)]  # 2nd is mipmapped
    gpu = CTRenderer(vol, device="cuda").render(cams)
    assert gpu.device.type == "cuda"
    cpu = CTRenderer(vol, device="cpu").render(cams)
    assert float((gpu.cpu() - cpu).abs().max()) <= 1e-4 * float(cpu.abs().max())


@pytest.mark.parametrize("backend", BACKENDS)
def test_uniform_grid_integrates_to_its_extent(backend: str) -> None:
    # trilinear with zero outside: the ramps over the outermost half voxels sum to exactly n·spacing
    vol = Volume(np.ones((6, 7, 9), np.float32), spacing_mm=(1.5, 0.5, 2.0), origin_mm=(3.0, -2.0, 1.0))
    renderer = CTRenderer(vol, device="cpu", backend=backend)
    for lao, expected in ((0.0, 7 * 0.5), (90.0, 9 * 1.5)):  # AP ray along y, lateral ray along x
        T = carm_camera_from_world(
            lao_rao_deg=lao,
            cran_caud_deg=90.0,
            source_to_isocenter_mm=300.0,
            isocenter_world=vol.center_world,
        )
        img = renderer.render_one(Camera(5, 5, _K(500.0, 5, 5), T))
        assert float(img[2, 2]) == pytest.approx(expected, rel=1e-5)


def test_mipmap_downsampling_preserves_mass_and_centroid() -> None:
    from fluoronav.rendering.ct import _downsample

    rng = np.random.default_rng(0)
    mu = rng.random((7, 10, 13)).astype(np.float32)  # odd sizes: padded with the zero outside
    W = np.eye(4)
    W[:3, :3] = np.diag([0.7, 0.9, 2.0])
    W[:3, 3] = [4.0, -3.0, 1.0]
    small, W_small = _downsample(torch.from_numpy(mu), W, (2, 2, 1))
    assert tuple(small.shape) == (7, 5, 7)

    def mass_and_centroid(v: np.ndarray, w: np.ndarray) -> tuple[float, np.ndarray]:
        k, j, i = np.meshgrid(*(np.arange(n) for n in v.shape), indexing="ij")
        p = np.stack([i, j, k, np.ones_like(i)], axis=-1).reshape(-1, 4) @ w.T
        voxel = abs(np.linalg.det(w[:3, :3]))
        return float(v.sum() * voxel), (v.reshape(-1, 1) * p[:, :3]).sum(0) / v.sum()

    m0, _ = mass_and_centroid(mu.astype(np.float64), W)
    m1, _ = mass_and_centroid(small.numpy().astype(np.float64), W_small)
    assert m1 == pytest.approx(m0, rel=1e-6)
    # constant over each 2×2×1 block, the centroid is kept too (checks the index offset of W_small)
    blocks = np.repeat(np.repeat(rng.random((7, 5, 6)), 2, axis=1), 2, axis=2).astype(np.float32)
    small, W_small = _downsample(torch.from_numpy(blocks), W, (2, 2, 1))
    _, c0 = mass_and_centroid(blocks.astype(np.float64), W)
    _, c1 = mass_and_centroid(small.numpy().astype(np.float64), W_small)
    np.testing.assert_allclose(c1, c0, atol=1e-6)


def _sparse_volume(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A mostly empty volume: a few small blobs and a thin shell, rotated anisotropic grid."""
    rng = np.random.default_rng(seed)
    nz, ny, nx = 41, 37, 45
    k, j, i = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    mu = np.zeros((nz, ny, nx), np.float32)
    for _ in range(5):
        c = rng.uniform([3, 3, 3], [nx - 4, ny - 4, nz - 4])
        r = rng.uniform(1.0, 4.0)
        mu[(i - c[0]) ** 2 + (j - c[1]) ** 2 + (k - c[2]) ** 2 <= r * r] = rng.uniform(0.5, 2.0)
    d = np.sqrt((i - nx / 2) ** 2 + (j - ny / 2) ** 2 + (k - nz / 2) ** 2)
    mu[np.abs(d - 15.0) < 0.8] = 0.3
    mu[0, 0, 0] = 1.0  # a corner voxel: face samples next to non-zero data
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    W = np.eye(4)
    W[:3, :3] = R @ np.diag([0.9, 1.1, 1.3])
    W[:3, 3] = -W[:3, :3] @ np.array([nx / 2, ny / 2, nz / 2])
    return mu, W


def test_empty_space_distance_matches_brute_force() -> None:
    from fluoronav.rendering._ct_numba import empty_space_distance

    rng = np.random.default_rng(0)
    vol = np.where(rng.random((9, 10, 11)) < 0.02, 1.0, 0.0).astype(np.float32)
    vol[4, 5, 5] = 2.0
    d = empty_space_distance(vol)
    nz = np.argwhere(vol != 0)
    for idx in np.ndindex(vol.shape):
        assert d[idx] == np.abs(nz - np.array(idx)).max(axis=1).min()
    assert np.all(empty_space_distance(np.zeros((3, 4, 5), np.float32)) == 255)


@pytest.mark.parametrize(
    ("shape", "fraction"), [((40, 31, 57), 1e-3), ((300, 3, 2), 1e-3), ((64, 64, 64), 1e-5), ((2, 2, 2), 0.2)]
)
def test_empty_space_distance_equals_scipys_chessboard_transform(
    shape: tuple[int, ...], fraction: float
) -> None:
    """The in-place uint8 passes give scipy's chessboard distance clipped at 255, on volumes where
    distances pass 255 and on thin ones whose voxels are all on a face."""
    from scipy import ndimage

    from fluoronav.rendering._ct_numba import empty_space_distance

    vol = (np.random.default_rng(1).random(shape) < fraction).astype(np.float32)
    vol.flat[0] = 1.0  # never all empty
    expected = np.minimum(ndimage.distance_transform_cdt(vol == 0, metric="chessboard"), 255)
    assert np.array_equal(empty_space_distance(vol), expected.astype(np.uint8))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_empty_space_skipping_gives_the_same_integrals(seed: int) -> None:
    """Skipping leaves out only samples whose eight corners are zero: the same sums."""
    mu, W = _sparse_volume(seed)
    rows, cols = 48, 52
    rng = np.random.default_rng(seed)
    T = np.stack(
        [
            carm_camera_from_world(
                lao_rao_deg=float(a), cran_caud_deg=float(b), source_to_isocenter_mm=float(s)
            )
            for a, b, s in zip(
                rng.uniform(-180, 180, 4), rng.uniform(0, 180, 4), rng.uniform(60, 400, 4), strict=True
            )
        ]
    )
    K = _K(500.0, rows, cols)
    for dtype in (torch.float32, torch.float64):
        m = torch.from_numpy(mu).to(dtype)
        plain = CTRenderer.from_tensor(m, W, skip_empty=False).render_poses(K, T, rows, cols)
        skip = CTRenderer.from_tensor(m, W, skip_empty=True).render_poses(K, T, rows, cols)
        assert float(plain.abs().max()) > 1.0
        tol = 1e-6 if dtype == torch.float32 else 1e-12
        assert float((plain - skip).abs().max()) <= tol * float(plain.abs().max())
        # and both equal the function API, which does not skip
        ref = render_line_integrals(m, W, K, T, rows, cols)
        torch.testing.assert_close(skip, ref)
