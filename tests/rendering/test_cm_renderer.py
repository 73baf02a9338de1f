"""Analytic CM DRR: closed-form chords, notch visibility, batching, backends, CT-renderer agreement."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.signal import find_peaks

from fluoronav.geometry.camera import Camera
from fluoronav.geometry.transforms import transform_from_params
from fluoronav.manipulator import CMConfig, CMKinematics
from fluoronav.manipulator.geometry import voxelize_cm
from fluoronav.rendering.cm import CMRenderer

CONFIG = CMConfig()
BENT = np.array([5.0, -3.0, 4.0, 6.0, 2.0])
#: CM x → camera z (rays run along CM x), CM y → camera y, CM z → camera −x
R_SIDE = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])


def _pose(R: np.ndarray, point_cm: np.ndarray, depth_mm: float = 450.0) -> np.ndarray:
    """camera_from_cm putting ``point_cm`` on the principal ray at ``depth_mm``."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.array([0.0, 0.0, depth_mm]) - R @ point_cm
    return T


def _K(f: float, rows: int, cols: int) -> np.ndarray:
    return np.array([[f, 0.0, (cols - 1) / 2.0], [0.0, f, (rows - 1) / 2.0], [0.0, 0.0, 1.0]])


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / math.sqrt((a * a).sum() * (b * b).sum()))


def _annulus_chord(d: float, r: float, R: float) -> float:
    d = abs(d)
    if d >= R:
        return 0.0
    inner = math.sqrt(r * r - d * d) if d < r else 0.0
    return 2.0 * (math.sqrt(R * R - d * d) - inner)


def _population(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Oblique poses around the side-on view and random control points."""
    rng = np.random.default_rng(seed)
    T0 = torch.tensor(_pose(R_SIDE, np.array([0.0, 0.0, 15.0])))
    sigma = np.array([0.3, 0.3, 0.3, 3.0, 3.0, 3.0])
    T = T0 @ transform_from_params(torch.tensor(rng.normal(0.0, sigma, (n, 6))))
    cp = torch.tensor(rng.uniform(*CONFIG.control_point_range_deg, size=(n, 5)))
    return T, cp


@pytest.fixture(scope="module")
def renderer() -> CMRenderer:
    return CMRenderer(CONFIG, mu_per_mm=1.7)


def test_principal_ray_chords_match_closed_form(renderer: CMRenderer) -> None:
    """Rays perpendicular to the straight tube at offset d: annulus chord, zero through a notch gap."""
    c = CONFIG
    r, R, cut = c.inner_radius_mm, c.outer_radius_mm, c.notch_cut_level_mm
    z_plain, z_n0, z_n1 = -2.0, c.notch_z_mm(0) + 0.2, c.notch_z_mm(1) - 0.2  # notch 0 opens to +y, 1 to −y
    cases = []
    for d in (0.0, 0.7, -1.9, 2.0 + 1e-3, 2.6, -2.99, 3.1):
        cases.append((z_plain, d, _annulus_chord(d, r, R)))
    for d in (-2.5, -1.8, -1.0, 0.0, 2.5):
        cases.append((z_n0, d, _annulus_chord(d, r, R) if d <= cut else 0.0))
    for d in (2.5, 1.8, -2.5):
        cases.append((z_n1, d, _annulus_chord(d, r, R) if -d <= cut else 0.0))
    T = torch.tensor(np.stack([_pose(R_SIDE, np.array([0.0, d, z])) for z, d, _ in cases]))[:, None]
    K = torch.tensor(_K(2000.0, 5, 5))[None]
    img = renderer.render(T, torch.zeros(len(cases), 5), K, 5, 5)
    got = img[:, 0, 2, 2].double().numpy()
    expected = 1.7 * np.array([e for *_, e in cases])
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)
    assert (expected == 0).sum() >= 4 and (expected > 0).sum() >= 8


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_every_notch_is_visible_side_on(backend: str) -> None:
    """0.2 mm pixels at the CM: the profile along the projected axis dips once per notch."""
    rows, cols = 41, 200
    r = CMRenderer(CONFIG, mu_per_mm=1.0, backend=backend)  # type: ignore[arg-type]
    T = torch.tensor(_pose(R_SIDE, np.array([0.0, 0.0, 15.0])))[None, None]
    K = torch.tensor(_K(450.0 / 0.2, rows, cols))[None]
    profile = r.render(T, torch.zeros(1, 5), K, rows, cols)[0, 0, rows // 2].numpy()
    minima, _ = find_peaks(-profile, prominence=0.5)
    assert len(minima) == CONFIG.n_notches
    # the dips sit on the notch centres (CM z → image −u, pixel 0.2 mm at the CM, centre z = 15)
    z_of_u = 15.0 - (minima - (cols - 1) / 2.0) * 0.2
    np.testing.assert_allclose(np.sort(z_of_u), [CONFIG.notch_z_mm(j) for j in range(27)], atol=0.2)


def test_batched_render_equals_per_candidate(renderer: CMRenderer) -> None:
    rows, cols = 64, 72
    T, cp = _population(4, seed=1)
    T2 = torch.stack(
        [T, T @ transform_from_params(torch.tensor([0.0, 0.4, 0.0, 1.0, 0.0, 0.0], dtype=torch.float64))],
        dim=1,
    )
    K = torch.tensor(np.stack([_K(1200.0, rows, cols), _K(1500.0, rows, cols)]))
    batched = renderer.render(T2, cp, K, rows, cols)
    assert batched.shape == (4, 2, rows, cols) and batched.dtype == torch.float32
    for b in range(4):
        for v in range(2):
            single = renderer.render(T2[b : b + 1, v : v + 1], cp[b : b + 1], K[v : v + 1], rows, cols)
            torch.testing.assert_close(batched[b, v], single[0, 0], rtol=0, atol=1e-6)
    assert (batched.amax(dim=(2, 3)) > 5.0).all()  # every image sees the CM


def test_numba_and_torch_backends_agree_and_roi_is_lossless() -> None:
    rows, cols = 80, 96
    T, cp = _population(5, seed=2)
    T = T[:, None]
    K = torch.tensor(_K(1500.0, rows, cols))[None]
    a = CMRenderer(CONFIG, mu_per_mm=2.0, backend="numba").render(T, cp, K, rows, cols)
    b = CMRenderer(CONFIG, mu_per_mm=2.0, backend="torch", max_tile_elements=50_000).render(
        T, cp, K, rows, cols
    )
    scale = float(a.abs().max())
    assert scale > 5.0
    assert float((a - b).abs().max()) <= 1e-4 * scale
    dense = CMRenderer(CONFIG, mu_per_mm=2.0, backend="numba").render(T, cp, K, rows, cols, roi=False)
    assert float((a - dense).abs().max()) <= 1e-6 * scale


def test_landmarks_and_mask() -> None:
    rows, cols = 41, 200
    r = CMRenderer(CONFIG, mu_per_mm=1.0)
    Tn = _pose(R_SIDE, np.array([0.0, 0.0, 15.0]))
    T, K = torch.tensor(Tn)[None, None], torch.tensor(_K(450.0 / 0.2, rows, cols))[None]
    cp = torch.zeros(1, 5)
    lm = r.landmarks_px(T, cp, K)[0, 0].numpy()
    cam = Camera(rows, cols, _K(450.0 / 0.2, rows, cols), Tn)
    np.testing.assert_allclose(
        lm, cam.project(np.array([[0, 0, 0.0], [0, 0, CONFIG.distal_notch_plane_mm]])), atol=1e-9
    )
    mask = r.mask(T, cp, K, rows, cols)[0, 0].numpy()
    image = r.render(T, cp, K, rows, cols)[0, 0].numpy()
    assert mask.dtype == bool and mask.any()
    assert not (mask & (image <= 0)).any()  # the notched part is part of the CM
    cols_hit = np.nonzero(mask.any(axis=0))[0]
    # along the axis the mask spans A..B (u decreases with CM z here); walls seen obliquely at the
    # ends add at most a pixel of perspective spread
    assert abs(cols_hit.max() - lm[0, 0]) <= 1.5 and abs(cols_hit.min() - lm[1, 0]) <= 1.5


@pytest.mark.parametrize("bent", [False, True], ids=["straight", "bent"])
def test_matches_ct_renderer_on_voxelized_cm(bent: bool) -> None:
    """Oblique view: analytic DRR vs the CT ray marcher through the 0.1 mm voxelised CM.

    Bent, adjacent links overlap at the spine of each joint (the kinematics rotate links about the
    tube axis); the renderer adds both links there while the voxelisation clips at 1, so the
    integrated sum is only compared for the straight CM.
    """
    from fluoronav.rendering.ct import render_line_integrals

    cp = BENT if bent else np.zeros(5)
    rows, cols = 96, 96
    rv = torch.tensor([0.5, 1.1, 0.4, 0.0, 0.0, 0.0], dtype=torch.float64)
    R = transform_from_params(rv)[:3, :3].numpy()
    kin = CMKinematics(CONFIG)
    centre = kin.centerline_cm(torch.tensor(cp), n_points=3, to_z_mm=CONFIG.tip_z_mm)[1].numpy()
    Tn = _pose(R, centre)
    K = _K(450.0 / 0.4, rows, cols)  # 0.4 mm pixels at the CM
    mu = 1.3
    analytic = (
        CMRenderer(CONFIG, mu_per_mm=mu)
        .render(torch.tensor(Tn)[None, None], torch.tensor(cp)[None], torch.tensor(K)[None], rows, cols)[0, 0]
        .numpy()
    )
    vox = voxelize_cm(CONFIG, cp, spacing_mm=0.1, supersample=3)
    ct = render_line_integrals(
        torch.from_numpy(vox.occupancy * mu),
        vox.world_from_index,
        K[None],
        Tn[None],
        rows,
        cols,
        step_mm=0.05,
        mipmap=False,
    )[0].numpy()
    assert (analytic > 0).mean() > 0.05
    assert _ncc(analytic, ct) >= 0.99
    if not bent:
        assert analytic.sum() == pytest.approx(float(ct.sum()), rel=0.01)


@pytest.mark.parametrize("in_plane_deg", [0.0, 30.0, 45.0, 80.0])
def test_row_spans_are_lossless_for_oblique_and_foreshortened_links(in_plane_deg: float) -> None:
    """Each box row evaluated only across the link's projected footprint gives the same image as
    every pixel of the box: the CM turned in the image plane and tilted 20–70° towards the source
    (foreshortened links, whose footprints are far from their axis-aligned boxes)."""
    rows, cols = 120, 128
    a = math.radians(in_plane_deg)
    Rz = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    poses = []
    for tilt in (20.0, 45.0, 70.0):
        t = math.radians(tilt)
        Ry = np.array([[math.cos(t), 0.0, math.sin(t)], [0.0, 1.0, 0.0], [-math.sin(t), 0.0, math.cos(t)]])
        poses.append(_pose(Rz @ Ry @ R_SIDE, np.array([0.0, 0.0, 15.0]), depth_mm=300.0))
    T = torch.tensor(np.stack(poses))[:, None]
    cp = torch.tensor(np.stack([BENT, -BENT, np.zeros(5)]))
    K = torch.tensor(_K(1500.0, rows, cols))[None]
    spans = CMRenderer(CONFIG, mu_per_mm=2.0).render(T, cp, K, rows, cols)
    boxes = CMRenderer(CONFIG, mu_per_mm=2.0, row_spans=False).render(T, cp, K, rows, cols)
    scale = float(boxes.abs().max())
    assert scale > 5.0 and (boxes.amax(dim=(2, 3)) > 1.0).all()
    assert float((spans - boxes).abs().max()) <= 1e-6 * scale
