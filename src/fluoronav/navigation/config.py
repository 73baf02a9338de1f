"""The navigation pipeline's settings as one tree: :class:`NavigationConfig`.

It contains the settings of each part rather than copies of their fields: the view-set
registration of the first images (``views``), the checks and bounds (``safety``, with the CM
registration's checks), the preflight and the verification. A site sets any of them from a TOML
file (:func:`~fluoronav.settings.load_settings`; ``fluoronav config show`` writes the defaults);
named settings files ship in ``fluoronav/data/settings`` (:func:`shipped_settings`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from importlib import resources
from typing import ClassVar

from fluoronav.navigation.checks.preflight_config import PreflightConfig
from fluoronav.navigation.checks.safety import SafetyConfig
from fluoronav.navigation.kinematic_prior import KinematicUncertainty
from fluoronav.registration.bone.presets import (
    PELVIS_LINEARIZED_PRESET,
    PELVIS_REFINE_PRESET,
    BoneRegistrationConfig,
)
from fluoronav.registration.cm.config import CMRegistrationConfig, default_cm_levels, fbg_shape_prior
from fluoronav.registration.view_set import ViewSetSettings
from fluoronav.settings import load_settings, setting

__all__ = [
    "NavigationConfig",
    "VerificationConfig",
    "navigation_cm_config",
    "shipped_settings",
]


def navigation_cm_config() -> CMRegistrationConfig:
    """The pipeline's CM registration settings from the images' own starts: both levels CMA-ES
    (:func:`default_cm_levels`; the settings of fluoronav 0.4.1 too).

    Why not the multi-view workflow's linearised 2× level: it finds the tip as well but not the
    base's direction, and the first move carries that over its length (docs/validation.md, "CM
    levels and priors"). The verification's registration from the kinematic prediction has its own
    local levels (:func:`~fluoronav.registration.cm.config.local_cm_levels`)."""
    return CMRegistrationConfig(levels=default_cm_levels())


def _navigation_views() -> ViewSetSettings:
    """The first images' view-set registration: the linearised pelvis, the pipeline's CM levels."""
    return ViewSetSettings(pelvis=PELVIS_LINEARIZED_PRESET, cm=navigation_cm_config())


@dataclass(frozen=True)
class VerificationConfig:
    """How the verification registers the images taken after the move.

    Attributes:
        fuse_kinematics: the CM is registered with the robot's kinematic prediction as a prior
            weighted by its stated uncertainty (``uncertainty``,
            :func:`~fluoronav.navigation.kinematic_prior.prediction_sigma_mm`) where the images'
            own landmarks agree with it; False: from the images alone, the prediction one start
            among theirs.
        uncertainty: the stated uncertainties of the robot, the hand-eye matrix and the first
            registration.
        local_bones: where every verification view says which first view its C-arm moved from
            and by how much (the C-arm's nominal motion), its camera starts there and the bones
            are registered with their local levels only (and not at all where no C-arm and no
            anatomy moved); where that verification refuses, it is registered again with the
            whole ladders (:func:`~fluoronav.navigation.verification.register_verification`).
            False: every view's bones with the whole ladders from the case's camera estimates.
        pelvis_refine: the verification views' second pelvis registration, from the first, with
            the femur (placed by the first registration) left out of the similarity; None: none (in
            views centred on the hip the femoral head pulled the pelvis 1.5–2 mm along the beam).
        cm: the verification's CM registration from the images' own starts (its ``device`` and
            ``cm_config`` are the pipeline's and the case's); from the kinematic prediction it
            has its own local levels (``NavigationConfig.views.fusion_cm_levels``).
        go_on_at_prediction: where the images show the CM at the kinematic prediction and a
            view's detection elsewhere (:mod:`~fluoronav.navigation.disagreement`) and the CM
            registered there passes every view's check, the verification goes on with that CM,
            with a warning naming the detection; False: it refuses (``detection_disagrees``).
        register_undetected: where the detector finds the CM in no verification view, the CM is
            registered from the kinematic prediction on the images alone, and its checks (each
            view's outline, the agreement with the prediction) decide, with a warning; where it
            fails them the refusal is ``views_with_cm``. False: refused at once (``views_with_cm``).
    """

    fuse_kinematics: bool = setting(
        True, "the CM registered with the robot's kinematic prediction as a prior"
    )
    uncertainty: KinematicUncertainty = setting(
        doc="stated uncertainties (1 sigma) of the kinematic prediction's parts",
        default_factory=KinematicUncertainty,
    )
    local_bones: bool = setting(True, "bones from the C-arm's nominal motion with their local levels only")
    pelvis_refine: BoneRegistrationConfig | None = setting(
        PELVIS_REFINE_PRESET, "each view's second pelvis registration with the femur left out; none: none"
    )
    cm: CMRegistrationConfig = setting(
        doc="the verification's CM registration from the images' own starts",
        default_factory=navigation_cm_config,
    )
    go_on_at_prediction: bool = setting(
        True, "where the images show the CM at the prediction and a detection elsewhere, go on with it"
    )
    register_undetected: bool = setting(
        True, "with the CM found in no verification view, register it from the kinematic prediction"
    )

    @classmethod
    def reference(cls) -> VerificationConfig:
        """The verification as fluoronav 0.4.1 ran it: every view's bones with the whole ladders,
        the CM from the images alone (``reference-0.4.1``, the bench's ``navigate_verify_s_reference``)."""
        return shipped_settings("reference-0.4.1").verification


@dataclass(frozen=True)
class NavigationConfig:
    """Settings of the pipeline (recorded in ``navigation.json``; a site's file sets them).

    Attributes:
        device: torch device of the detector, renderers and similarities (``--device``).
        seed: seeds every optimiser (the same seed gives the same result; ``--seed``).
        min_views: views with a usable CM detection that the first registration needs (the
            triangulation of A and B needs two).
        landmark_band_mm: half-width at the detector of the CM region assumed about A–B in a view
            whose case gives landmarks but no mask.
        ik_tol_mm, ik_tol_deg: inverse-kinematics acceptance.
        safety: the thresholds of the registration checks and the bounds of the robot's commands.
        preflight: the thresholds of the checks of the case's inputs and plan before any
            registration (:mod:`fluoronav.navigation.checks.preflight`); None: none.
        verification: how the verification registers its images and uses the kinematics.
        views: the first images' view-set registration (pelvis per view: CMA-ES to ~96 px, then the
            linearised refinement at ~128 and ~256 px; femur; CM: :func:`navigation_cm_config`),
            the verification's too but for its CM and pelvis refinement (``verification``). Its
            device, CM geometry, checks and pelvis refinement are set by the pipeline
            (:attr:`derived_settings`).
    """

    #: the settings the pipeline sets itself (glob pattern → from what); a settings file cannot
    derived_settings: ClassVar[dict[str, str]] = {
        "*.device": "set from device, the run's",
        "*.cm_config": "set from the case's CM",
        "views.local": "set per registration from the case's C-arm motion",
        "views.cm_checks": "set from safety",
        "views.pelvis_refine": "set from verification.pelvis_refine",
        "safety.cm.max_shape_departure_sigmas": "set from safety.max_fbg_departure_sigmas",
    }

    device: str = setting("cpu", "torch device of the detector, renderers and similarities", site=False)
    seed: int = setting(0, "seeds every optimiser (the same seed gives the same result)", site=False)
    min_views: int = setting(2, "views with a usable CM detection the first registration needs", ge=2)
    landmark_band_mm: float = setting(
        6.0, "half-width of the CM region about A-B where a view has landmarks but no mask", unit="mm", gt=0
    )
    ik_tol_mm: float = setting(1e-6, "inverse-kinematics acceptance of the position", unit="mm", gt=0)
    ik_tol_deg: float = setting(1e-6, "inverse-kinematics acceptance of the rotation", unit="deg", gt=0)
    safety: SafetyConfig = setting(
        doc="thresholds of the registration checks and bounds of the robot's commands",
        default_factory=SafetyConfig,
    )
    preflight: PreflightConfig | None = setting(
        doc="thresholds of the checks of the case before any registration; none: none",
        default_factory=PreflightConfig,
    )
    verification: VerificationConfig = setting(
        doc="how the verification registers the images after the move", default_factory=VerificationConfig
    )
    views: ViewSetSettings = setting(
        doc="the first images' view-set registration (pelvis, femur, CM)", default_factory=_navigation_views
    )

    def view_set_settings(
        self,
        *,
        verification: bool,
        local: bool = False,
        n_views: int | None = None,
        fbg_sigma_deg: float | None = None,
    ) -> ViewSetSettings:
        """The settings of the registration of one set of views: the first images, or (``verification``)
        the images after the move; ``local``: their cameras start within a millimetre or so
        (:attr:`ViewSetSettings.local`); ``n_views``: how many views the set has (with two, a
        verification fused with the kinematics may stand on one: :attr:`SafetyConfig.verify_min_views`);
        ``fbg_sigma_deg``: the first images' FBG reading's stated accuracy (the case's), which
        weights the prior of the CM's shape (:func:`fbg_shape_prior`)."""
        fused_views = n_views if verification and self.verification.fuse_kinematics else None
        cm = self.verification.cm if verification else fbg_shape_prior(self.views.cm, fbg_sigma_deg)
        return dataclasses.replace(
            self.views,
            local=local,
            device=self.device,
            pelvis_refine=self.verification.pelvis_refine,
            cm=cm,
            cm_checks=self.safety.cm_checks(fused_views=fused_views, fbg=not verification),
        )


def shipped_settings(name: str, base: NavigationConfig | None = None) -> NavigationConfig:
    """``base`` (default :class:`NavigationConfig`) with a settings file shipped with fluoronav,
    ``fluoronav/data/settings/<name>.toml`` (e.g. ``reference-0.4.1``)."""
    path = resources.files("fluoronav") / "data" / "settings" / f"{name}.toml"
    return load_settings(base or NavigationConfig(), str(path))
