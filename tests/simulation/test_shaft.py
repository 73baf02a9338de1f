"""The CM's mounting shaft in the simulator: analytic tube chords and where the shaft shows."""

from __future__ import annotations

import numpy as np
import torch

from fluoronav.simulation.xray import tube_chord_mm


def test_tube_chord_matches_sampled_integration() -> None:
    rng = np.random.default_rng(0)
    origin = torch.tensor([7.0, -3.0, 40.0], dtype=torch.float64)
    # rays aimed at random points around the cylinder (some miss, some graze, some cross the ends)
    targets = np.column_stack([rng.uniform(-4, 4, 200), rng.uniform(-4, 4, 200), rng.uniform(-60, 5, 200)])
    d = targets - origin.numpy()
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = tube_chord_mm(origin, torch.as_tensor(d), 3.0, -54.0, -4.0).numpy()
    t = np.linspace(0.0, 200.0, 400_001)
    for k in range(0, 200, 7):
        p = origin.numpy()[None] + t[:, None] * d[k]
        inside = (p[:, 0] ** 2 + p[:, 1] ** 2 <= 9.0) & (p[:, 2] >= -54.0) & (p[:, 2] <= -4.0)
        assert abs(inside.sum() * (t[1] - t[0]) - got[k]) < 2e-3
    assert (got == 0).any() and (got > 0).any()
