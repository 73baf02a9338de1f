"""Registration engine on a toy 2D problem with a known renderer (3 params: shift u, v in px, angle deg)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from fluoronav.errors import RegistrationFailure
from fluoronav.registration.engine import Registration
from fluoronav.registration.levels import LevelConfig
from fluoronav.registration.priors import LandmarkPrior

H = W = 96
CENTRE = np.array([(W - 1) / 2, (H - 1) / 2])
# asymmetric blob layout (u, v) in full-resolution pixels relative to the centre, and amplitudes
BLOBS = torch.tensor(
    [[-20.0, -12.0], [15.0, -18.0], [22.0, 16.0], [-8.0, 20.0], [0.0, 0.0]], dtype=torch.float64
)
AMPS = torch.tensor([1.0, 0.6, 1.4, 0.8, 0.5], dtype=torch.float64)
SIGMA_PX = 3.5
TRUTH = np.array([4.3, -2.7, 8.0])


def blob_centres(params: torch.Tensor) -> torch.Tensor:
    """(P, 3) → (P, 5, 2) full-resolution blob centres."""
    a = torch.deg2rad(params[:, 2])
    c, s = torch.cos(a), torch.sin(a)
    R = torch.stack([torch.stack([c, -s], -1), torch.stack([s, c], -1)], -2)  # (P, 2, 2)
    return BLOBS @ R.transpose(-1, -2) + torch.as_tensor(CENTRE) + params[:, None, :2]


def render(params: torch.Tensor, level: LevelConfig) -> torch.Tensor:
    """(P, 3) → (P, 1, H/f, W/f): Gaussian blobs sampled at the working-resolution pixel centres."""
    f = level.downsample
    ctr = (blob_centres(params) - (f - 1) / 2) / f  # working pixels
    v, u = torch.meshgrid(
        torch.arange(H // f, dtype=torch.float64), torch.arange(W // f, dtype=torch.float64), indexing="ij"
    )
    d2 = (u[None, None] - ctr[..., 0, None, None]) ** 2 + (v[None, None] - ctr[..., 1, None, None]) ** 2
    img = (AMPS[None, :, None, None] * torch.exp(-0.5 * d2 / (SIGMA_PX / f) ** 2)).sum(1)
    return img[:, None]


def levels() -> list[LevelConfig]:
    return [
        LevelConfig(
            sigma=(4.0, 4.0, 6.0),
            downsample=2,
            patch_radius=5,
            stride=2,
            popsize=16,
            tolx=0.05,
            tolfun=1e-4,
            max_iters=200,
            name="coarse",
        ),
        LevelConfig(
            sigma=(0.5, 0.5, 1.0),
            downsample=1,
            patch_radius=8,
            stride=3,
            popsize=12,
            tolx=1e-3,
            tolfun=1e-7,
            max_iters=300,
            name="fine",
        ),
    ]


def test_engine_recovers_known_params() -> None:
    fixed = render(torch.tensor(TRUTH[None]), LevelConfig(sigma=(1.0,)))[0]  # (1, H, W)
    seen_shapes: set[tuple[int, ...]] = set()

    def render_logged(params: torch.Tensor, level: LevelConfig) -> torch.Tensor:
        seen_shapes.add(tuple(params.shape))
        assert params.dtype == torch.float64
        return render(params, level)

    reg = Registration(
        render_logged, fixed, levels(), parameter_names=["du_px", "dv_px", "angle_deg"], seed=3
    )
    res = reg.run(np.zeros(3))
    assert res.success and res.converged, res.reason
    np.testing.assert_allclose(res.params, TRUTH, atol=0.02)
    assert res.cost < 1e-4
    # whole populations are rendered at once
    assert seen_shapes == {(16, 3), (12, 3)}
    tr = res.trace
    assert [lv.name for lv in tr.levels] == ["coarse", "fine"]
    assert tr.levels[1].x_start == tr.levels[0].x  # warm start
    assert all(lv.n_iters == len(lv.iterations) > 0 for lv in tr.levels)
    it = tr.levels[0].iterations
    assert it[-1].best_cost < it[0].best_cost and it[-1].elapsed_s >= it[0].elapsed_s
    d = json.loads(tr.to_json())
    assert d["parameter_names"] == ["du_px", "dv_px", "angle_deg"]
    assert d["levels"][0]["config"]["patch_radius"] == 5


def test_engine_with_landmark_prior_and_callable_fixed() -> None:
    truth = torch.tensor(TRUTH[None])
    detected = blob_centres(truth)[0, :2][None]  # (K=1, L=2, 2) full-resolution landmarks

    def project(params: torch.Tensor) -> torch.Tensor:
        return blob_centres(params)[:, None, :2]

    prior = LandmarkPrior(project, detected, sigma_px=100.0)
    reg = Registration(render, lambda lv: render(truth, lv)[0], levels()[1:], priors=[prior], seed=5)
    res = reg.run(np.array([1.5, -1.0, 3.0]))
    assert res.success
    np.testing.assert_allclose(res.params, TRUTH, atol=0.02)
    # the prior at the start is what eq. 2 says
    start = reg.objective(levels()[1])(np.array([[1.5, -1.0, 3.0], TRUTH]))
    p = float(prior(torch.tensor([[1.5, -1.0, 3.0]], dtype=torch.float64))[0])
    assert p > 0 and start[1] < 1e-9 and start[0] > p


def test_engine_reports_non_finite_cost() -> None:
    fixed = render(torch.tensor(TRUTH[None]), LevelConfig(sigma=(1.0,)))[0]

    def broken(params: torch.Tensor, level: LevelConfig) -> torch.Tensor:
        return torch.full_like(render(params, level), math.nan)

    lv = [LevelConfig(sigma=(1.0, 1.0, 1.0), popsize=6, max_iters=3, patch_radius=8, stride=4)]
    res = Registration(broken, fixed, lv).run(np.zeros(3))
    assert not res.success and not res.converged and res.reason == "non-finite cost at level 0"
    assert res.trace.levels[0].n_nonfinite == res.trace.levels[0].n_evals > 0
    with pytest.raises(RegistrationFailure):
        Registration(broken, fixed, lv).run(np.zeros(3), raise_on_failure=True)
    # budget exhausted: finite but not converged
    res2 = Registration(render, fixed, lv).run(np.zeros(3))
    assert np.isfinite(res2.cost) and not res2.converged and res2.reason.startswith("not converged")


def test_engine_shape_mismatch_is_reported() -> None:
    fixed = torch.zeros(1, 50, 50, dtype=torch.float64)
    lv = [LevelConfig(sigma=(1.0, 1.0, 1.0), popsize=4, max_iters=1, patch_radius=3)]
    with pytest.raises(ValueError, match="render returned"):
        Registration(render, fixed, lv).run(np.zeros(3))


def test_engine_two_views_with_mask_sums_view_costs() -> None:
    def render2(params: torch.Tensor, level: LevelConfig) -> torch.Tensor:
        img = render(params, level)[:, 0]
        return torch.stack([img, img.flip(-1)], dim=1)  # second "view": mirrored

    truth = torch.tensor(TRUTH[None])
    fixed = render2(truth, LevelConfig(sigma=(1.0,)))[0]  # (2, H, W)
    mask = torch.ones(H, W, dtype=torch.bool)
    mask[:, :20] = False
    lv = levels()[1]
    reg = Registration(render2, fixed, [lv], fixed_mask=mask, seed=2)
    X = np.array([[1.0, 0.5, 2.0]])
    f_level, m_level = reg.fixed_for(lv)
    assert f_level.shape == (2, H, W) and m_level is not None and int((~m_level).sum()) == 20 * H
    from fluoronav.registration.similarity import PatchGradNCC

    per_view = PatchGradNCC(fixed, patch_radius=lv.radius, stride=lv.stride, mask=mask)(
        render2(torch.tensor(X), lv)
    )
    np.testing.assert_allclose(reg.objective(lv)(X), per_view.sum(1).numpy(), rtol=1e-12)
    X3 = np.array([[1.0, 0.5, 2.0], [0.0, 0.0, 0.0], [-2.0, 1.0, -3.0]])
    chunked = Registration(render2, fixed, [lv], fixed_mask=mask, chunk_size=2).objective(lv)(X3)
    np.testing.assert_allclose(chunked, reg.objective(lv)(X3), rtol=1e-12)
    res = reg.run(np.zeros(3))
    assert res.success
    np.testing.assert_allclose(res.params, TRUTH, atol=0.02)


def test_multi_start_keeps_the_lowest_first_level_and_records_the_others():
    """A tilted double well f(x) = (x² − 1)² + 0.3 (x − 1)²: from x0 = −1.2 with a small σ CMA-ES
    stays in the local well at −1; a second start at +1.2 finds the global one near +1."""

    def render_x(params: torch.Tensor, level: LevelConfig) -> torch.Tensor:
        return params[:, :1, None, None]  # (P, 1, 1, 1): the "image" is the parameter

    def double_well(fixed, level, mask):
        return lambda moving: (moving[:, 0, 0, 0] ** 2 - 1) ** 2 + 0.3 * (moving[:, 0, 0, 0] - 1) ** 2

    lv = [
        LevelConfig(sigma=(0.05,), popsize=8, tolx=1e-6, tolfun=1e-12, max_iters=100, name="a"),
        LevelConfig(sigma=(0.01,), popsize=8, tolx=1e-7, tolfun=1e-12, max_iters=100, name="b"),
    ]
    reg = Registration(render_x, torch.zeros(1, 1, 1), lv, similarity=double_well, seed=3)
    single = reg.run([-1.2])
    assert single.params[0] < 0 and not single.trace.screened
    multi = reg.run([-1.2], starts=[[1.2]])
    assert multi.params[0] > 0.9 and multi.cost < single.cost
    assert len(multi.trace.levels) == 2 and len(multi.trace.screened) == 1
    assert multi.trace.screened[0].x[0] < 0 and multi.trace.levels[0].x_start == [1.2]
    back = type(multi.trace).from_json(multi.trace.to_json())
    assert len(back.screened) == 1 and back.screened[0].x == multi.trace.screened[0].x


def test_multi_start_keep_two_lets_the_last_level_choose():
    """The first level prefers the well at −1, the last the well at +1: with ``keep=1`` the result
    stays at −1, with ``keep=2`` both wells are finished and the last level's choice wins."""

    def render_x(params: torch.Tensor, level: LevelConfig) -> torch.Tensor:
        return params[:, :1, None, None]

    def wells(fixed, level, mask):
        tilt = 1.0 if level.name == "a" else -1.0
        return lambda m: (m[:, 0, 0, 0] ** 2 - 1) ** 2 + 0.3 * (m[:, 0, 0, 0] + tilt) ** 2

    lv = [
        LevelConfig(sigma=(0.05,), popsize=8, tolx=1e-6, tolfun=1e-12, max_iters=100, name="a"),
        LevelConfig(sigma=(0.01,), popsize=8, tolx=1e-7, tolfun=1e-12, max_iters=100, name="b"),
    ]
    reg = Registration(render_x, torch.zeros(1, 1, 1), lv, similarity=wells, seed=5)
    one = reg.run([1.2], starts=[[-1.2]], keep=1)
    two = reg.run([1.2], starts=[[-1.2]], keep=2)
    assert one.params[0] < 0 and two.params[0] > 0.9
    assert len(two.trace.levels) == 2 and len(two.trace.screened) == 2  # the other run's two levels
    assert [lt.name for lt in two.trace.levels] == ["a", "b"]
