"""Data set reading, resizing and augmentation keep masks and landmarks consistent (A stays A)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from det_synthetic import write_dataset

from fluoronav.detection.augment import (
    AugmentConfig,
    apply_affine,
    augment_geometric,
    lower_dose,
    view_affine,
)
from fluoronav.detection.dataset import (
    CMDetectionDataset,
    Sample,
    load_sample,
    make_view,
    photons_per_pixel_of,
    read_manifest,
    split_of,
)
from fluoronav.detection.model import DetectorConfig
from fluoronav.detection.views import full_view
from fluoronav.errors import InputError

CFG = DetectorConfig(input_size=64, roi_size=48, channels=(4, 8, 16), roi_channels=(4, 8, 16))


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
        image, mask, lm = make_view(s, view, CFG, rng=np.random.default_rng(seed), augment=aug)
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
    view = full_view(s.image.shape, CFG.input_size)
    # every other augmentation off: the view differs from the plain one only by the added noise
    only_dose = AugmentConfig(
        p_flip=0.0, p_rot90=0.0, max_angle_deg=0.0, gamma=(1.0, 1.0), contrast=(1.0, 1.0),
        brightness=0.0, noise_std=0.0, p_blur=0.0, p_low_dose=1.0, min_dose_fraction=0.05,
    )  # fmt: skip
    plain = make_view(s, view, CFG)[0]
    same = make_view(s, view, CFG, rng=np.random.default_rng(0), augment=only_dose)[0]
    noisy = make_view(s, view, CFG, rng=np.random.default_rng(0), augment=only_dose, photons_per_pixel=100.0)[
        0
    ]
    np.testing.assert_allclose(same, plain, atol=1e-6)  # no photon count: no dose augmentation
    assert np.abs(noisy - plain).mean() > 0.01
    assert photons_per_pixel_of(data_dir) is None
    (tmp_path / "dataset.json").write_text('{"storage": {"photons_per_pixel": 45000.0}}')
    assert photons_per_pixel_of(tmp_path) == 45000.0
