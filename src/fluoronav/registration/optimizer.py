"""Derivative-free optimisers with a batched objective (the whole population in one call).

The objective maps a population ``X (P, D)`` to costs ``(P,)`` so that all candidates can be
rendered in one batch. :class:`CMAES` wraps pycma's ask/tell interface (with optional IPOP-style
restarts); :class:`NelderMead` (scipy) is a local refinement behind the same ``minimize`` interface.
Non-finite costs are passed to the optimiser as a large finite penalty so that one failed render
cannot stop the search; the result records how many were seen.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

__all__ = [
    "CMAES",
    "IterationRecord",
    "NelderMead",
    "Objective",
    "OptimizationResult",
    "Optimizer",
]

logger = logging.getLogger(__name__)

Objective = Callable[[np.ndarray], np.ndarray]
"""``objective(X (P, D) float64) -> (P,) float64`` costs, lower is better."""

# pycma stop keys that mean the run converged (rather than ran out of budget or degenerated)
_CONVERGED_KEYS = frozenset({"tolx", "tolfun", "tolfunhist", "tolfunrel", "ftarget"})
_NONFINITE_PENALTY = 1e30


@dataclass(frozen=True)
class IterationRecord:
    """One optimiser iteration (generation).

    Attributes:
        iteration: 1-based over the whole run (restarts included).
        best_cost: lowest cost of this generation.
        mean_cost: mean finite cost of this generation.
        sigma: CMA-ES step size (overall scale, multiplies the per-parameter stds); simplex size
            for Nelder-Mead.
        best_params: (D,) parameters of the generation's best.
        n_evals: cumulative objective evaluations.
        elapsed_s: wall time since the start of ``minimize``.
        restart: restart index (0 for the first run).
    """

    iteration: int
    best_cost: float
    mean_cost: float
    sigma: float
    best_params: tuple[float, ...]
    n_evals: int
    elapsed_s: float
    restart: int = 0


@dataclass(frozen=True)
class OptimizationResult:
    """Result of ``minimize``: best parameters over the whole run and how it stopped."""

    x: np.ndarray
    f: float
    n_evals: int
    n_iters: int
    converged: bool
    stop_reason: str
    history: list[IterationRecord] = field(default_factory=list)
    n_nonfinite: int = 0


class Optimizer(Protocol):
    """What the registration engine needs from an optimiser."""

    def minimize(
        self,
        objective: Objective,
        x0: np.ndarray,
        *,
        callback: Callable[[IterationRecord], None] | None = None,
    ) -> OptimizationResult: ...


def _evaluate(objective: Objective, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Call the objective once on the population; returns (raw costs, costs safe for the optimiser)."""
    f = np.asarray(objective(np.ascontiguousarray(X, dtype=np.float64)), dtype=np.float64).reshape(-1)
    if f.shape[0] != X.shape[0]:
        raise ValueError(f"objective returned {f.shape[0]} costs for {X.shape[0]} candidates")
    return f, np.where(np.isfinite(f), f, _NONFINITE_PENALTY)


def _as_bounds(
    bounds: tuple[Sequence[float], Sequence[float]] | None, dim: int
) -> tuple[np.ndarray, np.ndarray] | None:
    if bounds is None:
        return None
    lo = np.broadcast_to(np.asarray(bounds[0], dtype=np.float64), (dim,)).copy()
    hi = np.broadcast_to(np.asarray(bounds[1], dtype=np.float64), (dim,)).copy()
    if np.any(lo >= hi):
        raise ValueError("every lower bound must be below its upper bound")
    return lo, hi


@dataclass(frozen=True)
class CMAES:
    """CMA-ES (pycma) with a batched objective.

    Args:
        sigma: per-parameter initial standard deviations (D,), in parameter units (e.g. deg, mm);
            passed to pycma as ``CMA_stds`` with overall ``sigma0 = 1``.
        popsize: population size per generation (authors: 50).
        tolx: stop when all coordinate steps are below this (parameter units; authors 0.01).
        tolfun: stop when the range of recent costs is below this (authors 0.01).
        bounds: optional (lower (D,), upper (D,)); candidates are always sampled inside.
        max_iters: generations per run (None: pycma's default).
        max_evals: objective evaluations over the whole call, restarts included (None: unlimited).
        seed: random seed (pycma's; a seed of 0 is mapped to 1, since pycma treats 0 as "random").
        restarts: number of IPOP restarts from the best point so far, each with the population
            multiplied by ``incpopsize``; only taken when the previous run did not converge.
    """

    sigma: tuple[float, ...]
    popsize: int = 50
    tolx: float = 0.01
    tolfun: float = 0.01
    bounds: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    max_iters: int | None = None
    max_evals: int | None = None
    seed: int = 1
    restarts: int = 0
    incpopsize: float = 2.0

    def _options(self, dim: int, popsize: int, seed: int, evals_left: float) -> dict[str, Any]:
        opts: dict[str, Any] = {
            "CMA_stds": list(np.broadcast_to(np.asarray(self.sigma, dtype=np.float64), (dim,))),
            "popsize": int(popsize),
            "tolx": float(self.tolx),
            "tolfun": float(self.tolfun),
            "seed": int(seed) if seed != 0 else 1,
            "verbose": -9,
            "verb_log": 0,
            "verb_disp": 0,
        }
        if self.max_iters is not None:
            opts["maxiter"] = int(self.max_iters)
        if np.isfinite(evals_left):
            opts["maxfevals"] = int(evals_left)
        b = _as_bounds(self.bounds, dim)
        if b is not None:
            opts["bounds"] = [list(b[0]), list(b[1])]
        return opts

    def minimize(
        self,
        objective: Objective,
        x0: np.ndarray,
        *,
        callback: Callable[[IterationRecord], None] | None = None,
    ) -> OptimizationResult:
        """Minimise ``objective`` from ``x0`` (D,); the population is evaluated in one call per generation."""
        x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
        dim = x0.size
        if np.asarray(self.sigma).size not in (1, dim):
            raise ValueError(f"sigma has {np.asarray(self.sigma).size} entries for {dim} parameters")
        b = _as_bounds(self.bounds, dim)
        if b is not None and (np.any(x0 < b[0]) or np.any(x0 > b[1])):
            raise ValueError("x0 lies outside the bounds")
        t0 = time.perf_counter()
        history: list[IterationRecord] = []
        best_x, best_f = x0.copy(), np.inf
        n_evals = n_iters = n_nonfinite = 0
        converged, reason = False, ""
        popsize, start = self.popsize, x0
        for restart in range(self.restarts + 1):
            evals_left = np.inf if self.max_evals is None else self.max_evals - n_evals
            if evals_left < popsize:
                reason = reason or "maxfevals"
                break
            import cma  # here, not at the top: its import loads scipy.stats and pyplot

            es = cma.CMAEvolutionStrategy(
                start, 1.0, self._options(dim, popsize, self.seed + restart, evals_left)
            )
            while not es.stop():
                X = np.asarray(es.ask(), dtype=np.float64)
                raw, safe = _evaluate(objective, X)
                es.tell(list(X), list(safe))
                n_evals += len(X)
                n_iters += 1
                n_nonfinite += int(np.sum(~np.isfinite(raw)))
                i = int(np.argmin(safe))
                if safe[i] < best_f and np.isfinite(raw[i]):
                    best_f, best_x = float(safe[i]), X[i].copy()
                finite = raw[np.isfinite(raw)]
                rec = IterationRecord(
                    iteration=n_iters,
                    best_cost=float(raw[i]),
                    mean_cost=float(finite.mean()) if finite.size else float("nan"),
                    sigma=float(es.sigma),
                    best_params=tuple(float(v) for v in X[i]),
                    n_evals=n_evals,
                    elapsed_s=time.perf_counter() - t0,
                    restart=restart,
                )
                history.append(rec)
                if callback is not None:
                    callback(rec)
            stop = dict(es.stop())
            reason = ",".join(sorted(stop)) or "stopped"
            converged = bool(_CONVERGED_KEYS & set(stop))
            logger.debug(
                "CMA-ES run %d stopped after %d iterations: %s (best %.6g)", restart, n_iters, reason, best_f
            )
            if converged:
                break
            popsize = round(popsize * self.incpopsize)
            start = best_x
        return OptimizationResult(
            x=best_x,
            f=best_f,
            n_evals=n_evals,
            n_iters=n_iters,
            converged=converged,
            stop_reason=reason,
            history=history,
            n_nonfinite=n_nonfinite,
        )


@dataclass(frozen=True)
class NelderMead:
    """Local refinement by scipy's Nelder-Mead (bounded), behind the same interface as :class:`CMAES`.

    Args:
        sigma: per-parameter size of the initial simplex (D,), parameter units.
        xatol, fatol: absolute tolerances on parameters and cost.
        bounds: optional (lower, upper).
        max_iters, max_evals: budgets.

    The simplex is evaluated point by point (a batch of one); each iteration is recorded with the
    best vertex (``mean_cost`` = best cost and ``sigma`` = NaN, which scipy does not expose).
    """

    sigma: tuple[float, ...]
    xatol: float = 0.01
    fatol: float = 0.01
    bounds: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    max_iters: int | None = None
    max_evals: int | None = None

    def minimize(
        self,
        objective: Objective,
        x0: np.ndarray,
        *,
        callback: Callable[[IterationRecord], None] | None = None,
    ) -> OptimizationResult:
        x0 = np.asarray(x0, dtype=np.float64).reshape(-1)
        dim = x0.size
        step = np.broadcast_to(np.asarray(self.sigma, dtype=np.float64), (dim,))
        b = _as_bounds(self.bounds, dim)
        simplex = np.vstack([x0, x0 + np.diag(step)])
        if b is not None:
            # reflect vertices that leave the box to the other side of x0
            over = (simplex > b[1]) | (simplex < b[0])
            simplex = np.where(over, 2 * x0 - simplex, simplex)
            simplex = np.clip(simplex, b[0], b[1])
        t0 = time.perf_counter()
        history: list[IterationRecord] = []
        state = {"n": 0, "nonfinite": 0}

        def f1(x: np.ndarray) -> float:
            raw, safe = _evaluate(objective, x[None])
            state["n"] += 1
            state["nonfinite"] += int(not np.isfinite(raw[0]))
            return float(safe[0])

        from scipy import optimize  # here: a slow import, not needed at start-up

        def cb(intermediate_result: optimize.OptimizeResult) -> None:
            # scipy reports only the best vertex per iteration: no simplex size (σ = NaN)
            rec = IterationRecord(
                iteration=len(history) + 1,
                best_cost=float(intermediate_result.fun),
                mean_cost=float(intermediate_result.fun),
                sigma=float("nan"),
                best_params=tuple(float(v) for v in intermediate_result.x),
                n_evals=state["n"],
                elapsed_s=time.perf_counter() - t0,
            )
            history.append(rec)
            if callback is not None:
                callback(rec)

        options: dict[str, Any] = {"initial_simplex": simplex, "xatol": self.xatol, "fatol": self.fatol}
        if self.max_iters is not None:
            options["maxiter"] = int(self.max_iters)
        if self.max_evals is not None:
            options["maxfev"] = int(self.max_evals)
        bounds = None if b is None else optimize.Bounds(b[0], b[1])
        res = optimize.minimize(f1, x0, method="Nelder-Mead", bounds=bounds, options=options, callback=cb)
        converged = bool(res.success)
        return OptimizationResult(
            x=np.asarray(res.x, dtype=np.float64),
            f=float(res.fun),
            n_evals=int(res.nfev),
            n_iters=len(history),
            converged=converged,
            stop_reason="tolx,tolfun" if converged else str(res.message),
            history=history,
            n_nonfinite=state["nonfinite"],
        )
