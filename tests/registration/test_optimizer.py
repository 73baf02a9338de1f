"""CMA-ES and Nelder-Mead wrappers on analytic functions."""

from __future__ import annotations

import numpy as np
import pytest

from fluoronav.registration.optimizer import CMAES, NelderMead

TARGET = np.array([1.0, -2.0, 3.0, 0.5])


def sphere(X: np.ndarray) -> np.ndarray:
    return ((X - TARGET) ** 2).sum(axis=1)


def rosenbrock(X: np.ndarray) -> np.ndarray:
    return (100.0 * (X[:, 1:] - X[:, :-1] ** 2) ** 2 + (1.0 - X[:, :-1]) ** 2).sum(axis=1)


def test_cmaes_sphere_whole_population_per_call() -> None:
    shapes: list[tuple[int, ...]] = []

    def f(X: np.ndarray) -> np.ndarray:
        shapes.append(X.shape)
        return sphere(X)

    res = CMAES(sigma=(1.0, 1.0, 2.0, 0.5), popsize=16, tolx=1e-6, tolfun=1e-12, seed=4).minimize(
        f, np.zeros(4)
    )
    assert set(shapes) == {(16, 4)}
    assert len(shapes) == res.n_iters and res.n_evals == 16 * res.n_iters
    assert res.converged and res.stop_reason
    np.testing.assert_allclose(res.x, TARGET, atol=1e-4)
    assert res.f < 1e-8
    assert len(res.history) == res.n_iters
    assert res.history[-1].n_evals == res.n_evals


def test_cmaes_rosenbrock() -> None:
    res = CMAES(sigma=(0.5,) * 4, popsize=20, tolx=1e-9, tolfun=1e-14, seed=3).minimize(
        rosenbrock, np.zeros(4)
    )
    np.testing.assert_allclose(res.x, np.ones(4), atol=1e-4)
    assert res.f < 1e-8


def test_cmaes_reproducible_with_seed() -> None:
    opt = CMAES(sigma=(1.0,) * 4, popsize=10, tolx=1e-3, tolfun=1e-6, seed=7)
    a = opt.minimize(sphere, np.zeros(4))
    b = opt.minimize(sphere, np.zeros(4))
    c = CMAES(sigma=(1.0,) * 4, popsize=10, tolx=1e-3, tolfun=1e-6, seed=8).minimize(sphere, np.zeros(4))
    np.testing.assert_array_equal(a.x, b.x)
    assert a.n_evals == b.n_evals
    assert not np.array_equal(a.x, c.x)


def test_cmaes_bounds_respected() -> None:
    seen: list[np.ndarray] = []

    def f(X: np.ndarray) -> np.ndarray:
        seen.append(X.copy())
        return sphere(X)

    lo, hi = (-1.0, -1.0, -1.0, -1.0), (0.5, 0.0, 2.0, 2.0)
    res = CMAES(sigma=(0.5,) * 4, popsize=12, tolx=1e-6, tolfun=1e-12, bounds=(lo, hi), seed=2).minimize(
        f, np.zeros(4)
    )
    allx = np.concatenate(seen)
    assert np.all(allx >= np.array(lo) - 1e-12) and np.all(allx <= np.array(hi) + 1e-12)
    # constrained optimum is the clipped target
    np.testing.assert_allclose(res.x, np.clip(TARGET, lo, hi), atol=1e-3)


def test_cmaes_budget_and_nonfinite() -> None:
    def f(X: np.ndarray) -> np.ndarray:
        out = sphere(X)
        out[0] = np.nan  # one failed candidate per generation must not stop the search
        return out

    res = CMAES(sigma=(1.0,) * 4, popsize=8, max_iters=5, seed=1).minimize(f, np.zeros(4))
    assert res.n_iters == 5 and not res.converged and "maxiter" in res.stop_reason
    assert res.n_nonfinite == 5 and np.isfinite(res.f)


def test_cmaes_ipop_restart_increases_population() -> None:
    sizes: list[int] = []

    def f(X: np.ndarray) -> np.ndarray:
        sizes.append(X.shape[0])
        return rosenbrock(X)

    res = CMAES(sigma=(0.5,) * 4, popsize=6, max_iters=3, restarts=2, seed=1).minimize(f, np.zeros(4))
    assert sorted(set(sizes)) == [6, 12, 24]
    assert [r.restart for r in res.history].count(2) == 3


def test_nelder_mead_same_interface() -> None:
    res = NelderMead(sigma=(0.5, 0.5), xatol=1e-8, fatol=1e-14, max_evals=5000).minimize(
        rosenbrock, np.zeros(2)
    )
    assert res.converged
    np.testing.assert_allclose(res.x, np.ones(2), atol=1e-5)
    assert len(res.history) == res.n_iters
    bounded = NelderMead(
        sigma=(0.5,) * 4, xatol=1e-6, fatol=1e-12, bounds=((-1,) * 4, (0.5, 0.0, 2.0, 2.0)), max_evals=4000
    ).minimize(sphere, np.zeros(4))
    np.testing.assert_allclose(bounded.x, np.clip(TARGET, -1, [0.5, 0.0, 2.0, 2.0]), atol=1e-3)


def test_bad_inputs() -> None:
    with pytest.raises(ValueError):
        CMAES(sigma=(1.0, 1.0)).minimize(sphere, np.zeros(4))
    with pytest.raises(ValueError):
        CMAES(sigma=(1.0,), bounds=((0,) * 4, (1,) * 4)).minimize(sphere, -np.ones(4))
