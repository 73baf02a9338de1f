"""Multi-level intensity-based 2D/3D registration engine (renderer independent).

Level by level it minimises ``cost(x) = Σ_views S_level(fixed_level, render(x, level)) + Σ_priors
prior(x)`` with the optimiser the level names (CMA-ES by default), each level warm-started from the
previous one's best parameters. The workflow supplies the parts:

- ``render(params (P, D) float64, level) -> (P, V, h, w)``: the whole population in one call;
- ``fixed``: (V, H, W) full-resolution images, area-binned per level, or a callable ``level -> (V, h, w)``;
- ``similarity``: factory ``(fixed_level (V, h, w), level, mask_level) -> module`` mapping
  (P, V, h, w) to (P, V) or (P,) costs, built once per level (default :class:`PatchGradNCC`);
- ``priors``: callables ``params (P, D) -> (P,)`` (e.g. :class:`LandmarkPrior` at full resolution).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from fluoronav.errors import RegistrationFailure
from fluoronav.registration.levels import LevelConfig
from fluoronav.registration.linearized import LinearizedRefiner
from fluoronav.registration.optimizer import (
    CMAES,
    IterationRecord,
    NelderMead,
    Objective,
    OptimizationResult,
    Optimizer,
)
from fluoronav.registration.roi import area_downsample
from fluoronav.registration.similarity import PatchGradNCC
from fluoronav.registration.trace import LevelTrace, RegistrationTrace

__all__ = [
    "PriorFn",
    "Registration",
    "RegistrationResult",
    "RenderFn",
    "SimilarityFactory",
    "default_similarity",
    "optimizer_for",
]

logger = logging.getLogger(__name__)

RenderFn = Callable[[torch.Tensor, LevelConfig], torch.Tensor]
PriorFn = Callable[[torch.Tensor], torch.Tensor]
SimilarityFactory = Callable[
    [torch.Tensor, LevelConfig, "torch.Tensor | None"], Callable[[torch.Tensor], torch.Tensor]
]


def default_similarity(
    fixed: torch.Tensor, level: LevelConfig, mask: torch.Tensor | None
) -> Callable[[torch.Tensor], torch.Tensor]:
    """Patch gradient NCC with the level's radius, stride and smoothing."""
    return PatchGradNCC(
        fixed,
        patch_radius=level.radius,
        stride=level.stride,
        sigma_px=level.smooth_sigma_px,
        mask=mask,
        backend=level.similarity_backend,
    )


def optimizer_for(level: LevelConfig, *, seed: int) -> Optimizer:
    """The derivative-free optimiser a level asks for ("linearized" levels need the rendered images,
    not only their costs: :meth:`Registration.run` gives them a
    :class:`~fluoronav.registration.linearized.LinearizedRefiner`)."""
    if level.optimizer == "linearized":
        raise ValueError(f"level {level.name!r} is 'linearized': it runs in Registration, not as Optimizer")
    if level.optimizer == "nelder-mead":
        return NelderMead(
            sigma=level.sigma,
            xatol=level.tolx,
            fatol=level.tolfun,
            bounds=level.bounds,
            max_iters=level.max_iters,
            max_evals=level.max_evals,
        )
    return CMAES(
        sigma=level.sigma,
        popsize=level.popsize,
        tolx=level.tolx,
        tolfun=level.tolfun,
        bounds=level.bounds,
        max_iters=level.max_iters,
        max_evals=level.max_evals,
        seed=seed,
        restarts=level.restarts,
    )


@dataclass(frozen=True)
class RegistrationResult:
    """Outcome of :meth:`Registration.run`.

    Attributes:
        params: (D,) best parameters of the last level run.
        cost: their cost (similarity + priors) at that level.
        converged: the last level stopped on its tolerances.
        success: converged with a finite cost.
        reason: "converged (<pycma keys>)", "not converged: <keys>" or "non-finite cost at level i".
        trace: per-iteration and per-level records.
        seconds: wall time of the whole run.
    """

    params: np.ndarray
    cost: float
    converged: bool
    success: bool
    reason: str
    trace: RegistrationTrace
    seconds: float


class Registration:
    """Multi-level registration; see the module docstring for the parts.

    Args:
        render: ``(params (P, D) float64 on device, level) -> (P, V, h, w)``.
        fixed: (V, H, W) full-resolution fixed images, or a callable ``level -> (V, h, w)``.
        levels: level settings, run in order.
        priors: callables ``params (P, D) -> (P,)`` added to the similarity.
        similarity: factory of the per-level similarity (default patch gradient NCC).
        fixed_mask: optional (V, H, W) or (H, W) mask at full resolution (binned per level, a working
            pixel is used when at least half of its block is); ignored when ``fixed`` is a callable.
        parameter_names: labels for the trace.
        seed: CMA-ES seed of level 0 (level i uses seed + i).
        chunk_size: render at most this many candidates per call (memory bound); None = all at once.
        device: device of the parameters passed to ``render`` and of the fixed images.
        before_level: called as ``before_level(i, level, x)`` before level ``i`` starts from ``x``
            (e.g. the CM registration measures the image's response at the current estimate).
    """

    def __init__(
        self,
        render: RenderFn,
        fixed: torch.Tensor | np.ndarray | Callable[[LevelConfig], torch.Tensor],
        levels: Sequence[LevelConfig],
        *,
        priors: Sequence[PriorFn] = (),
        similarity: SimilarityFactory = default_similarity,
        fixed_mask: torch.Tensor | None = None,
        parameter_names: Sequence[str] | None = None,
        seed: int = 1,
        chunk_size: int | None = None,
        device: torch.device | str = "cpu",
        before_level: Callable[[int, LevelConfig, np.ndarray], None] | None = None,
    ) -> None:
        if not levels:
            raise ValueError("at least one level is needed")
        self.render = render
        self.levels = list(levels)
        self.priors = list(priors)
        self.similarity = similarity
        self.fixed_mask = fixed_mask
        self.parameter_names = list(parameter_names) if parameter_names is not None else None
        self.seed = int(seed)
        self.chunk_size = chunk_size
        self.device = torch.device(device)
        self.before_level = before_level
        if callable(fixed):
            self._fixed_fn: Callable[[LevelConfig], torch.Tensor] | None = fixed
            self._fixed: torch.Tensor | None = None
        else:
            f = torch.as_tensor(fixed, device=self.device)
            self._fixed = f if f.dim() == 3 else f.unsqueeze(0)
            self._fixed_fn = None

    # ----- per-level pieces -----------------------------------------------------------------------
    def fixed_for(self, level: LevelConfig) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Fixed images (V, h, w) and mask at the level's resolution."""
        if self._fixed_fn is not None:
            f = torch.as_tensor(self._fixed_fn(level), device=self.device)
            return (f if f.dim() == 3 else f.unsqueeze(0)), None
        assert self._fixed is not None
        f = area_downsample(self._fixed, level.downsample)
        mask = None
        if self.fixed_mask is not None:
            m = torch.as_tensor(self.fixed_mask, device=self.device).to(torch.float64)
            mask = area_downsample(m, level.downsample) >= 0.5
        return f, mask

    def level_parts(
        self, level: LevelConfig
    ) -> tuple[Callable[[torch.Tensor], torch.Tensor], Callable[[torch.Tensor, torch.Tensor], torch.Tensor]]:
        """``render_images(params (P, D)) -> (P, V, h, w)`` and ``cost_of(moving, params) -> (P,)``
        (similarity summed over views, plus the priors) of one level."""
        fixed, mask = self.fixed_for(level)
        sim = self.similarity(fixed, level, mask)
        n_views = fixed.shape[0]

        def render_images(params: torch.Tensor) -> torch.Tensor:
            moving = self.render(params, level)
            if moving.dim() == 3 and n_views == 1:
                moving = moving.unsqueeze(1)
            if moving.shape[1:] != fixed.shape:
                raise ValueError(
                    f"render returned {tuple(moving.shape)}, expected (P, {', '.join(map(str, fixed.shape))})"
                    f" at downsample {level.downsample}"
                )
            return moving.to(fixed.dtype)

        def cost_of(moving: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
            s = sim(moving)
            c = (s.sum(dim=1) if s.dim() == 2 else s).to(torch.float64)
            for prior in self.priors:
                c = c + prior(params).to(c)
            return c

        return render_images, cost_of

    def objective(self, level: LevelConfig) -> Objective:
        """The batched objective ``X (P, D) numpy -> (P,) numpy`` of one level."""
        render_images, cost_of = self.level_parts(level)

        def cost_torch(params: torch.Tensor) -> torch.Tensor:
            return cost_of(render_images(params), params)

        def objective(X: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                params = torch.as_tensor(X, dtype=torch.float64, device=self.device)
                step = self.chunk_size or params.shape[0]
                out = torch.cat([cost_torch(params[i : i + step]) for i in range(0, params.shape[0], step)])
            return out.cpu().numpy()

        return objective

    # ----- run ------------------------------------------------------------------------------------
    def _run_level(
        self,
        i: int,
        level: LevelConfig,
        x: np.ndarray,
        on_iteration: Callable[[int, IterationRecord], None] | None,
    ) -> tuple[LevelTrace, OptimizationResult]:
        """One level from ``x``: its trace and the optimiser's result."""
        if len(level.sigma) not in (1, x.size):
            raise ValueError(f"level {i} has {len(level.sigma)} sigmas for {x.size} parameters")
        if level.bounds is not None:
            x = np.clip(
                x,
                np.asarray(level.bounds[0], dtype=np.float64),
                np.asarray(level.bounds[1], dtype=np.float64),
            )
        if self.before_level is not None:
            self.before_level(i, level, x)  # e.g. calibrate the renderer at the current estimate
        lt = LevelTrace(index=i, name=level.name or f"level{i}", config=level.to_dict(), x_start=x.tolist())
        tl = time.perf_counter()
        cb = None if on_iteration is None else (lambda rec, i=i: on_iteration(i, rec))
        if level.optimizer == "linearized":
            res = LinearizedRefiner(
                level.sigma,
                fd_step_sigma=level.fd_step_sigma,
                trust_sigma=level.trust_sigma,
                tolx=level.tolx,
                tolfun=level.tolfun,
                max_iters=level.max_iters,
                bounds=level.bounds,
            ).minimize(*self.level_parts(level), x, device=self.device, callback=cb)
        else:
            res = optimizer_for(level, seed=self.seed + i).minimize(self.objective(level), x, callback=cb)
        lt.iterations = res.history
        lt.x, lt.cost, lt.n_evals, lt.n_iters = res.x.tolist(), float(res.f), res.n_evals, res.n_iters
        lt.converged, lt.stop_reason, lt.n_nonfinite = res.converged, res.stop_reason, res.n_nonfinite
        lt.seconds = time.perf_counter() - tl
        logger.info(
            "level %d (%s): cost %.6g after %d evaluations, %s",
            i,
            lt.name,
            res.f,
            res.n_evals,
            res.stop_reason,
        )
        return lt, res

    def _continue(
        self,
        first: tuple[LevelTrace, OptimizationResult] | None,
        x: np.ndarray,
        trace: RegistrationTrace,
        on_iteration: Callable[[int, IterationRecord], None] | None,
    ) -> tuple[np.ndarray, float, bool, str]:
        """Run the levels into ``trace`` from ``x`` (or after an already run first level ``first``).
        Returns (x, cost, converged, reason)."""
        cost, converged, reason = float("nan"), False, ""
        for i, level in enumerate(self.levels):
            lt, res = first if (i == 0 and first is not None) else self._run_level(i, level, x, on_iteration)
            trace.levels.append(lt)
            cost, converged = float(res.f), res.converged
            if not np.isfinite(cost):  # the level's (bound-clipped) start is the result
                return np.asarray(lt.x_start, dtype=np.float64), cost, False, f"non-finite cost at level {i}"
            x = res.x
            reason = f"converged ({res.stop_reason})" if converged else f"not converged: {res.stop_reason}"
        return x, cost, converged, reason

    def run(
        self,
        x0: np.ndarray | Sequence[float],
        *,
        starts: Sequence[np.ndarray | Sequence[float]] = (),
        keep: int = 1,
        raise_on_failure: bool = False,
        on_iteration: Callable[[int, IterationRecord], None] | None = None,
    ) -> RegistrationResult:
        """Run every level from ``x0`` (D,), warm-starting each from the previous best.

        ``starts``: more (D,) starts for the first level (multi-start): the first level runs from
        ``x0`` and from each of them; the ``keep`` runs with the lowest finite first-level costs go on
        through the other levels, and the one with the lowest final cost is the result (a coarse
        first level may not tell the basins apart as well as the last). The first-level runs not
        continued and the levels of the continued runs not chosen are kept in ``trace.screened``.

        Raises:
            RegistrationFailure: when ``raise_on_failure`` and the result is not a success.
        """
        t0 = time.perf_counter()
        x = np.asarray(x0, dtype=np.float64).reshape(-1)
        names = self.parameter_names or [f"p{i}" for i in range(x.size)]
        trace = RegistrationTrace(parameter_names=list(names))
        if len(starts) == 0:
            x, cost, converged, reason = self._continue(None, x, trace, on_iteration)
        else:
            firsts = [
                self._run_level(0, self.levels[0], np.asarray(s, dtype=np.float64).reshape(-1), on_iteration)
                for s in [x, *starts]
            ]
            first_costs = [float(r.f) if np.isfinite(r.f) else math.inf for _, r in firsts]
            order = [int(k) for k in np.argsort(first_costs, kind="stable")]
            kept = [k for k in order[: max(1, keep)] if math.isfinite(first_costs[k])] or order[:1]
            finished = []
            for k in kept:
                tr = RegistrationTrace(parameter_names=list(names))
                x_k = np.asarray(firsts[k][0].x_start, dtype=np.float64)
                finished.append((k, tr, *self._continue(firsts[k], x_k, tr, on_iteration)))
            final = [c if math.isfinite(c) else math.inf for _, _, _, c, _, _ in finished]
            j = int(np.argmin(final))
            k, best_trace, x, cost, converged, reason = finished[j]
            trace.levels = best_trace.levels
            trace.screened = [firsts[i][0] for i in order if i not in kept] + [
                lt for jj, f in enumerate(finished) if jj != j for lt in f[1].levels
            ]
            logger.info(
                "multi-start: first-level costs %s, continued %s, final costs %s, result from start %d",
                np.round(first_costs, 6).tolist(),
                kept,
                np.round(final, 6).tolist(),
                k,
            )
        success = converged and np.isfinite(cost)
        result = RegistrationResult(
            params=np.asarray(x, dtype=np.float64).copy(),
            cost=cost,
            converged=converged,
            success=bool(success),
            reason=reason,
            trace=trace,
            seconds=time.perf_counter() - t0,
        )
        if raise_on_failure and not success:
            raise RegistrationFailure(reason)
        return result
