"""Per-level registration settings and the authors' presets (Gao et al., IEEE TBME 69(1), 2022, and
the authors' code).

Resolution convention: ``downsample`` is the integer binning factor of the working image (4 means a
quarter of the rows and columns). xReg's "downsampling factor" is the *scale* ``1 / downsample``
(0.25 for 4×), so the authors' "patch radius = round(41 × downsampling factor)" becomes
``round(41 / downsample)`` here: 41 px at full resolution, 10 px at 4× (41 × 0.25 = 10.25). Rounding
is half away from zero, as C++ ``std::round`` (Python's ``round`` would give 20 for 20.5).
Likewise "landmark σ = 100 px × downsampling factor" is ``100 / downsample`` px at the working
resolution, i.e. 100 px at full resolution.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Literal

__all__ = [
    "CM_SIGMA",
    "FEMUR_SIGMA",
    "PELVIS_SIGMA",
    "LevelConfig",
    "cm_levels",
    "femur_levels",
    "patch_radius_for",
    "pelvis_levels",
]

# Authors' CMA-ES initial σ per parameter (deg for rotations and control points, mm for translations)
CM_SIGMA = (2.0, 2.0, 2.0, 5.0, 5.0, 5.0, 1.5, 1.5, 1.5, 1.5, 1.5)
PELVIS_SIGMA = (30.0, 30.0, 30.0, 50.0, 50.0, 100.0)
FEMUR_SIGMA = (10.0, 10.0, 10.0)


def patch_radius_for(downsample: int, full_resolution_radius: float = 41.0) -> int:
    """Patch radius in working pixels: round-half-away(41 × (1 / downsample)), at least 1."""
    return max(1, math.floor(full_resolution_radius / downsample + 0.5))


@dataclass(frozen=True)
class LevelConfig:
    """Settings of one registration level.

    Attributes:
        sigma: initial per-parameter step (CMA-ES std, Nelder-Mead simplex size), parameter units.
        downsample: integer binning factor of the images at this level (1 = full resolution).
        patch_radius: patch-NCC radius in working pixels; None → :func:`patch_radius_for`.
        stride: patch-centre spacing in working pixels (authors: 1 for bone, 5 for the CM).
        smooth_sigma_px: Gaussian σ before the Sobel filters, working pixels.
        popsize: CMA-ES population (authors: 50).
        tolx, tolfun: stopping tolerances (authors: 0.01).
        max_iters, max_evals: optimiser budgets (None: optimiser defaults / unlimited).
        landmark_sigma_full_px: landmark prior σ in full-resolution pixels (authors: 100).
        optimizer: "cmaes", "nelder-mead" (local refinement) or "linearized" (trust-region steps
            on the forward-difference image Jacobian, :mod:`~fluoronav.registration.linearized`;
            ``max_iters`` counts its accepted steps).
        fd_step_sigma, trust_sigma: the "linearized" optimiser's difference step and initial trust
            region, as multiples of ``sigma``.
        restarts: IPOP restarts when CMA-ES does not converge.
        bounds: optional absolute (lower, upper) parameter bounds.
        similarity_backend: the patch gradient NCC's backend (:class:`PatchGradNCC`): ``"auto"``
            (the fused numba kernel on the CPU) or ``"torch"`` (always the torch ops; the
            benchmarks' reference).
        name: label for traces.
    """

    sigma: tuple[float, ...]
    downsample: int = 1
    patch_radius: int | None = None
    stride: int = 1
    smooth_sigma_px: float = 1.0
    popsize: int = 50
    tolx: float = 0.01
    tolfun: float = 0.01
    max_iters: int | None = None
    max_evals: int | None = None
    landmark_sigma_full_px: float = 100.0
    optimizer: Literal["cmaes", "nelder-mead", "linearized"] = "cmaes"
    fd_step_sigma: float = 0.1
    trust_sigma: float = 2.0
    restarts: int = 0
    bounds: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    similarity_backend: Literal["auto", "torch"] = "auto"
    name: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        if int(self.downsample) != self.downsample or self.downsample < 1:
            raise ValueError(f"downsample must be a positive integer, got {self.downsample}")
        if self.patch_radius is None:
            object.__setattr__(self, "patch_radius", patch_radius_for(int(self.downsample)))
        if self.stride < 1 or (self.patch_radius is not None and self.patch_radius < 0):
            raise ValueError("stride must be ≥ 1 and patch_radius ≥ 0")
        if self.optimizer not in ("cmaes", "nelder-mead", "linearized"):
            raise ValueError(f"unknown optimizer {self.optimizer!r}")
        if any(s <= 0 for s in self.sigma):
            raise ValueError("sigma entries must be positive")
        object.__setattr__(self, "sigma", tuple(float(s) for s in self.sigma))

    @property
    def radius(self) -> int:
        """The patch radius as an int (always set after construction)."""
        assert self.patch_radius is not None
        return int(self.patch_radius)

    @property
    def scale(self) -> float:
        """xReg's downsampling factor (image scale), ``1 / downsample``."""
        return 1.0 / self.downsample

    @property
    def landmark_sigma_px(self) -> float:
        """Landmark σ in working pixels: 100 px × scale for the authors' setting."""
        return self.landmark_sigma_full_px * self.scale

    def with_(self, **changes: Any) -> LevelConfig:
        """Copy with changes (``patch_radius`` is recomputed when ``downsample`` changes alone)."""
        if "downsample" in changes and "patch_radius" not in changes:
            changes["patch_radius"] = None
        return replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def cm_levels(*, downsample: int = 4, popsize: int = 50) -> list[LevelConfig]:
    """Authors' CM level: 500×500 ROI at 4×, stride 5, σ 2°/5 mm/1.5°, tolerances 0.01."""
    return [LevelConfig(sigma=CM_SIGMA, downsample=downsample, stride=5, popsize=popsize, name="cm")]


def pelvis_levels(*, popsize: int = 50) -> list[LevelConfig]:
    """Pelvis: coarse level with the authors' σ (30°×3, 50/50/100 mm), then a finer level.

    The paper gives only "then a finer level"; the coarse level at 8× and the fine one at 4× with σ
    divided by 10 are our choice.
    """
    coarse = LevelConfig(sigma=PELVIS_SIGMA, downsample=8, stride=1, popsize=popsize, name="pelvis-coarse")
    fine = LevelConfig(
        sigma=tuple(s / 10.0 for s in PELVIS_SIGMA),
        downsample=4,
        stride=1,
        popsize=popsize,
        name="pelvis-fine",
    )
    return [coarse, fine]


def femur_levels(*, downsample: int = 4, popsize: int = 50) -> list[LevelConfig]:
    """Femur: rotation about the femoral head only, σ = 10°, stride 1 (resolution: our choice, 4×)."""
    return [LevelConfig(sigma=FEMUR_SIGMA, downsample=downsample, stride=1, popsize=popsize, name="femur")]
