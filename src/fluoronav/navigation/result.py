"""What the navigation pipeline finds: its settings, per-stage records, registrations and result.

``navigation.json`` is :meth:`NavigationResult.to_json`: the status and reason, every stage with
its seconds, checks and diagnostics, the registered poses in the CT frame (LPS, mm), and the robot
command only when the status is "ok".
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fluoronav import __version__
from fluoronav.errors import RegistrationRefused
from fluoronav.geometry import se3
from fluoronav.navigation.checks.preflight_config import PreflightConfig
from fluoronav.navigation.checks.safety import SafetyConfig
from fluoronav.navigation.kinematic_prior import KinematicUncertainty
from fluoronav.navigation.planning import Plan
from fluoronav.registration.bone.presets import (
    PELVIS_LINEARIZED_PRESET,
    PELVIS_REFINE_PRESET,
    BoneRegistrationConfig,
)
from fluoronav.registration.cm.config import CMRegistrationConfig, default_cm_levels, fbg_shape_prior
from fluoronav.registration.stages import StageRecord
from fluoronav.registration.view_set import ViewDetection, ViewSetRegistration, ViewSetSettings

__all__ = [
    "NavigationConfig",
    "NavigationRefused",
    "NavigationResult",
    "StageRecord",
    "VerificationConfig",
    "ViewDetection",
    "navigation_cm_config",
    "navigation_refusals",
    "reference_cm_config",
]


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
    """

    fuse_kinematics: bool = True
    uncertainty: KinematicUncertainty = field(default_factory=KinematicUncertainty)
    local_bones: bool = True

    @classmethod
    def reference(cls) -> VerificationConfig:
        """The verification as fluoronav 0.4.1 ran it: every view's bones with the whole ladders,
        the CM from the images alone (the bench's ``navigate_verify_s_reference``)."""
        return cls(fuse_kinematics=False, local_bones=False)


@dataclass(frozen=True)
class NavigationConfig:
    """Settings of the pipeline (recorded in ``navigation.json``).

    Attributes:
        device: torch device of the detector, renderers and similarities.
        seed: seeds every optimiser (the same seed gives the same result).
        min_views: views with a usable CM detection that the first registration needs (the
            triangulation of A and B needs two).
        max_cm_starts: roll minima of the centreline initialisation the CM registration starts from.
        landmark_band_mm: half-width at the detector of the CM region assumed about A–B in a view
            whose case gives landmarks but no mask.
        ik_tol_mm, ik_tol_deg: inverse-kinematics acceptance.
        safety: the thresholds of the registration checks.
        preflight: the thresholds of the checks of the case's inputs and plan before any
            registration (:mod:`fluoronav.navigation.checks.preflight`); None: none.
        pelvis: the per-view pelvis registration's levels (its ``device`` is replaced by ``device``):
            CMA-ES to ~96 px, then the linearised refinement at ~128 and ~256 px.
        femur: the femur registration's levels; None: the multi-view preset
            (:func:`~fluoronav.registration.bone.presets.femur_config`).
        verify_pelvis_refine: the verification views' second pelvis registration, from the first,
            with the femur (placed by the first registration) left out of the similarity; None:
            none (in views centred on the hip the femoral head pulled the pelvis 1.5–2 mm along
            the beam).
        femur_margin_mm: how far around the femur's footprint that second registration leaves out,
            in mm at the femur (the femur's and the camera's errors, and a leg that moved a little).
        cm: the first CM registration's settings (its ``device`` and ``cm_config`` are replaced by
            the pipeline's and the case's); None: :func:`navigation_cm_config`.
        verify_cm: the verification's CM registration's settings, likewise; None:
            :func:`navigation_cm_config`.
        verification: how the verification uses the kinematics and the C-arm's motion.
    """

    device: str = "cpu"
    seed: int = 0
    min_views: int = 2
    max_cm_starts: int = 2
    landmark_band_mm: float = 6.0
    ik_tol_mm: float = 1e-6
    ik_tol_deg: float = 1e-6
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    preflight: PreflightConfig | None = field(default_factory=PreflightConfig)
    pelvis: BoneRegistrationConfig = PELVIS_LINEARIZED_PRESET
    femur: BoneRegistrationConfig | None = None
    verify_pelvis_refine: BoneRegistrationConfig | None = PELVIS_REFINE_PRESET
    femur_margin_mm: float = 3.0
    cm: CMRegistrationConfig | None = None
    verify_cm: CMRegistrationConfig | None = None
    verification: VerificationConfig = field(default_factory=VerificationConfig)

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
        cm = (self.verify_cm if verification else self.cm) or navigation_cm_config()
        if not verification:
            cm = fbg_shape_prior(cm, fbg_sigma_deg)
        return ViewSetSettings(
            local=local,
            device=self.device,
            pelvis=self.pelvis,
            femur=self.femur,
            pelvis_refine=self.verify_pelvis_refine,
            femur_margin_mm=self.femur_margin_mm,
            cm=cm,
            max_cm_starts=self.max_cm_starts,
            cm_checks=self.safety.cm_checks(fused_views=fused_views, fbg=not verification),
        )


def navigation_cm_config() -> CMRegistrationConfig:
    """The pipeline's CM registration settings from the images' own starts: both levels CMA-ES
    (:func:`default_cm_levels`).

    Why not the multi-view workflow's linearised 2× level: it finds the tip as well but not the
    base's direction, and the first move carries that over its length (docs/validation.md, "CM
    levels and priors"). The verification's registration from the kinematic prediction has its own
    local levels (:func:`~fluoronav.registration.cm.config.local_cm_levels`)."""
    return CMRegistrationConfig(levels=default_cm_levels())


def reference_cm_config() -> CMRegistrationConfig:
    """The CM registration settings of fluoronav 0.4.1 (the bench's reference): both levels CMA-ES."""
    return CMRegistrationConfig(levels=default_cm_levels())


class NavigationRefused(RegistrationRefused):
    """A stage could not go on; no robot command may be given.

    Args:
        stage: the stage that refused; check: the check that failed; view: the view concerned or "".
    """


@contextmanager
def navigation_refusals(prefix: str) -> Iterator[None]:
    """A registration's refusal as the navigation's, its stage named as the pipeline's."""
    try:
        yield
    except RegistrationRefused as exc:
        if isinstance(exc, NavigationRefused):
            raise
        raise NavigationRefused(f"{prefix}{exc.stage}", exc.check, exc.detail, view=exc.view) from exc


@dataclass
class NavigationResult:
    """What ``navigate`` found and commanded (``navigation.json``: :meth:`to_json`).

    ``first`` / ``verification`` are the registrations; ``plan`` is the plan as used (with the CM's
    registered shape where the case's plan gives none); the robot commands are set only when the
    status is "ok". ``warnings``: what a user must know about a result that stands (e.g. the
    verification images and the robot's kinematics disagreed and the images were trusted).
    """

    config: NavigationConfig
    status: str = "ok"
    reason: str = ""
    stages: dict[str, StageRecord] = field(default_factory=dict)
    first: ViewSetRegistration | None = None
    plan: Plan | None = None
    femur_from_cm_target: np.ndarray | None = None
    rbase_from_ee_target: np.ndarray | None = None
    joints_target_deg: np.ndarray | None = None
    verification: ViewSetRegistration | None = None
    correction_femur_from_cm_target: np.ndarray | None = None
    rbase_from_ee_correction: np.ndarray | None = None
    joints_correction_deg: np.ndarray | None = None
    warnings: list[str] = field(default_factory=list)

    def refuse(self, exc: NavigationRefused) -> None:
        """Mark the run refused and withdraw every robot command (none may be acted on)."""
        self.status, self.reason = "refused", str(exc)
        if exc.stage in self.stages:
            self.stages[exc.stage].passed = False
        self.rbase_from_ee_target = self.joints_target_deg = None
        self.rbase_from_ee_correction = self.joints_correction_deg = None

    def flat_diagnostics(self) -> dict[str, float]:
        """The registrations' diagnostics in one flat dict (study rows): per set of views (prefix
        ``""`` or ``"verify_"``) the worst view's CM landmark residual and edge NCC, the pelvis's
        worst view cost, the femur cost; the first CM's shape against the FBG reading (in the reading's
        σ); the verification's kinematic motion agreement."""
        out: dict[str, float] = {}
        for prefix in ("", "verify_"):
            st = self.stages
            if f"{prefix}cm" in st and "views" in st[f"{prefix}cm"].diagnostics:
                views = st[f"{prefix}cm"].diagnostics["views"].values()
                res = [v["landmark_residual_mm"] for v in views if v["landmark_residual_mm"] is not None]
                if res:
                    out[f"{prefix}cm_landmark_residual_mm"] = float(max(res))
                out[f"{prefix}cm_edge_ncc"] = float(min(v["edge_ncc"] for v in views))
                for key in ("motion_tip_mm", "motion_rotation_deg"):
                    if key in st[f"{prefix}cm"].diagnostics:
                        out[f"{prefix}{key}"] = float(st[f"{prefix}cm"].diagnostics[key])
                if "fbg_departure_sigmas" in st[f"{prefix}cm"].diagnostics:
                    out[f"{prefix}cm_fbg_departure_sigmas"] = float(
                        st[f"{prefix}cm"].diagnostics["fbg_departure_sigmas"]
                    )
            if f"{prefix}pelvis" in st and "views" in st[f"{prefix}pelvis"].diagnostics:
                out[f"{prefix}pelvis_cost"] = float(
                    max(v["cost"] for v in st[f"{prefix}pelvis"].diagnostics["views"].values())
                )
            if f"{prefix}femur" in st and "cost" in st[f"{prefix}femur"].diagnostics:
                out[f"{prefix}femur_cost"] = float(st[f"{prefix}femur"].diagnostics["cost"])
        return {**out, **self._verification_route()}

    def _verification_route(self) -> dict[str, float]:
        """How the verification went: views its CM used, from the kinematic prediction (1/0), fused
        with it (1/0), registered again with the whole ladders after the local bones refused (1/0)."""
        st = self.stages
        if "verify_cm" not in st:
            return {}
        cm = st["verify_cm"].diagnostics
        detect = st["verify_detect"].diagnostics if "verify_detect" in st else {}
        return {
            "verify_views_used": float(len(cm.get("views_used", ()))),
            "verify_from_prediction": float(bool(cm.get("from_prediction", False))),
            "verify_fused": float("fusion_shift_mm" in cm),
            "verify_whole_ladders_retry": float("local_bones_refused" in detect),
        }

    @property
    def verified(self) -> bool:
        """True where the move was checked on images taken after it (a verification that passed).

        Without verification views a command rests on the first registration, the hand-eye matrix
        and the robot's kinematics alone: a wrong hand-eye matrix cannot be seen before the move.
        """
        return self.status == "ok" and self.verification is not None

    def to_json(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "version": __version__,
            "status": self.status,
            "reason": self.reason,
            "verified": self.verified,
            "warnings": list(self.warnings),
            "config": dataclasses.asdict(self.config),
            "stages": {k: v.to_dict() for k, v in self.stages.items()},
        }
        if self.first is not None:
            d.update(self.first.to_dict())
        if self.plan is not None:
            d["plan"] = self.plan.to_dict()
        if self.femur_from_cm_target is not None:
            d["femur_from_cm_target"] = self.femur_from_cm_target.tolist()
        if self.status == "ok" and self.joints_target_deg is not None:
            assert self.rbase_from_ee_target is not None
            d["rbase_from_ee_target"] = self.rbase_from_ee_target.tolist()
            d["joints_target_deg"] = self.joints_target_deg.tolist()
            d.update(self._command_motion("robot"))
        if self.verification is not None:
            v = self.verification.to_dict()
            if self.plan is not None:
                planned_tip_ct = se3.apply(self.verification.ct_from_femur, self.plan.tip_target_world_mm)
                v["tip_to_plan_mm"] = float(np.linalg.norm(self.verification.tip_ct_mm - planned_tip_ct))
            if self.status == "ok" and self.joints_correction_deg is not None:
                assert self.rbase_from_ee_correction is not None
                v["rbase_from_ee_target"] = self.rbase_from_ee_correction.tolist()
                v["joints_target_deg"] = self.joints_correction_deg.tolist()
                v.update(self._command_motion("correct"))
            d["verification"] = v
        return d

    def _command_motion(self, stage: str) -> dict[str, Any]:
        """A command's ``joint_motion_deg`` (per joint, degrees) from its stage's measurement."""
        rec = self.stages.get(stage)
        if rec is None or "joint_motion_per_joint_deg" not in rec.diagnostics:
            return {}
        return {"joint_motion_deg": list(rec.diagnostics["joint_motion_per_joint_deg"])}
