"""Settings of the bone registrations: levels (:class:`BoneLevel`), :class:`BoneRegistrationConfig`
and the presets of the pelvis and the femur, as data.

Every level renders the whole CMA-ES population and all views in one call of a box-downsampled copy of
the cropped volume (``voxel_mm``) at a binned working image of about ``image_px`` pixels. The
presets run from ~96 px with 2 mm voxels to ~256 px with 1 mm voxels, with populations of 12–16 and
capped generations; the authors' presets (Gao et al., IEEE TBME 69(1), 2022, and the authors' code)
use their σ and population 50. Rotations and translations are in the first view's camera axes
(z = depth); degrees and mm.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from fluoronav.registration.levels import FEMUR_SIGMA, PELVIS_SIGMA, LevelConfig

__all__ = [
    "FEMUR_AUTHORS_PRESET",
    "FEMUR_LOCAL_PRESET",
    "FEMUR_MULTI_VIEW_PRESET",
    "FEMUR_ONE_VIEW_PRESET",
    "FEMUR_TILT_STARTS",
    "FEMUR_TILT_START_DEG",
    "PELVIS_AUTHORS_PRESET",
    "PELVIS_CMAES_PRESET",
    "PELVIS_LINEARIZED_PRESET",
    "PELVIS_PRESET",
    "PELVIS_REFINE_PRESET",
    "BoneLevel",
    "BoneRegistrationConfig",
    "femur_config",
    "pelvis_config",
]


@dataclass(frozen=True)
class BoneLevel:
    """One registration level.

    Attributes:
        optimizer: CMA-ES settings (σ, population, tolerances, generation cap, patch stride and
            smoothing; its ``downsample`` and ``patch_radius`` are not used).
        image_px: target working image side; the image is binned by ``round(cols / image_px)``.
        voxel_mm: voxel size of the rendered volume (box-downsampled by an integer factor ≥ 1).
        patch_radius_px: patch-NCC radius in working pixels; None → xReg's rule, round(41 / s) with
            s the working pixel size over the 0.194 mm CIOS Fusion pixel.
    """

    optimizer: LevelConfig
    image_px: int = 96
    voxel_mm: float = 2.0
    patch_radius_px: int | None = None


@dataclass(frozen=True)
class BoneRegistrationConfig:
    """Levels run in order, each warm-started from the previous.

    Attributes:
        levels: the levels, coarse to fine.
        device: torch device of the renderer and the similarity.
        starts: more first-level starts in the parameters' units (deg, mm) relative to the initial
            pose (multi-start: the first level runs from the initial pose and from each, the
            ``keep`` lowest go on through all levels and the lowest final cost wins; see
            :meth:`Registration.run`).
        keep: how many of the first level's starts go on through all levels.
        skip_empty: the renderer skips the bone volume's empty space (the same DRRs, faster).
    """

    levels: tuple[BoneLevel, ...]
    device: str = "cpu"
    starts: tuple[tuple[float, ...], ...] = ()
    keep: int = 1
    skip_empty: bool = True


# ----- pelvis (6 DoF: rotation about the pelvis centre, translation) ---------------------------------
#: The CMA-ES ladder (the default, :data:`PELVIS_PRESET`): for an initial error of a few degrees /
#: ~10 mm as in the authors' protocol, σ 5° / 10, 10, 20 mm, population 16, ≤ 40 generations at
#: ~96 px (patch radius 10 px), then σ 1° / 2, 2, 4 mm at ~128 px, then σ 0.5° / 1, 1, 2 mm at ~256 px
#: with 1 mm voxels (population 12, ≤ 30 generations each). The third level resolves the pelvis
#: centre's depth, which ~128 px leaves open (docs/validation.md). With ``skip_empty=False`` it is
#: the reference of :mod:`fluoronav.bench.navigation`.
PELVIS_CMAES_PRESET = BoneRegistrationConfig(
    levels=(
        BoneLevel(
            LevelConfig(
                sigma=(5.0, 5.0, 5.0, 10.0, 10.0, 20.0),
                popsize=16,
                max_iters=40,
                smooth_sigma_px=2.0,
                name="pelvis-coarse",
            ),
            image_px=96,
            voxel_mm=2.0,
            patch_radius_px=10,
        ),
        BoneLevel(
            LevelConfig(sigma=(1.0, 1.0, 1.0, 2.0, 2.0, 4.0), popsize=12, max_iters=30, name="pelvis-fine"),
            image_px=128,
            voxel_mm=2.0,
        ),
        BoneLevel(
            LevelConfig(sigma=(0.5, 0.5, 0.5, 1.0, 1.0, 2.0), popsize=12, max_iters=30, name="pelvis-finest"),
            image_px=256,
            voxel_mm=1.0,
        ),
    ),
)

#: The pelvis preset of :func:`pelvis_config` and the navigation pipeline.
PELVIS_PRESET = PELVIS_CMAES_PRESET

#: CMA-ES finds the basin (σ 5° / 10, 10, 20 mm, population 12, ≤ 25 generations at ~96 px), then
#: the linearised refinement (:mod:`~fluoronav.registration.linearized`, ≤ 8 steps of 7 renders each)
#: at ~128 px / 2 mm and ~256 px / 1 mm, where CMA-ES spent 720 renders: about the accuracy of
#: :data:`PELVIS_CMAES_PRESET` at ~400 renders instead of 1,360 (docs/validation.md). The navigation
#: pipeline's pelvis (``NavigationConfig.views.pelvis``).
PELVIS_LINEARIZED_PRESET = BoneRegistrationConfig(
    levels=(
        BoneLevel(
            LevelConfig(
                sigma=(5.0, 5.0, 5.0, 10.0, 10.0, 20.0),
                popsize=12,
                max_iters=25,
                smooth_sigma_px=2.0,
                name="pelvis-coarse",
            ),
            image_px=96,
            voxel_mm=2.0,
            patch_radius_px=10,
        ),
        BoneLevel(
            LevelConfig(
                sigma=(1.0, 1.0, 1.0, 2.0, 2.0, 4.0),
                optimizer="linearized",
                max_iters=8,
                tolfun=1e-5,
                name="pelvis-fine",
            ),
            image_px=128,
            voxel_mm=2.0,
        ),
        BoneLevel(
            LevelConfig(
                sigma=(0.5, 0.5, 0.5, 1.0, 1.0, 2.0),
                optimizer="linearized",
                max_iters=8,
                tolfun=1e-5,
                name="pelvis-finest",
            ),
            image_px=256,
            voxel_mm=1.0,
        ),
    )
)

#: The linearised levels of :data:`PELVIS_LINEARIZED_PRESET` alone: a refinement from a pose already
#: within ~1 mm / 1° (the navigation's verification views, registered again with the femur left out,
#: or started from a registered view moved by the C-arm's known motion). The ~256 px level matters
#: there: with the ~128 px level alone, cameras from the C-arm's motion were left a few tenths of a
#: millimetre off, and the verification's CM failed its checks in 2 more of 20 trials (docs/validation.md).
PELVIS_REFINE_PRESET = BoneRegistrationConfig(levels=PELVIS_LINEARIZED_PRESET.levels[1:])

#: The authors' coarse σ (30° ×3, 50/50/100 mm) and population 50 at ~96 px, then σ / 10 at ~128 px;
#: 2 mm voxels, no generation cap.
PELVIS_AUTHORS_PRESET = BoneRegistrationConfig(
    levels=(
        BoneLevel(
            LevelConfig(sigma=PELVIS_SIGMA, popsize=50, stride=1, name="pelvis-coarse"),
            image_px=96,
            voxel_mm=2.0,
        ),
        BoneLevel(
            LevelConfig(sigma=tuple(s / 10 for s in PELVIS_SIGMA), popsize=50, stride=1, name="pelvis-fine"),
            image_px=128,
            voxel_mm=2.0,
        ),
    )
)


# ----- femur (3 DoF: rotation about the femoral head) -------------------------------------------------
#: tilt of the femur's one-view start grid about the camera's x and y axes, degrees
FEMUR_TILT_START_DEG = 8.0
#: the 8 tilted starts of the one-view femur: a grid of ±``FEMUR_TILT_START_DEG`` about x and y
FEMUR_TILT_STARTS: tuple[tuple[float, ...], ...] = tuple(
    (a, b, 0.0)
    for a in (-FEMUR_TILT_START_DEG, 0.0, FEMUR_TILT_START_DEG)
    for b in (-FEMUR_TILT_START_DEG, 0.0, FEMUR_TILT_START_DEG)
    if (a, b) != (0.0, 0.0)
)

#: Several views: σ = 10°, 2°, 1° at ~96 px / 2 mm, ~128 px / 1 mm, ~256 px / 1 mm, population 16,
#: ≤ 50 / 30 / 50 generations.
FEMUR_MULTI_VIEW_PRESET = BoneRegistrationConfig(
    levels=(
        BoneLevel(
            LevelConfig(sigma=FEMUR_SIGMA, popsize=16, max_iters=50, name="femur-coarse"),
            image_px=96,
            voxel_mm=2.0,
        ),
        BoneLevel(
            LevelConfig(sigma=tuple(s / 5 for s in FEMUR_SIGMA), popsize=16, max_iters=30, name="femur-fine"),
            image_px=128,
            voxel_mm=1.0,
        ),
        BoneLevel(
            LevelConfig(sigma=(1.0, 1.0, 1.0), popsize=16, max_iters=50, name="femur-finest"),
            image_px=256,
            voxel_mm=1.0,
        ),
    )
)

#: One view hardly tells a femur tilted towards the source from one tilted away, and the out-of-plane
#: rotation (the entry point's depth) shows at ~256 px, hardly at 128 or 96; a σ = 10° level can run
#: from every start into a minimum far off (docs/validation.md). So the first level (~128 px / 1 mm,
#: σ = 3°, population 12, ≤ 30 generations) is local and runs from 9 starts (the initial pose and
#: :data:`FEMUR_TILT_STARTS`); the best 3 are finished at ~256 px / 1 mm (σ = 1.5°, population 16,
#: ≤ 40 generations) and the lowest final cost wins.
FEMUR_ONE_VIEW_PRESET = BoneRegistrationConfig(
    levels=(
        BoneLevel(
            LevelConfig(sigma=(3.0, 3.0, 3.0), popsize=12, max_iters=30, name="femur-tilt-grid"),
            image_px=128,
            voxel_mm=1.0,
        ),
        BoneLevel(
            LevelConfig(sigma=(1.5, 1.5, 1.5), popsize=16, max_iters=40, name="femur-fine"),
            image_px=256,
            voxel_mm=1.0,
        ),
    ),
    starts=FEMUR_TILT_STARTS,
    keep=3,
)

#: A femur already within a degree or so (the navigation's verification, from the first
#: registration's femur): the linearised refinement (≤ 8 steps of 4 renders) at ~256 px / 1 mm,
#: where the out-of-plane rotation shows, instead of two CMA-ES levels.
FEMUR_LOCAL_PRESET = BoneRegistrationConfig(
    levels=(
        BoneLevel(
            LevelConfig(
                sigma=(1.0, 1.0, 1.0), optimizer="linearized", max_iters=8, tolfun=1e-5, name="femur-local"
            ),
            image_px=256,
            voxel_mm=1.0,
        ),
    )
)

#: The authors' σ = 10° and population 50 at ~96 px / 2 mm voxels, then σ = 2° at ~128 px / 1 mm, no
#: generation cap.
FEMUR_AUTHORS_PRESET = BoneRegistrationConfig(
    levels=(
        BoneLevel(LevelConfig(sigma=FEMUR_SIGMA, popsize=50, name="femur-coarse"), image_px=96, voxel_mm=2.0),
        BoneLevel(
            LevelConfig(sigma=tuple(s / 5 for s in FEMUR_SIGMA), popsize=50, name="femur-fine"),
            image_px=128,
            voxel_mm=1.0,
        ),
    )
)


def pelvis_config(*, authors: bool = False, device: str = "cpu") -> BoneRegistrationConfig:
    """The pelvis preset on ``device``: :data:`PELVIS_PRESET`, or with ``authors``
    :data:`PELVIS_AUTHORS_PRESET`."""
    return replace(PELVIS_AUTHORS_PRESET if authors else PELVIS_PRESET, device=device)


def femur_config(*, authors: bool = False, device: str = "cpu", views: int = 1) -> BoneRegistrationConfig:
    """The femur preset for ``views`` views on ``device``: :data:`FEMUR_ONE_VIEW_PRESET` for one view,
    :data:`FEMUR_MULTI_VIEW_PRESET` for several, or with ``authors`` :data:`FEMUR_AUTHORS_PRESET`."""
    if authors:
        preset = FEMUR_AUTHORS_PRESET
    else:
        preset = FEMUR_MULTI_VIEW_PRESET if views > 1 else FEMUR_ONE_VIEW_PRESET
    return replace(preset, device=device)
