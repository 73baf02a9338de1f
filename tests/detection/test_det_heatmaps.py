"""Heatmap targets and sub-pixel decoding."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fluoronav.detection.heatmaps import decode_heatmaps, gaussian_heatmaps


@pytest.mark.parametrize("method", ["gaussian", "softargmax"])
@pytest.mark.parametrize("sigma", [1.5, 2.0, 3.0])
def test_decoding_recovers_subpixel_positions(method: str, sigma: float) -> None:
    rng = np.random.default_rng(0)
    pts = torch.from_numpy(rng.uniform(8, 56, size=(4, 2, 2)))
    hm = gaussian_heatmaps(pts, (64, 64), sigma_px=sigma)
    est, conf = decode_heatmaps(hm, method=method, window=int(np.ceil(4 * sigma)))
    assert torch.max(torch.abs(est - pts.float())) < 0.05
    # the peak of a sampled unit Gaussian is within exp(−(0.5² + 0.5²)/2σ²) of 1
    assert torch.all(conf > np.exp(-0.25 / sigma**2) - 1e-6) and torch.all(conf <= 1.0)


def test_absent_landmarks_give_zero_targets_and_confidence() -> None:
    pts = torch.tensor([[[10.0, 12.0], [float("nan"), float("nan")]]])
    hm = gaussian_heatmaps(pts, (32, 40), sigma_px=2.0, valid=torch.tensor([[True, True]]))
    assert hm.shape == (1, 2, 32, 40)
    assert float(hm[0, 0].max()) == pytest.approx(1.0)
    assert float(hm[0, 1].abs().max()) == 0.0
    hm2 = gaussian_heatmaps(pts[:, :1], (32, 40), sigma_px=2.0, valid=torch.tensor([[False]]))
    assert float(hm2.abs().max()) == 0.0
    _, conf = decode_heatmaps(hm)
    assert conf[0, 1] == 0.0


def test_heatmap_row_col_convention() -> None:
    # u is the column, v the row
    hm = gaussian_heatmaps(torch.tensor([[[5.0, 20.0]]]), (32, 16), sigma_px=1.0)
    v, u = np.unravel_index(int(hm[0, 0].argmax()), (32, 16))
    assert (u, v) == (5, 20)


def test_confidence_is_clipped_and_edges_do_not_break() -> None:
    hm = torch.zeros(1, 1, 8, 8)
    hm[0, 0, 0, 7] = 3.0  # a corner peak above 1
    pts, conf = decode_heatmaps(hm)
    assert conf.item() == 1.0
    assert pts[0, 0].tolist() == [7.0, 0.0]


def test_softmax_heatmaps_decode_subpixel_and_confidence() -> None:
    from fluoronav.detection.heatmaps import decode_logit_heatmaps

    pts = torch.tensor([[[20.3, 11.7], [5.55, 40.2]]], dtype=torch.float64)
    sigma = 2.0
    v, u = torch.meshgrid(torch.arange(48.0), torch.arange(40.0), indexing="ij")
    logits = torch.stack([-((u - p[0]) ** 2 + (v - p[1]) ** 2) / (2 * sigma**2) + 7.0 for p in pts[0]])[None]
    est, conf = decode_logit_heatmaps(logits, sigma_px=sigma)
    torch.testing.assert_close(est.double(), pts, atol=1e-3, rtol=0)
    # mass of a 2-D Gaussian within 2σ of its centre: 1 − exp(−2) (± the pixel grid)
    assert torch.all((conf - (1 - np.exp(-2.0))).abs() < 0.05)
    _, conf_flat = decode_logit_heatmaps(torch.zeros(1, 2, 48, 40), sigma_px=sigma)
    assert torch.all(conf_flat < 0.05)  # a diffuse prediction is not confident


def test_heatmap_cross_entropy_is_minimal_at_the_target_and_skips_absent() -> None:
    from fluoronav.detection.heatmaps import heatmap_cross_entropy

    pts = torch.tensor([[[10.4, 12.2], [float("nan"), float("nan")]]])
    logits = torch.zeros(1, 2, 24, 24, requires_grad=True)
    opt = torch.optim.Adam([logits], lr=0.3)
    for _ in range(300):
        opt.zero_grad()
        loss = heatmap_cross_entropy(logits, pts, sigma_px=1.5)
        loss.backward()
        opt.step()
    assert logits.grad is not None and float(logits.grad[0, 1].abs().max()) == 0.0  # absent: no signal
    from fluoronav.detection.heatmaps import decode_logit_heatmaps

    est, _ = decode_logit_heatmaps(logits.detach()[:, :1], sigma_px=1.5)
    assert float((est[0, 0] - pts[0, 0]).abs().max()) < 0.1
    none = heatmap_cross_entropy(torch.zeros(1, 2, 8, 8), torch.full((1, 2, 2), float("nan")), sigma_px=1.5)
    assert float(none) == 0.0


def _gauss_logits(
    centres: list[tuple[float, float, float]], shape: tuple[int, int], sigma: float
) -> torch.Tensor:
    """log of a mixture of Gaussians [(u, v, weight)] on a (rows, cols) grid."""
    v, u = torch.meshgrid(torch.arange(float(shape[0])), torch.arange(float(shape[1])), indexing="ij")
    parts = [np.log(w) - ((u - cu) ** 2 + (v - cv) ** 2) / (2 * sigma**2) for cu, cv, w in centres]
    return torch.logsumexp(torch.stack(parts), dim=0)


@pytest.mark.parametrize("mode", ["softmax", "gaussian"])
def test_min_separation_moves_the_landmark_that_costs_less(mode: str) -> None:
    from fluoronav.detection.heatmaps import decode_landmarks

    sigma = 2.0
    # both maps peak on one end (30.2, 20.6); B also has a weaker mode at the other end (70.4, 50.3),
    # A only a much weaker one at (60.0, 10.0): B should move, to its second mode
    a = _gauss_logits([(30.2, 20.6, 1.0), (60.0, 10.0, 0.05)], (64, 96), sigma)
    b = _gauss_logits([(30.2, 20.6, 1.0), (70.4, 50.3, 0.6)], (64, 96), sigma)
    logits = torch.stack([a, b])[None]
    maps = logits if mode == "softmax" else torch.exp(logits - logits.amax(dim=(-2, -1), keepdim=True))
    plain, _ = decode_landmarks(maps, mode=mode, sigma_px=sigma)
    assert float((plain[0, 1] - torch.tensor([30.2, 20.6])).abs().max()) < 0.05  # collapsed on one end
    est, conf = decode_landmarks(maps, mode=mode, sigma_px=sigma, min_separation_px=8.0)
    assert float((est[0, 0] - torch.tensor([30.2, 20.6])).abs().max()) < 0.05  # A kept
    assert float((est[0, 1] - torch.tensor([70.4, 50.3])).abs().max()) < 0.05  # B at its own end
    if mode == "softmax":
        # B's confidence is its mass there in the whole map: 0.6 / 1.6 of its Gaussians' 0.86
        assert abs(float(conf[0, 1]) - 0.6 / 1.6 * (1 - np.exp(-2.0))) < 0.03
    # the same with the roles exchanged: A moves
    est_swapped, _ = decode_landmarks(maps.flip(1), mode=mode, sigma_px=sigma, min_separation_px=8.0)
    torch.testing.assert_close(est_swapped, est.flip(1))


def test_min_separation_leaves_separate_peaks_alone() -> None:
    from fluoronav.detection.heatmaps import decode_landmarks, separation_exclusion

    sigma = 2.0
    a = _gauss_logits([(20.0, 20.0, 1.0)], (48, 48), sigma)
    b = _gauss_logits([(31.5, 20.0, 1.0), (20.0, 21.0, 0.9)], (48, 48), sigma)
    logits = torch.stack([a, b])[None]
    assert not separation_exclusion(logits, min_separation_px=11.0).any()  # 11.5 px apart
    torch.testing.assert_close(
        decode_landmarks(logits, mode="softmax", sigma_px=sigma, min_separation_px=11.0),
        decode_landmarks(logits, mode="softmax", sigma_px=sigma),
    )
    assert separation_exclusion(logits, min_separation_px=12.0)[0, 1].any()  # 11.5 < 12: B moves
    assert not separation_exclusion(logits, min_separation_px=0.0).any()
    with pytest.raises(ValueError, match="B, 2"):
        separation_exclusion(logits[:, :1], min_separation_px=4.0)
