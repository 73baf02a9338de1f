"""What the navigation pipeline finds: per-stage records, registrations, refusals and result.

``navigation.json`` is :meth:`NavigationResult.to_json`: the status and reason, the settings in
force (:mod:`fluoronav.navigation.config`), every stage with its seconds, checks and diagnostics,
the registered poses in the CT frame (LPS, mm), and the robot command only when the status is "ok".
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fluoronav import __version__
from fluoronav.errors import RegistrationRefused
from fluoronav.geometry import se3
from fluoronav.navigation.config import NavigationConfig
from fluoronav.navigation.planning import Plan
from fluoronav.registration.stages import StageRecord
from fluoronav.registration.view_set import ViewDetection, ViewSetRegistration
from fluoronav.settings import settings_dict

__all__ = [
    "NavigationRefused",
    "NavigationResult",
    "StageRecord",
    "ViewDetection",
    "navigation_refusals",
]


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
            "settings": settings_dict(self.config),
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
