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
