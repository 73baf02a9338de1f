"""The linearised refinement against known optima of analytic image models."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fluoronav.registration.engine import Registration, optimizer_for
from fluoronav.registration.levels import LevelConfig
from fluoronav.registration.linearized import LinearizedRefiner
from fluoronav.registration.similarity import PatchGradNCC

H, W = 64, 72


def _blobs(params: torch.Tensor) -> torch.Tensor:
    """(P, 1, H, W) images of two anisotropic Gaussian blobs moved by (du, dv, rotation deg, scale %)
    about the image centre: a smooth, exactly known image model with its optimum at the truth."""
    v, u = torch.meshgrid(
        torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij"
    )
    du, dv, rot, sc = (params[:, i, None, None] for i in range(4))
    a = torch.deg2rad(rot)
    s = 1.0 + sc / 100.0
    x, y = u - W / 2 - du, v - H / 2 - dv
    xr = (torch.cos(a) * x + torch.sin(a) * y) / s
    yr = (-torch.sin(a) * x + torch.cos(a) * y) / s
    img = torch.exp(-(((xr - 8) / 6) ** 2 + ((yr + 3) / 3) ** 2)) + 0.7 * torch.exp(
        -(((xr + 10) / 4) ** 2 + ((yr - 6) / 7) ** 2)
    )
    return img[:, None]


TRUTH = np.array([2.3, -1.7, 4.0, 3.0])


def _parts() -> tuple:
    fixed = _blobs(torch.as_tensor(TRUTH)[None])[0]
    sim = PatchGradNCC(fixed, patch_radius=6, stride=2, sigma_px=1.0)

    def cost_of(moving: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
        return sim(moving).sum(dim=1).to(torch.float64)

    return _blobs, cost_of


@pytest.mark.parametrize("start", [(0.0, 0.0, 0.0, 0.0), (4.0, 0.5, 7.0, 0.0), (1.0, -3.5, 1.0, 6.0)])
def test_refiner_recovers_the_known_optimum(start: tuple[float, ...]) -> None:
    render, cost_of = _parts()
    res = LinearizedRefiner((1.0, 1.0, 2.0, 2.0), tolx=1e-3, tolfun=1e-9, max_iters=20).minimize(
        render, cost_of, np.asarray(start), device=torch.device("cpu")
    )
    # 0.01 px and 0.05° / 0.05 % of scale
    assert np.all(np.abs(res.x - TRUTH) < [0.01, 0.01, 0.05, 0.05]), res.x
    assert res.f < 1e-4
    assert res.n_evals <= 5 * 20  # five renders per linearisation, from starts up to 3.5σ off


def test_refiner_never_returns_a_worse_point_and_respects_bounds() -> None:
    render, cost_of = _parts()
    x0 = np.array([1.0, -1.0, 2.0, 1.0])
    with torch.no_grad():
        f0 = float(cost_of(render(torch.as_tensor(x0)[None]), torch.as_tensor(x0)[None])[0])
    bounds = ((-5.0, -5.0, -10.0, -10.0), (2.0, 5.0, 10.0, 10.0))  # the optimum's du is outside
    res = LinearizedRefiner((1.0, 1.0, 2.0, 2.0), tolx=1e-3, bounds=bounds).minimize(
        render, cost_of, x0, device=torch.device("cpu")
    )
    assert res.f <= f0
    assert res.x[0] <= 2.0 + 1e-12
    assert abs(res.x[0] - 2.0) < 0.05  # pressed against the bound nearest the optimum


def test_engine_runs_a_linearized_level_after_cmaes() -> None:
    """The engine dispatches a "linearized" level and warm-starts it from the CMA-ES level."""
    fixed = _blobs(torch.as_tensor(TRUTH)[None])[0]
    levels = [
        LevelConfig(
            sigma=(3.0, 3.0, 5.0, 5.0), popsize=10, max_iters=15, patch_radius=6, stride=2, name="cma"
        ),
        LevelConfig(
            sigma=(1.0, 1.0, 2.0, 2.0),
            optimizer="linearized",
            patch_radius=6,
            stride=2,
            tolx=1e-3,
            tolfun=1e-9,
            max_iters=20,
            name="lin",
        ),
    ]
    reg = Registration(lambda p, lv: _blobs(p), fixed, levels, seed=3)
    res = reg.run(np.zeros(4))
    assert [lt.name for lt in res.trace.levels] == ["cma", "lin"]
    assert res.trace.levels[1].cost <= res.trace.levels[0].cost
    assert np.all(np.abs(res.params - TRUTH) < [0.01, 0.01, 0.05, 0.05])
    with pytest.raises(ValueError, match="runs in Registration"):
        optimizer_for(levels[1], seed=0)  # no silent CMA-ES in its place
    with pytest.raises(ValueError, match="unknown optimizer"):
        LevelConfig(sigma=(1.0,), optimizer="newton")  # type: ignore[arg-type]


def test_refiner_counts_every_render_and_spends_one_on_a_rejected_step() -> None:
    """``n_evals`` is the number of images rendered; a trial step is one render, and the Jacobian's
    D renders are made only where a next step starts."""
    render, cost_of = _parts()
    rendered = []

    def counting(params: torch.Tensor) -> torch.Tensor:
        rendered.append(params.shape[0])
        return render(params)

    res = LinearizedRefiner((1.0, 1.0, 2.0, 2.0), tolx=1e-3, tolfun=1e-9, max_iters=20).minimize(
        counting, cost_of, np.array([4.0, 0.5, 7.0, 0.0]), device=torch.device("cpu")
    )
    assert res.n_evals == sum(rendered)
    trials = [n for n in rendered[1:] if n == 1]
    jacobians = [n for n in rendered[1:] if n == 4]
    assert rendered[0] == 5 and len(trials) + len(jacobians) == len(rendered) - 1
    assert len(jacobians) <= len(trials)  # one Jacobian per accepted step that is not the last
