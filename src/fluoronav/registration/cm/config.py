"""Settings of the CM registration (:func:`~fluoronav.registration.cm.register_cm`): its levels and
:class:`CMRegistrationConfig` (Gao et al., IEEE TBME 69(1), 2022, sec. II-C; the authors' code)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Literal

from fluoronav.manipulator.config import CMConfig
from fluoronav.registration.levels import CM_SIGMA, LevelConfig

__all__ = [
    "CM_COARSE_LEVEL",
    "CM_FINE_LEVEL",
    "CM_FINE_LINEARIZED_LEVEL",
    "CM_LOCAL_LEVEL",
    "DEFAULT_CM_MU_PER_MM",
    "FBG_TOLERANCE_SIGMAS",
    "CMRegistrationConfig",
    "default_cm_levels",
    "fbg_shape_prior",
    "local_cm_levels",
]

#: μ of the CM material for the analytic DRR, 1/mm: nitinol is 0.76/mm at 60 keV and 0.52/mm at
#: 70 keV (xraylib); 0.6 sits between, consistent with μ_water = 0.02/mm of ``hu_to_mu`` (≈ 60 keV).
#: It only matters relative to a background DRR (the similarity is invariant to a global scale).
DEFAULT_CM_MU_PER_MM = 0.6

#: the authors' CMA-ES level at 4× (σ 2°/5 mm/1.5°, stride 5, population 50, tolx 0.01) with tolfun
#: 1e-3 instead of 0.01 (the cost changes by only ~0.002 per mm of depth at 4×: 0.01 stops before the
#: depth is resolved)
CM_COARSE_LEVEL = LevelConfig(sigma=CM_SIGMA, downsample=4, stride=5, popsize=50, tolfun=1e-3, name="cm-4x")
#: a local CMA-ES level at 2× (σ / 4, population 20, tolfun 1e-4), where depth is ~3× better resolved
#: (our choice, see docs/registration.md)
CM_FINE_LEVEL = LevelConfig(
    sigma=tuple(s / 4.0 for s in CM_SIGMA),
    downsample=2,
    stride=5,
    popsize=20,
    tolfun=1e-4,
    name="cm-2x",
)

#: :data:`CM_FINE_LEVEL` with the linearised refinement (:mod:`~fluoronav.registration.linearized`,
#: ≤ 8 steps of 12 renders) instead of CMA-ES: the default of the multi-view workflow
#: (:meth:`CMRegistrationConfig.levels_for`): with several views about as accurate in less than half
#: the time. Not for one view (nor multiple-CM, one camera): there the depth changes the cost too
#: little for its stopping rule (docs/validation.md).
CM_FINE_LINEARIZED_LEVEL = CM_FINE_LEVEL.with_(optimizer="linearized", max_iters=8, tolfun=1e-5)


#: a local CMA-ES level at 4× from a start within a few mm (the robot's kinematics after a move):
#: σ a quarter of :data:`CM_COARSE_LEVEL`'s, population 20, ≤ 30 generations
CM_LOCAL_LEVEL = CM_COARSE_LEVEL.with_(
    sigma=tuple(s / 4.0 for s in CM_SIGMA), popsize=20, max_iters=30, name="cm-4x-local"
)


def local_cm_levels(n_views: int) -> tuple[LevelConfig, ...]:
    """CM levels from a start within a few mm and degrees: :data:`CM_LOCAL_LEVEL`, then the 2×
    level (linearised with several views, CMA-ES with one: :data:`CM_FINE_LINEARIZED_LEVEL`)."""
    return (CM_LOCAL_LEVEL, CM_FINE_LINEARIZED_LEVEL if n_views > 1 else CM_FINE_LEVEL)


def default_cm_levels(
    *, popsize: int = CM_COARSE_LEVEL.popsize, refine: bool = True, linearized: bool = False
) -> tuple[LevelConfig, ...]:
    """CM levels: :data:`CM_COARSE_LEVEL` with population ``popsize``, then with ``refine``
    :data:`CM_FINE_LEVEL` (:data:`CM_FINE_LINEARIZED_LEVEL` with ``linearized``)."""
    coarse = CM_COARSE_LEVEL.with_(popsize=popsize)
    fine = CM_FINE_LINEARIZED_LEVEL if linearized else CM_FINE_LEVEL
    return (coarse, fine) if refine else (coarse,)


@dataclass(frozen=True)
class CMRegistrationConfig:
    """Settings of :func:`register_cm`.

    Attributes:
        levels: registration levels; ``downsample`` is counted in full-detector pixels (4 = the
            authors' 4× of a 1536² image), whatever the binning of the input images; a level finer
            than the coarsest image binning is skipped (e.g. the 2× level for 384² CIOS images).
            None: the workflow's default (:meth:`levels_for`).
        roi_size_full_px: side of the square crop around the landmarks, full-detector pixels.
        landmark_sigma_full_px: landmark prior σ in full-detector pixels (authors: 100); None
            disables the prior.
        control_point_sigma_deg, control_point_tolerance_deg: prior of the control points around
            their initial values (the FBG reading): free within ± tolerance, Gaussian walls of σ
            beyond (:func:`~fluoronav.registration.priors.gaussian_parameter_prior`); σ None disables
            it (the authors have none). Why a flat bottom: a plain Gaussian holds the notch angles
            at the FBG error, and without any prior the base rotation trades against the shape
            (docs/validation.md). The tolerance is the FBG accuracy with a margin (the simulated
            reading is within ±0.5°).
        control_point_step_sigmas: every level's step of the control points (CMA-ES σ, the
            linearised optimiser's scale) is at most the prior's tolerance plus this many of its σ.
            Why: a step far wider than a tight prior (an FBG reading stated to 0.1°) spends the
            population on candidates the prior rules out, and the prior's cost then ranks them
            rather than the images (docs/validation.md). The default prior's 1° + 2 × 0.25° leaves
            the levels' steps as they are.
        single_view_control_point_sigma_deg: one view without a measured response (a single
            level, e.g. 384² images, or ``response="linear"``): a plain Gaussian of this σ instead of
            the flat-bottomed prior; there one view does not tell depth from shape. With the
            measured response the flat prior is used in every workflow (docs/validation.md).
        use_background: add the views' background DRRs (when given) to the CM DRR.
        cm_mu_per_mm: attenuation of the CM in the DRR (matters only relative to a background).
        cm_config: CM geometry.
        shaft_length_mm: length of the rigid tube the CM is mounted on, rendered as a longer base
            (:func:`~fluoronav.manipulator.config.with_shaft`): it shows in the images and pins the
            base's direction down; 0 for a bare CM. The simulator's default is the same 50 mm.
        max_rotation_deg, max_translation_mm: search box of the pose around each start (per
            parameter: rotation-vector components, translation components; None: unbounded). A
            result on the box's edge is reported as a failure (``success`` False): the optimiser
            left the region it was started in, typically pulled by a wrong landmark.
        response: ``"measured"``: before every level after the first, each view's response to the
            CM (:mod:`~fluoronav.rendering.response`: gain and veil, from scatter, glare and beam
            hardening) is fitted on the CM's shaft at the current estimate
            (:func:`~fluoronav.detection.tube_profile.fit_tube_profile`, the shaft's scale known
            from the pose) and applied to the DRR; a view whose fit fails stays linear.
            ``"linear"``: the plain DRR throughout. Why: against physics-simulated images the linear
            DRR puts single-view depth nearer the source (the image's compressed profile matches a
            larger CM); docs/registration.md, docs/validation.md.
        response_shaft_span: the stretch of the shaft whose profiles are fitted for the response,
            as fractions of ``shaft_length_mm`` behind A.
        response_profiles: number of profiles fitted along that stretch.
        chunk_size: render at most this many candidates per call (None: the whole population).
        row_spans: the CM renderer evaluates each row of a link's box only across the link's
            projected footprint (:class:`~fluoronav.rendering.cm.CMRenderer`; False: the whole box,
            the benchmark's reference; the same images).
        device: torch device of rendering and similarity.
    """

    levels: tuple[LevelConfig, ...] | None = None
    roi_size_full_px: int = 500
    landmark_sigma_full_px: float | None = 100.0
    control_point_sigma_deg: float | None = 0.25
    control_point_tolerance_deg: float = 1.0
    control_point_step_sigmas: float = 2.0
    single_view_control_point_sigma_deg: float | None = 1.0
    use_background: bool = True
    cm_mu_per_mm: float = DEFAULT_CM_MU_PER_MM
    cm_config: CMConfig = field(default_factory=CMConfig)
    shaft_length_mm: float = 50.0
    max_rotation_deg: float | None = 45.0
    max_translation_mm: float | None = 50.0
    response: Literal["linear", "measured"] = "measured"
    response_shaft_span: tuple[float, float] = (0.1, 0.9)
    response_profiles: int = 40
    chunk_size: int | None = None
    row_spans: bool = True
    device: str = "cpu"

    def levels_for(self, workflow: str) -> tuple[LevelConfig, ...]:
        """The levels of a workflow ("single-view", "multi-view", "multi-cm"): ``levels``, or by
        default :func:`default_cm_levels`, finished by the linearised refinement in the multi-view
        workflow (:data:`CM_FINE_LINEARIZED_LEVEL`)."""
        if self.levels is not None:
            return self.levels
        return default_cm_levels(linearized=workflow == "multi-view")

    def with_(self, **changes: Any) -> CMRegistrationConfig:
        """Copy with changes."""
        return replace(self, **changes)


#: the shape is free within this many of the FBG reading's stated σ (about its 95 % interval), with
#: Gaussian walls of σ beyond: an FBG's error is partly a bias shared by every control point, which a
#: plain Gaussian of independent points holds the shape to, so the base tilts to make up for the
#: bias's bend over 27 notches (docs/validation.md, "The FBG reading")
FBG_TOLERANCE_SIGMAS = 2.0


def fbg_shape_prior(cm: CMRegistrationConfig, fbg_sigma_deg: float | None) -> CMRegistrationConfig:
    """The CM registration with its shape held to the FBG reading as a measurement of stated accuracy
    σ: free within :data:`FBG_TOLERANCE_SIGMAS` σ of the reading, Gaussian walls of σ beyond; ``cm``
    itself where no σ is stated (its own prior: the paper's ±0.5° reading, free within ±1°).

    Notes:
        The shape's freedom is the reading's: a tight reading leaves the base's direction nothing
        to trade against, a loose one lets the images decide. A shape pulled beyond the reading's
        accuracy is refused
        (:attr:`~fluoronav.registration.cm.checks.CMCheckConfig.max_shape_departure_sigmas`).
    """
    if fbg_sigma_deg is None:
        return cm
    sigma = float(fbg_sigma_deg)
    return cm.with_(control_point_sigma_deg=sigma, control_point_tolerance_deg=FBG_TOLERANCE_SIGMAS * sigma)
