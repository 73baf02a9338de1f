"""Strip stage: strips along paths, A's column and its probabilities, the V's apex, training, and the
detector's move of A to the apex."""

from __future__ import annotations

import dataclasses
import itertools
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from det_synthetic import first_tiny_model

import fluoronav.detection.detector as detector_module
from fluoronav.detection.dataset import StripDataset
from fluoronav.detection.detector import Detector
from fluoronav.detection.model import DetectorConfig, DetectorNet
from fluoronav.detection.strip import (
    StripJitter,
    a_column,
    path_strips,
    resample_path,
    strip_log_probs,
    strip_targets,
    training_path,
    v_apex,
    window_probability,
)
from fluoronav.detection.train import sidecar_path, train

TINY = DetectorConfig(input_size=32, roi_size=32, channels=(4, 8, 16), roi_channels=(4, 8, 16))


def _dot(u: float, v: float, shape: tuple[int, int] = (120, 160)) -> np.ndarray:
    vv, uu = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    return np.exp(-0.5 * ((uu - u) ** 2 + (vv - v) ** 2) / 1.5**2).astype(np.float32)


@pytest.mark.parametrize(
    ("path", "col"),
    [
        (((30.0, 40.0), (90.0, 40.0)), 40),  # along +u: the dot (50, 40) 20 px on, 0.5 px per column
        (((50.0, 10.0), (50.0, 100.0)), 60),  # along +v: 30 px on
        (((30.0, 40.0), (50.0, 40.0), (50.0, 100.0)), 40),  # past a corner: arc length, not distance
    ],
)
def test_a_strip_samples_the_image_along_the_path_by_arc_length(path: tuple, col: int) -> None:
    strips, valid = path_strips(_dot(50.0, 40.0), [np.array(path)], step_px=0.5, shape=(16, 128), smooth_px=0)
    length = float(np.linalg.norm(np.diff(np.array(path), axis=0), axis=1).sum())
    assert valid[0].sum() == min(int(length / 0.5) + 1, 128) and valid[0, : valid[0].sum()].all()
    r, c = np.unravel_index(np.argmax(strips[0]), strips[0].shape)
    assert c == col and r in (7, 8)  # the path's own row: (rows − 1)/2 = 7.5
    on = strips[0][:, valid[0]]
    assert abs(float(on.mean())) < 1e-5 and float(on.std()) == pytest.approx(1.0, abs=1e-3)
    assert (strips[0][:, ~valid[0]] == 0).all()


def test_a_path_without_length_gives_an_empty_strip() -> None:
    point = np.array([[5.0, 5.0], [5.0, 5.0]])
    strips, valid = path_strips(_dot(50, 40), [point], step_px=0.5, shape=(8, 32))
    assert not valid.any() and (strips == 0).all()
    assert len(resample_path(np.array([[0.0, 0.0], [10.0, 0.0]]), 1.0, 4)) == 4


def test_strip_probabilities_sum_to_one_over_the_path_and_none() -> None:
    torch.manual_seed(0)
    logits = torch.randn(3, 2, 8, 32)
    valid = torch.zeros(3, 32, dtype=torch.bool)
    valid[0, :32], valid[1, :10], valid[2, :1] = True, True, True
    p = strip_log_probs(logits, valid).exp()
    torch.testing.assert_close(p.sum(dim=1), torch.ones(3))
    assert float(p[1, 10:32].max()) < 1e-30  # off the path: nothing
    # the "none" logit is the mean of the second channel over the path's columns only
    big = logits.clone()
    big[1, 1, :, 10:] = 1e3
    torch.testing.assert_close(strip_log_probs(big, valid)[1], strip_log_probs(logits, valid)[1])


def test_strip_targets_peak_at_a_or_say_none() -> None:
    valid = torch.ones(2, 40, dtype=torch.bool)
    t = strip_targets(valid, torch.tensor([12.0, -1.0]), sigma_px=2.0)
    assert int(t[0].argmax()) == 12 and float(t[0, -1]) == 0.0
    torch.testing.assert_close(t.sum(dim=1), torch.ones(2))
    assert float(t[1, -1]) == 1.0
    # σ: the neighbours 2 columns off weigh e^(−1/2) of the peak
    assert float(t[0, 14] / t[0, 12]) == pytest.approx(np.exp(-0.5), rel=1e-5)


def test_window_probability_sums_the_columns_around_a_place() -> None:
    p = np.zeros(21)
    p[[0, 3, 10, 19]] = [0.1, 0.2, 0.3, 0.4]  # the last entry (20) is "none"
    assert window_probability(p, 0.0, 3) == pytest.approx(0.3)
    assert window_probability(p, 9.6, 2) == pytest.approx(0.3)
    assert window_probability(p, 19.0, 5) == pytest.approx(0.4)  # "none" is never in a window


def _thick_polyline(
    points: list[tuple[float, float]], half_width: float, shape: tuple[int, int]
) -> np.ndarray:
    vv, uu = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    mask = np.zeros(shape, bool)
    for p, q in itertools.pairwise(points):
        p_, q_ = np.array(p), np.array(q)
        d = q_ - p_
        t = np.clip(((uu - p_[0]) * d[0] + (vv - p_[1]) * d[1]) / (d @ d), 0.0, 1.0)
        mask |= np.hypot(uu - p_[0] - t * d[0], vv - p_[1] - t * d[1]) <= half_width
    return mask


def test_the_apex_of_a_v_mask_lies_on_the_tubes_axis_at_the_corner() -> None:
    stub_end, corner, b = (20.0, 80.0), (60.0, 20.0), (130.0, 80.0)
    mask = _thick_polyline([stub_end, corner, b], 4.0, (100, 160))
    apex, offset = v_apex(mask, np.array(stub_end), np.array(b))  # type: ignore[misc]
    # the farthest pixel is the corner's outer edge, 60 + 4 px from the segment; moved in by ~4 px
    assert offset == pytest.approx(64.0, abs=1.0)
    assert float(np.linalg.norm(apex - np.array(corner))) <= 1.5
    # a straight tube: the farthest pixel is its half-width off the axis
    straight = _thick_polyline([(20.0, 50.0), (130.0, 50.0)], 4.0, (100, 160))
    _, off = v_apex(straight, np.array([20.0, 50.0]), np.array([130.0, 50.0]))  # type: ignore[misc]
    assert off <= 4.0
    assert v_apex(np.zeros((10, 10), bool), np.zeros(2), np.ones(2)) is None


def test_training_paths_through_a_are_labelled_where_they_pass_it() -> None:
    rng = np.random.default_rng(3)
    line = np.stack([np.linspace(100.0, 180.0, 81), np.full(81, 60.0)], axis=1)  # A (100, 60) → B
    shaft_dir = np.array([-0.6, 0.8])  # the shaft leaves A at an angle: a V
    step, mm = 0.5, 2.0  # px per column, px per mm
    kinds: dict[str, list[int]] = {"true": [], "legs": [], "wrong": [], "bend": []}
    for _ in range(400):
        path, kind = training_path(
            line, rng, px_per_mm=mm, shaft_inside_px=60.0, shaft_direction=shaft_dir, jitter=StripJitter()
        )
        kinds[kind].append(a_column(path, line[0], step_px=step, cols=512, tol_px=1.5 * mm))
        if kind == "true":  # it starts on the shaft (within its 60 px inside the image), ends at B
            s = path[0] - line[0]
            assert float(np.linalg.norm(s)) <= 60.0 + 1.5 and float(s @ shaft_dir) >= -1.5
            np.testing.assert_allclose(path[-1], line[-1])
    assert all(len(v) > 50 for v in kinds.values())
    assert all(c >= 0 for c in kinds["true"])  # the true path passes A
    assert np.mean(np.array(kinds["legs"]) >= 0) > 0.95  # legs through A, jittered by 0.4 mm
    assert np.mean(np.array(kinds["bend"]) >= 0) > 0.9 and np.median(kinds["bend"]) <= 2  # from A
    assert np.mean(np.array(kinds["wrong"]) >= 0) < 0.7  # wrong corners mostly miss A
    # without a shaft every path starts at (or next to) A
    path, _ = training_path(
        line, rng, px_per_mm=mm, shaft_inside_px=0.0, shaft_direction=None, jitter=StripJitter()
    )
    assert float(np.linalg.norm(path[0] - line[0])) <= 4.0 * mm


def test_settings_are_validated_and_the_stage_is_off_by_default() -> None:
    cfg = DetectorConfig()
    assert cfg.strip_channels == () and cfg.apex_max_confidence == 0.0
    assert DetectorNet(cfg).strip is None
    with pytest.raises(ValueError, match="strip_shape"):
        dataclasses.replace(TINY, strip_channels=(4, 8, 16), strip_shape=(62, 100))
    with pytest.raises(ValueError, match="apex_max_confidence"):
        dataclasses.replace(TINY, apex_max_confidence=1.5)
    with pytest.raises(ValueError, match="apex_window_mm"):
        dataclasses.replace(TINY, apex_window_mm=0.0)
    c = dataclasses.replace(TINY, strip_channels=(4, 8), strip_shape=(16, 64), apex_max_confidence=0.5)
    assert DetectorConfig.from_dict(json.loads(json.dumps(c.to_dict()))) == c


def test_training_the_strip_stage_adds_it_and_leaves_the_others(tmp_path: Path) -> None:
    data, cfg, first, w0 = first_tiny_model(tmp_path, TINY)
    out = tmp_path / "strip.pt"
    m = train(data, out, config=dataclasses.replace(cfg, stages=("strip",)), init=first, progress=False)
    assert np.isfinite(m["val_loss"]) and 0.0 <= m["val_a_missed"] <= 1.0
    det = Detector.load(out, device="cpu")
    assert det.net.strip is not None and det.config.strip_channels == (16, 32, 64, 128)
    w1 = torch.load(out, weights_only=True)["state_dict"]
    assert all(torch.equal(w0[k], w1[k]) for k in w0) and any(k.startswith("strip.") for k in w1)
    assert json.loads(sidecar_path(out).read_text())["train"]["augmentation"]["near_a_prob"] == 0.3
    # items: two strips per positive, none on negatives; A's column on most of them
    ds = StripDataset(data, config=det.config, split="all", repeats=1, seed=0)
    items = [ds[i] for i in range(len(ds))]
    ok = np.stack([it["strip_ok"].numpy() for it in items])
    assert (ok == 1).all(axis=1).any() and (ok == 0).all(axis=1).any()
    a = np.concatenate([it["strip_a"].numpy()[it["strip_ok"].numpy() > 0] for it in items])
    assert np.mean(a >= 0) > 0.5
    # the detector reads paths with it: probabilities over each path's columns and "none"
    p = det.strip_probabilities(np.zeros((64, 64), np.float32), [np.array([[5.0, 5.0], [50.0, 40.0]])])
    assert p.shape == (1, 385) and p.sum() == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize(
    ("confidence", "p_start", "p_apex_start", "p_apex", "moves"),
    [
        (0.5, 0.1, 0.1, 0.8, True),  # unsure A; both paths say "not A at the start", one "A at the apex"
        (0.5, 0.4, 0.1, 0.8, False),  # its own path still sees A at its start
        (0.5, 0.1, 0.25, 0.7, False),  # so does the apex path
        (0.5, 0.1, 0.1, 0.2, False),  # the apex path sees no A at the apex either
        (0.9, 0.1, 0.1, 0.8, False),  # a sure A is not looked at
    ],
)
def test_an_unsure_a_at_a_stubs_far_end_moves_to_the_vs_apex(
    monkeypatch: pytest.MonkeyPatch,
    confidence: float,
    p_start: float,
    p_apex_start: float,
    p_apex: float,
    moves: bool,
) -> None:
    stub_end, corner, b = (20.0, 80.0), (60.0, 20.0), (130.0, 80.0)
    mask = _thick_polyline([stub_end, corner, b], 4.0, (100, 160))
    config = dataclasses.replace(
        TINY,
        strip_channels=(4, 8, 16),
        strip_shape=(16, 384),
        apex_max_confidence=0.65,
        apex_start_max_prob=0.3,
        apex_path_start_max_prob=0.2,
    )
    det = Detector(DetectorNet(config), device="cpu")
    res = detector_module.FineResult(
        np.array([stub_end, b]), np.array([confidence, 0.9]), mask, detector_module.View(0, 0, 160, 64)
    )
    # the centreline cuts across the V (as the detector's does), straight from the stub's end to B
    line = np.stack([np.linspace(20.0, 130.0, 50), np.full(50, 80.0)], axis=1)
    final = detector_module.Finished(res.landmarks_px.copy(), line, mask)
    step_px = config.refine_step_px(None)
    seen: list[list[np.ndarray]] = []

    def strip_probabilities(image: np.ndarray, paths: list, **kw: object) -> np.ndarray:
        seen.append(paths)
        p = np.zeros((2, 385))
        p[0, 0], p[0, 200] = p_start, 1.0 - p_start  # the own path: A at its start, or 58 mm on
        k = round(float(np.linalg.norm(paths[1][1] - paths[1][0])) / step_px)
        p[1, 0], p[1, k] = p_apex_start, p_apex  # the apex path: A at its start, at the apex, or none
        p[1, -1] = 1.0 - p_apex - p_apex_start
        return p

    finished: list[np.ndarray] = []

    def finish(fine_pts: np.ndarray) -> detector_module.Finished:
        finished.append(fine_pts.copy())
        return detector_module.Finished(fine_pts.copy(), line, mask)

    monkeypatch.setattr(det, "strip_probabilities", strip_probabilities)
    out = det.off_apex(np.zeros((100, 160), np.float32), res, final, finish)
    if not moves:
        assert out is final and not finished
        return
    assert len(seen) == 1 and np.allclose(seen[0][0], line) and np.allclose(seen[0][1][2], b)
    assert float(np.linalg.norm(finished[0][0] - np.array(corner))) <= 1.5  # A at the apex
    np.testing.assert_allclose(finished[0][1], b)  # B's fine landmark stays
    # a straight mask has no apex: unchanged; without a strip stage: unchanged
    straight = _thick_polyline([stub_end, b], 4.0, (100, 160))
    flat = detector_module.Finished(res.landmarks_px.copy(), line, straight)
    assert det.off_apex(np.zeros((100, 160), np.float32), res, flat, finish) is flat
    det.net.strip = None
    assert det.off_apex(np.zeros((100, 160), np.float32), res, final, finish) is final
