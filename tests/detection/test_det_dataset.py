"""Data set reading, resizing and augmentation keep masks and landmarks consistent (A stays A)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from det_synthetic import with_settings, write_dataset
from hypothesis import given, settings
from hypothesis import strategies as st

from fluoronav.detection.config import DetectorConfig
from fluoronav.detection.training.augment import (
    AugmentConfig,
    apply_affine,
    augment_geometric,
    collimation_window,
    edge_point,
    lower_dose,
    view_affine,
)
from fluoronav.detection.training.dataset import (
    CMDetectionDataset,
    Sample,
    collimate,
    crop_sample,
    fine_view_for,
    load_sample,
    make_view,
    partial_cm_points,
    photons_per_pixel_of,
    read_manifest,
    split_of,
)
from fluoronav.detection.views import View, full_view
from fluoronav.errors import InputError

CFG = with_settings(
    DetectorConfig(),
    coarse={"network": {"channels": (4, 8, 16)}, "sampler": {"size": 64}},
    fine={"network": {"channels": (4, 8, 16)}, "sampler": {"size": 48}},
)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("det_data"), 12, size=96, seed=5, negative_every=4)


def _near_mask(mask: np.ndarray, uv: np.ndarray, radius: float) -> float:
    """Largest mask value within ``radius`` pixels of ``uv``."""
    vv, uu = np.mgrid[0 : mask.shape[0], 0 : mask.shape[1]]
    near = (uu - uv[0]) ** 2 + (vv - uv[1]) ** 2 <= radius**2
    return float(mask[near].max()) if near.any() else 0.0


def _end_points(mask: np.ndarray) -> np.ndarray:
    """The two mask pixels farthest apart (the ends of a ribbon)."""
    vv, uu = np.nonzero(mask > 0.5)
    pts = np.stack([uu, vv], axis=1).astype(float)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    i, j = np.unravel_index(np.argmax(d), d.shape)
    return pts[[i, j]]


def test_manifest_split_and_negatives(data_dir: Path) -> None:
    recs = read_manifest(data_dir)
    assert len(recs) == 12
    train = CMDetectionDataset(data_dir, config=CFG, split="train", val_fraction=0.3)
    val = CMDetectionDataset(data_dir, config=CFG, split="val", val_fraction=0.3)
    ids_t = {r["id"] for r in train.records}
    ids_v = {r["id"] for r in val.records}
    assert ids_t.isdisjoint(ids_v) and len(ids_t | ids_v) == 12
    assert all(split_of(i, 0.3) == "val" for i in ids_v)
    everything = CMDetectionDataset(data_dir, config=CFG, split="all")
    neg = [i for i in range(12) if everything.sample(i).landmarks_px is None]
    assert neg == [3, 7, 11]
    item = everything[3]
    assert not bool(item["positive"]) and np.isnan(item["fine_landmarks"].numpy()).all()
    assert float(item["coarse_mask"].max()) == 0.0


def test_resized_landmarks_sit_on_the_mask_ends(data_dir: Path) -> None:
    ds = CMDetectionDataset(data_dir, config=CFG, split="all")
    for i in (0, 1, 2):
        item = ds[i]
        for key, scale in (("coarse", 96 / 64), ("fine", float(item["fine_view"][2] / item["fine_view"][3]))):
            mask = item[f"{key}_mask"][0].numpy()
            lm = item[f"{key}_landmarks"].numpy()
            ends = _end_points(mask)
            # each landmark is on the mask and near one end (the ribbon's half width is ≤ 5 input px)
            for k in range(2):
                assert _near_mask(mask, lm[k], 1.0) > 0.3
                assert np.min(np.linalg.norm(ends - lm[k], axis=1)) < 7.0 / scale
        assert item["coarse_image"].shape == (1, 64, 64) and item["fine_image"].shape == (1, 48, 48)


def test_augmented_landmarks_stay_on_their_ends(data_dir: Path) -> None:
    base = load_sample(data_dir, read_manifest(data_dir)[0])
    # mark A with a bright dot in the image, so that A's identity can be checked after the warp
    img = base.image.copy()
    a = np.round(base.landmarks_px[0]).astype(int)
    img[a[1] - 1 : a[1] + 2, a[0] - 1 : a[0] + 2] = 50.0
    s = Sample(base.id, img, base.mask, base.landmarks_px, 0.5)
    view = full_view(img.shape, 96)
    aug = AugmentConfig(noise_std=0.0, p_blur=0.0, gamma=(1.0, 1.0), contrast=(1.0, 1.0), brightness=0.0)
    for seed in range(8):
        image, mask, lm = make_view(s, view, CFG.fine.sampler, rng=np.random.default_rng(seed), augment=aug)
        for k in range(2):
            assert _near_mask(mask, lm[k], 1.5) > 0.5
        # the bright dot (A) is where landmark A went, not B
        v, u = np.unravel_index(np.argmax(image), image.shape)
        assert np.linalg.norm(lm[0] - [u, v]) < 1.5 < np.linalg.norm(lm[1] - [u, v])


def test_rot90_and_flip_are_exact_permutations() -> None:
    rng = np.random.default_rng(0)
    img = rng.random((16, 16)).astype(np.float32)
    mask = (img > 0.5).astype(np.float32)
    lm = np.array([[3.0, 5.0], [12.0, 9.0]])
    out, _, l2 = apply_affine(view_affine(16, flip=False, angle_deg=90.0), img, mask, lm)
    # +90° in image coordinates (v down) maps (u, v) → (15 − v, u)
    np.testing.assert_allclose(out, np.rot90(img, k=-1), atol=1e-5)
    np.testing.assert_allclose(l2, [[15 - 5, 3], [15 - 9, 12]], atol=1e-9)
    out, _, l3 = apply_affine(view_affine(16, flip=True, angle_deg=0.0), img, mask, lm)
    np.testing.assert_allclose(out, img[:, ::-1], atol=1e-6)
    np.testing.assert_allclose(l3, [[12, 5], [3, 9]], atol=1e-9)
    with pytest.raises(ValueError):
        augment_geometric(
            rng, np.zeros((4, 5), np.float32), np.zeros((4, 5), np.float32), None, AugmentConfig()
        )


def test_bad_data_sets_raise_input_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="manifest"):
        read_manifest(tmp_path)
    (tmp_path / "manifest.jsonl").write_text('{"id": "x", "file": "x.npz"}\n')
    with pytest.raises(InputError, match=r"x\.npz"):
        load_sample(tmp_path, read_manifest(tmp_path)[0])


def test_simulate_layout_int_ids_subdir_and_nan_landmarks(tmp_path: Path) -> None:
    # the layout `fluoronav simulate` writes: integer ids, samples/<id>.npz, NaN landmarks without a CM
    import json

    (tmp_path / "samples").mkdir()
    rows = []
    for i, with_cm in enumerate([True, False]):
        mask = np.zeros((64, 64), np.uint8)
        lm = np.full((2, 2), np.nan)
        if with_cm:
            mask[30:34, 10:50] = 1
            lm = np.array([[10.0, 31.5], [49.0, 31.5]])
        np.savez_compressed(
            tmp_path / f"samples/{i:06d}.npz",
            image=np.ones((64, 64), np.float32) + mask,
            mask=mask,
            landmarks_px=lm,
        )
        rows.append(
            {
                "id": i,
                "file": f"samples/{i:06d}.npz",
                "rows": 64,
                "cols": 64,
                "pixel_spacing_mm": 1.164,
                "landmarks_px": lm.tolist() if with_cm else None,
                "has_cm": with_cm,
            }
        )
    (tmp_path / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows) + '{"id": 2, "fi')
    ds = CMDetectionDataset(tmp_path, config=CFG, split="all")
    assert len(ds) == 2  # the truncated last line (a crash while writing) is skipped
    assert ds.sample(0).landmarks_px is not None and ds.sample(0).pixel_spacing_mm == pytest.approx(1.164)
    assert ds.sample(1).landmarks_px is None and bool(ds[0]["positive"]) and not bool(ds[1]["positive"])


@pytest.mark.parametrize("dose_fraction", [0.25, 0.5])
def test_lower_dose_matches_a_poisson_image_taken_at_that_dose(dose_fraction: float) -> None:
    # the reference is physics, not the formula: log images of Poisson counts at N0 and at f·N0
    # (down to ~23 photons at f·N0 where p = 4; the log-normal approximation is for counts ≫ 1)
    rng = np.random.default_rng(11)
    n0 = 5000.0
    p = np.repeat(np.array([0.5, 2.0, 4.0], np.float32), 40_000).reshape(3, -1)  # line integrals

    def log_image(photons: float) -> np.ndarray:
        counts = np.maximum(rng.poisson(photons * np.exp(-p)), 1)
        return -np.log(counts / photons).astype(np.float32)

    lowered = lower_dose(rng, log_image(n0), photons_per_pixel=n0, dose_fraction=dose_fraction)
    direct = log_image(n0 * dose_fraction)
    np.testing.assert_allclose(lowered.std(axis=1), direct.std(axis=1), rtol=0.05)
    np.testing.assert_allclose(lowered.mean(axis=1), direct.mean(axis=1), atol=0.02)
    assert np.array_equal(lower_dose(rng, p, photons_per_pixel=n0, dose_fraction=1.0), p)
    with pytest.raises(ValueError, match="dose_fraction"):
        lower_dose(rng, p, photons_per_pixel=n0, dose_fraction=0.0)


def test_low_dose_augmentation_needs_the_data_sets_photon_count(data_dir: Path, tmp_path: Path) -> None:
    s = load_sample(data_dir, next(r for r in read_manifest(data_dir) if r.get("landmarks_px")))
    view = full_view(s.image.shape, CFG.coarse.sampler.size)
    # every other augmentation off: the view differs from the plain one only by the added noise
    only_dose = AugmentConfig(
        p_flip=0.0, p_rot90=0.0, max_angle_deg=0.0, gamma=(1.0, 1.0), contrast=(1.0, 1.0),
        brightness=0.0, noise_std=0.0, p_blur=0.0, p_low_dose=1.0, min_dose_fraction=0.05,
    )  # fmt: skip
    sampler = CFG.coarse.sampler
    plain = make_view(s, view, sampler)[0]
    same = make_view(s, view, sampler, rng=np.random.default_rng(0), augment=only_dose)[0]
    noisy = make_view(
        s, view, sampler, rng=np.random.default_rng(0), augment=only_dose, photons_per_pixel=100.0
    )[0]
    np.testing.assert_allclose(same, plain, atol=1e-6)  # no photon count: no dose augmentation
    assert np.abs(noisy - plain).mean() > 0.01
    assert photons_per_pixel_of(data_dir) is None
    (tmp_path / "dataset.json").write_text('{"storage": {"photons_per_pixel": 45000.0}}')
    assert photons_per_pixel_of(tmp_path) == 45000.0


@settings(max_examples=200, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    rows=st.integers(40, 300),
    cols=st.integers(40, 300),
    box=st.tuples(*(st.floats(0.0, 1.0),) * 4),
    min_frac=st.floats(0.1, 1.0),
)
def test_collimation_window_keeps_the_cm_inside_the_image(
    seed: int, rows: int, cols: int, box: tuple[float, ...], min_frac: float
) -> None:
    u0, u1 = sorted((box[0] * (cols - 1), box[2] * (cols - 1)))
    v0, v1 = sorted((box[1] * (rows - 1), box[3] * (rows - 1)))
    margin = 4.0
    x0, y0, x1, y1 = collimation_window(
        np.random.default_rng(seed), (rows, cols), (u0, v0, u1, v1), min_field_frac=min_frac, margin_px=margin
    )
    assert 0 <= x0 < x1 <= cols and 0 <= y0 < y1 <= rows
    # the CM's box with its margin (clipped to the image) is inside the window
    assert x0 <= max(u0 - margin, 0.0) and x1 >= min(u1 + margin + 1.0, cols)
    assert y0 <= max(v0 - margin, 0.0) and y1 >= min(v1 + margin + 1.0, rows)
    # no window is smaller than the drawn field or the CM's box needs, whichever is larger
    assert x1 - x0 >= min(round(min_frac * cols), cols - 1) - 1 or x1 - x0 >= u1 - u0 + 1
    assert y1 - y0 >= min(round(min_frac * rows), rows - 1) - 1 or y1 - y0 >= v1 - v0 + 1


def test_collimation_window_without_a_cm_is_a_random_field() -> None:
    rng = np.random.default_rng(3)
    sides = [collimation_window(rng, (100, 200), None, min_field_frac=0.4) for _ in range(200)]
    w = np.array([x1 - x0 for x0, _, x1, _ in sides])
    h = np.array([y1 - y0 for _, y0, _, y1 in sides])
    assert w.min() >= 80 and w.max() <= 200 and h.min() >= 40 and h.max() <= 100
    assert w.std() > 20 and len({(x0, y0) for x0, y0, _, _ in sides}) > 150  # it varies


def test_collimated_sample_keeps_the_whole_cm_and_its_landmarks(data_dir: Path) -> None:
    s = load_sample(data_dir, read_manifest(data_dir)[0])
    shapes = set()
    for seed in range(20):
        c = collimate(s, np.random.default_rng(seed), min_field_frac=0.2)
        shapes.add(c.image.shape)
        assert c.mask.sum() == s.mask.sum() and c.landmarks_px is not None
        # the same pixels under the same landmarks
        off = s.landmarks_px - c.landmarks_px
        x0, y0 = (round(o) for o in off[0])
        np.testing.assert_allclose(off, [[x0, y0], [x0, y0]], atol=1e-9)
        np.testing.assert_array_equal(
            c.image, s.image[y0 : y0 + c.image.shape[0], x0 : x0 + c.image.shape[1]]
        )
    assert len(shapes) > 5
    # a window that misses the CM makes a negative
    uu = np.nonzero(s.mask)[1]
    x_far = int(uu.max()) + 1
    far = crop_sample(s, (x_far, 0, s.image.shape[1], s.image.shape[0]))
    assert far.landmarks_px is None and not far.mask.any()


def test_dataset_items_of_collimated_samples_stay_consistent(data_dir: Path) -> None:
    ds = CMDetectionDataset(data_dir, config=CFG, split="all", augment=AugmentConfig(p_collimate=1.0), seed=2)
    plain = CMDetectionDataset(
        data_dir, config=CFG, split="all", augment=AugmentConfig(p_collimate=0.0), seed=2
    )
    scales = []
    for i in (0, 1, 2):
        item = ds[i]
        mask, lm = item["coarse_mask"][0].numpy(), item["coarse_landmarks"].numpy()
        for k in range(2):
            assert _near_mask(mask, lm[k], 1.5) > 0.3
        scales.append(float(item["coarse_scale"]))
        assert float(plain[i]["coarse_scale"]) == 96 / 64
    assert min(scales) < 96 / 64  # a smaller field: the CM is larger in the coarse view


def _tube(a: tuple[float, float], b: tuple[float, float], shape: tuple[int, int] = (160, 200)) -> np.ndarray:
    """A straight tube mask (radius 4 px) from a to b, (u, v) pixels."""
    vv, uu = np.mgrid[0 : shape[0], 0 : shape[1]]
    p = np.stack([uu, vv], axis=-1).astype(float)
    pa, ab = np.asarray(a, float), np.subtract(b, a)
    t = np.clip((p - pa) @ ab / (ab @ ab), 0.0, 1.0)
    return np.hypot(*(p - pa - t[..., None] * ab).transpose(2, 0, 1)) <= 4.0


def test_partial_cm_points_cover_one_end_and_the_drawn_fraction() -> None:
    a, b = (30.0, 40.0), (150.0, 120.0)
    mask, lm = _tube(a, b), np.array([a, b])
    axis = np.subtract(b, a) / np.hypot(*np.subtract(b, a))
    span = float(np.ptp((np.stack(np.nonzero(mask)[::-1], axis=1) - a) @ axis))
    ends = set()
    for seed in range(40):
        pts = partial_cm_points(mask, lm, np.random.default_rng(seed), frac_range=(0.4, 0.6))
        lo, hi, end = pts
        from_a = bool(np.allclose(end, a))
        assert from_a or np.allclose(end, b)
        ends.add(from_a)
        # the box spans 40-60 % of the tube's length along its axis (+ its width across), from that end
        assert 0.4 * span - 1.0 <= (hi - lo) @ axis <= 0.6 * span + 12.0
        assert np.all(end >= lo - 4.5) and np.all(end <= hi + 4.5)
        far = np.array(b if from_a else a)
        assert not (np.all(far >= lo) and np.all(far <= hi))
    assert ends == {True, False}  # both ends are drawn
    # end-on (A and B within 4 px): along the mask's principal axis, no failure
    blob = _tube((90.0, 80.0), (120.0, 80.0))
    pts = partial_cm_points(blob, np.array([[100.0, 80.0], [101.0, 80.0]]), np.random.default_rng(0))
    assert 5.0 < np.ptp(pts[:2, 0]) < 30.0


def test_partial_roi_leaves_the_far_landmark_out_of_the_fine_view() -> None:
    a, b = (20.0, 80.0), (180.0, 80.0)
    lm = np.array([a, b])
    s = Sample("t", np.zeros((160, 200), np.float32), _tube(a, b), lm, 0.5)
    cfg = DetectorConfig()
    partial = AugmentConfig(p_partial_roi=1.0, partial_frac=(0.4, 0.4))

    def inside(v: View) -> np.ndarray:
        uv = v.from_input(lm)
        return np.all((uv >= 0) & (uv <= v.size), axis=1)

    for seed in range(30):
        part = fine_view_for(s, cfg, np.random.default_rng(seed), augment=partial)
        assert inside(part).sum() == 1  # one end in the view, the other beyond its edge
        assert inside(fine_view_for(s, cfg, np.random.default_rng(seed))).all()  # no partial ROIs: both


def test_edge_point_lies_on_the_strongest_edges() -> None:
    # a bright disk (radius 30 px) on a flat background: its rim is the only edge
    v, u = np.mgrid[0:128, 0:160]
    r = np.hypot(u - 90.0, v - 60.0)
    image = (r < 30.0).astype(np.float32) + np.float32(0.2)
    rng = np.random.default_rng(3)
    pts = np.array([edge_point(image, rng) for _ in range(200)])
    assert np.all(np.abs(np.hypot(pts[:, 0] - 90.0, pts[:, 1] - 60.0) - 30.0) <= 3.0)
    assert len({(int(p[0]), int(p[1])) for p in pts}) > 50  # spread along the rim, not one pixel
    flat = edge_point(np.zeros((8, 8), np.float32), rng)  # no edge at all: any pixel
    assert 0 <= flat[0] < 8 and 0 <= flat[1] < 8


def test_edge_negative_roi_is_centred_on_an_edge_only_when_asked() -> None:
    v, u = np.mgrid[0:200, 0:200]
    image = (np.hypot(u - 140.0, v - 60.0) < 20.0).astype(np.float32)  # one small disk, top right
    s = Sample("n", image, np.zeros_like(image, bool), None, 0.5)
    cfg = DetectorConfig()
    on_edges = AugmentConfig(p_edge_negative_roi=1.0)
    for seed in range(20):
        view = fine_view_for(s, cfg, np.random.default_rng(seed), augment=on_edges)
        centre = np.array([view.x0, view.y0]) + view.side / 2.0 - 0.5
        assert abs(np.hypot(centre[0] - 140.0, centre[1] - 60.0) - 20.0) <= 3.0
    # off (the default): the same draws as before the option existed, a window anywhere
    off = [fine_view_for(s, cfg, np.random.default_rng(seed), augment=AugmentConfig()) for seed in range(20)]
    plain = [fine_view_for(s, cfg, np.random.default_rng(seed)) for seed in range(20)]
    assert [(a.x0, a.y0, a.side) for a in off] == [(b.x0, b.y0, b.side) for b in plain]
