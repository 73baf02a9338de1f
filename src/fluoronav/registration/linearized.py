"""Local refinement on the linearised DRR (a Gauss–Newton-type level behind the optimiser interface).

Near the optimum a few image Jacobians replace hundreds of CMA-ES samples. Each outer iteration renders, in
one batch, ``x`` and ``x + h_k e_k`` for every parameter ``k`` (``h_k = fd_step_sigma · σ_k``): the moving
images ``I(x)`` and their forward-difference Jacobian ``J_k``. The step ``δ`` lowers the cost of the linear
model ``S(I(x) + Σ_k δ_k J_k) + priors(x + δ)`` (a quadratic fit of its cost, damped Newton directions and a
line search, all from batched similarity evaluations, no render) within a trust region of ``trust_sigma · σ``
per parameter. ``x + δ`` is rendered: the step is kept when the true cost went down, else the region halves
and the step is solved again. It stops when a step gains less than ``tolfun``, after ``max_iters`` accepted
steps, or when the model sees no better point even in a region of ``tolx / 0.1``. One outer iteration costs
``D + 1`` renders (docs/registration.md, "Bones: CMA-ES to find the basin, the linearised DRR to finish").
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np
import torch

from fluoronav.registration.optimizer import IterationRecord, OptimizationResult

__all__ = ["LinearizedRefiner"]

#: the quadratic fits of the linear model sample it at this fraction of the trust radius (the linear
#: image model holds for sub-pixel motions)
_FIT_STEP = 0.1
#: fit-and-step rounds on one linear model
_ROUNDS = 1
#: lengths, in units of the Newton step, tried along each direction
_LENGTHS = (0.5, 1.0, 2.0, 4.0)

#: linear-model candidates per similarity call
_MODEL_BATCH = 16

logger = logging.getLogger(__name__)

RenderImages = Callable[[torch.Tensor], torch.Tensor]
"""``params (P, D) float64 -> moving images (P, V, h, w)``."""
CostOfImages = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""``(moving (P, V, h, w), params (P, D)) -> (P,)`` float64 cost, differentiable in both."""


class LinearizedRefiner:
    """Trust-region refinement on the forward-difference image Jacobian.

    Args:
        sigma: (D,) or (1,) parameter scales (the level's σ), parameter units.
        fd_step_sigma: forward-difference step as a fraction of σ.
        trust_sigma: initial trust region (largest step per parameter) as a multiple of σ.
        tolx: stop when every component of a step is below this (parameter units).
        tolfun: stop when an accepted step lowers the cost by less than this.
        max_iters: most accepted steps (default 8).
        bounds: optional absolute (lower, upper) parameter bounds; steps are clipped to them.
    """

    def __init__(
        self,
        sigma: tuple[float, ...],
        *,
        fd_step_sigma: float = 0.1,
        trust_sigma: float = 2.0,
        tolx: float = 0.01,
        tolfun: float = 1e-5,
        max_iters: int | None = None,
        bounds: tuple[tuple[float, ...], tuple[float, ...]] | None = None,
    ) -> None:
        if fd_step_sigma <= 0 or trust_sigma <= 0:
            raise ValueError("fd_step_sigma and trust_sigma must be positive")
        self.sigma = np.asarray(sigma, np.float64)
        self.fd_step_sigma = float(fd_step_sigma)
        self.trust_sigma = float(trust_sigma)
        self.tolx = float(tolx)
        self.tolfun = float(tolfun)
        self.max_iters = 8 if max_iters is None else int(max_iters)
        self.bounds = bounds

    def _model_costs(
        self, I0: torch.Tensor, J: torch.Tensor, x: torch.Tensor, cost_of: CostOfImages, deltas: np.ndarray
    ) -> np.ndarray:
        """Costs of the linear model at steps ``deltas`` (N, D), in batches of the population."""
        J2 = J.reshape(J.shape[0], -1)
        d = torch.as_tensor(deltas, dtype=torch.float64, device=x.device)
        out = []
        with torch.no_grad():
            for i in range(0, d.shape[0], _MODEL_BATCH):
                di = d[i : i + _MODEL_BATCH]
                moving = (I0.reshape(1, -1) + di.to(J2.dtype) @ J2).reshape(di.shape[0], *I0.shape)
                out.append(cost_of(moving, x[None] + di).cpu().numpy())
        return np.concatenate(out)

    def _solve(
        self,
        I0: torch.Tensor,
        J: torch.Tensor,
        x: torch.Tensor,
        cost_of: CostOfImages,
        radius: np.ndarray,
    ) -> np.ndarray:
        """δ (D,) reducing the linear model's cost within ±radius.

        ``_ROUNDS`` rounds of: a quadratic fit of the model's cost about the current step from
        1 + 2D + D(D−1)/2 batched evaluations (central differences for the gradient and the
        diagonal, one corner per pair for the rest of the Hessian), then Levenberg-damped Newton
        directions and steepest descent tried at several lengths (the model's cost is far from
        quadratic: NCC normalises), all in one batch; the best lowers the model's cost or the
        rounds end.
        """
        D = radius.size
        s = _FIT_STEP * radius
        E = np.diag(s)
        pairs = [(k, m) for k in range(D) for m in range(k + 1, D)]
        delta = np.zeros(D)
        f_cur = float("nan")
        for _ in range(_ROUNDS):
            pts = [delta, *(delta + E), *(delta - E), *(delta + E[k] + E[m] for k, m in pairs)]
            f = self._model_costs(I0, J, x, cost_of, np.stack(pts))
            f0, fp, fm, fpair = f[0], f[1 : D + 1], f[D + 1 : 2 * D + 1], f[2 * D + 1 :]
            f_cur = float(f0)
            g = (fp - fm) / 2.0  # in units of s
            H = np.diag(fp - 2.0 * f0 + fm)
            for (k, m), v in zip(pairs, fpair, strict=True):
                H[k, m] = H[m, k] = v - fp[k] - fp[m] + f0
            scale = max(float(np.abs(np.diag(H)).max()), 1e-12)
            dirs = []
            for lam in (0.0, 1e-2, 1e-1, 1.0):
                try:
                    z = np.linalg.solve(H + lam * scale * np.eye(D), -g)
                except np.linalg.LinAlgError:
                    continue
                if np.all(np.isfinite(z)) and np.any(z) and float(z @ g) < 0:
                    dirs.append(z)
            if float(np.abs(g).max()) > 0:
                dirs.append(-g / float(np.abs(g).max()))  # steepest descent, unit max-norm
            cands = []
            for z in dirs:
                for length in _LENGTHS:
                    step = delta + length * z * s
                    # scaled as a whole into the trust region, keeping the direction
                    over = float(np.max(np.abs(step) / radius))
                    cands.append(step / over if over > 1.0 else step)
            if not cands:
                break
            C = np.stack(cands)
            fc = self._model_costs(I0, J, x, cost_of, C)
            best = int(np.argmin(fc))
            if not fc[best] < f_cur - 1e-12:
                break
            delta, f_cur = C[best], float(fc[best])
        return delta

    def minimize(
        self,
        render_images: RenderImages,
        cost_of: CostOfImages,
        x0: np.ndarray,
        *,
        device: torch.device,
        callback: Callable[[IterationRecord], None] | None = None,
    ) -> OptimizationResult:
        """Refine from ``x0`` (D,); the result's ``x`` is the best parameters evaluated."""
        t0 = time.perf_counter()
        D = x0.size
        sig = np.broadcast_to(self.sigma, (D,)).astype(np.float64)
        radius = self.trust_sigma * sig
        lo = hi = None
        if self.bounds is not None:
            lo, hi = np.asarray(self.bounds[0], np.float64), np.asarray(self.bounds[1], np.float64)
        renders = _Renders(render_images, cost_of, self.fd_step_sigma * sig, device)
        x = np.asarray(x0, np.float64).copy()
        history: list[IterationRecord] = []
        steps = 0
        stop = "maxiter"
        converged = False
        f, I0, J = renders.linearise(x)
        if not np.isfinite(f):
            return OptimizationResult(x, f, renders.n_evals, 0, False, "non-finite cost", history, 1)
        J_at: torch.Tensor | None = J
        while steps < self.max_iters:
            if J_at is None:  # made lazily: a step that ends the refinement needs none
                J_at = renders.columns(x, I0)
            xt = torch.as_tensor(x, dtype=torch.float64, device=device)
            delta = self._solve(I0, J_at, xt, cost_of, radius)
            if lo is not None and hi is not None:
                delta = np.clip(x + delta, lo, hi) - x
            if np.all(np.abs(delta) < self.tolx):
                # the model sees no better point at this scale: look closer (its fit steps
                # shrink with the region), until the region itself is below tolx
                if np.all(_FIT_STEP * radius < self.tolx):
                    stop, converged = "tolx", True
                    break
                radius = 0.5 * radius
                continue
            f_new, I_new = renders.trial(x + delta)
            if np.isfinite(f_new) and f_new < f:
                gain = f - f_new
                x, f, I0, J_at = x + delta, f_new, I_new, None
                steps += 1
                if gain < self.tolfun:
                    stop, converged = "tolfun", True
                if np.abs(delta / radius).max() > 0.9:  # a full step that worked: widen the region
                    radius = np.minimum(2.0 * radius, self.trust_sigma * sig * 4.0)
            else:
                radius = 0.5 * radius
                if np.all(radius < self.tolx):
                    stop, converged = "trust region below tolx", True
                    break
            rec = IterationRecord(
                iteration=len(history) + 1,
                best_cost=f,
                mean_cost=f_new,
                sigma=float(np.max(radius / sig)),
                best_params=tuple(float(v) for v in x),
                n_evals=renders.n_evals,
                elapsed_s=time.perf_counter() - t0,
            )
            history.append(rec)
            if callback is not None:
                callback(rec)
            if converged:
                break
        logger.debug("linearised refinement: cost %.6g after %d renders, %s", f, renders.n_evals, stop)
        return OptimizationResult(x, f, renders.n_evals, len(history), converged, stop, history, 0)


class _Renders:
    """The renders of a refinement and their count: the cost at a point, and the forward-difference
    Jacobian columns (steps ``h`` (D,), parameter units)."""

    def __init__(
        self, render_images: RenderImages, cost_of: CostOfImages, h: np.ndarray, device: torch.device
    ) -> None:
        self.render_images = render_images
        self.cost_of = cost_of
        self.h = h
        self.device = device
        self.n_evals = 0

    def linearise(self, at: np.ndarray) -> tuple[float, torch.Tensor, torch.Tensor]:
        """Cost, images and Jacobian at ``at``, in one batch of D + 1 renders."""
        D = self.h.size
        X = np.repeat(at[None], D + 1, axis=0)
        X[1:] += np.diag(self.h)
        params = torch.as_tensor(X, dtype=torch.float64, device=self.device)
        with torch.no_grad():
            moving = self.render_images(params)
            c = float(self.cost_of(moving[:1], params[:1])[0])
        self.n_evals += D + 1
        return c, moving[0], self._jacobian(moving[0], moving[1:])

    def _jacobian(self, I0: torch.Tensor, shifted: torch.Tensor) -> torch.Tensor:
        D = self.h.size
        return (shifted - I0) / torch.as_tensor(self.h, dtype=shifted.dtype, device=shifted.device).reshape(
            D, *([1] * I0.dim())
        )

    def trial(self, at: np.ndarray) -> tuple[float, torch.Tensor]:
        """Cost and images at ``at`` (one render)."""
        params = torch.as_tensor(at[None], dtype=torch.float64, device=self.device)
        with torch.no_grad():
            moving = self.render_images(params)
            c = float(self.cost_of(moving, params)[0])
        self.n_evals += 1
        return c, moving[0]

    def columns(self, at: np.ndarray, I_at: torch.Tensor) -> torch.Tensor:
        """The Jacobian at ``at`` whose images ``I_at`` are rendered already (D renders)."""
        # the Jacobian's D renders only where the next step starts: a rejected trial costs one
        # render, the last accepted one none
        D = self.h.size
        X = np.repeat(at[None], D, axis=0) + np.diag(self.h)
        with torch.no_grad():
            shifted = self.render_images(torch.as_tensor(X, dtype=torch.float64, device=self.device))
        self.n_evals += D
        return self._jacobian(I_at, shifted)
