"""Whether a CM registration can be trusted: per-view verdicts, views left out, a second start, refusal.

A CM registration is checked in each view (:mod:`~fluoronav.registration.cm.diagnostics`): the
registered landmarks against the detected ones and the registered CM's outline against the image.
A view that fails is left out and the CM registered again without it while enough views remain.
Where another account of the CM's pose is known (after the robot's move: where its kinematics put
the CM, :class:`PredictedCMPose`), the registration must agree with it too, else the next start is
tried. A registration that passes from no start raises
:class:`~fluoronav.errors.RegistrationRefused`, naming the view and the check that failed last.
The thresholds are :class:`CMCheckConfig` and :attr:`PredictedCMPose.max_tip_mm`;
docs/validation.md ("The checks' thresholds") gives the data they were chosen on.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fluoronav.errors import RegistrationRefused
from fluoronav.geometry import se3
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.registration.cm.config import CMRegistrationConfig
from fluoronav.registration.cm.diagnostics import CMViewDiagnostics, cm_view_diagnostics
from fluoronav.registration.cm.multistart import register_cm_multistart
from fluoronav.registration.cm.problem import register_cm
from fluoronav.registration.cm.result import CMRegistrationResult
from fluoronav.registration.cm.views import CMView
from fluoronav.settings import setting

log = logging.getLogger(__name__)

__all__ = [
    "MAX_MOTION_TIP_MM",
    "CMCheckConfig",
    "PredictedCMPose",
    "ViewVerdict",
    "judge_cm_views",
    "judge_motion",
    "judge_shape",
    "motion_agreement",
    "register_cm_checked",
    "shape_departure_sigmas",
]

#: how far (mm) the registered CM tip may lie from a predicted one: the robot's and the first
#: registration's errors together (the default of every such tolerance; the navigation's is
#: ``SafetyConfig.max_motion_tip_mm``)
MAX_MOTION_TIP_MM = 3.0


@dataclass(frozen=True)
class CMCheckConfig:
    """Thresholds of the per-view checks of a CM registration.

    Attributes:
        max_landmark_residual_mm: a view's registered A or B may lie at most this far (mm at the
            detector) from the detected one.
        min_edge_ncc: a view's gradient NCC on the registered CM's outline must reach this.
        min_views: views that must pass for a CM registration to stand.
        max_shape_departure_sigmas: where the shape's prior is a measurement (the FBG reading), the
            registered control points may depart from it by at most the prior's tolerance plus this
            many of its σ (:func:`judge_shape`); None: not checked.
        shape_search_tolerance_deg: where such a registration fails a view's check, it is registered
            once more with the shape free within this of the reading
            (:func:`~fluoronav.registration.cm.shared_causes.name_fbg_cause`): a shape the images
            accept that far from the reading names the reading as the cause.
        shape_search_step_deg: that registration starts from the shape, within the same tolerance,
            whose multi-view centreline initialisation costs least, searched on this step
            (:func:`~fluoronav.registration.cm.shared_causes.centreline_shape`).
        min_scale_departure: where a view's check fails, the CM's size in the views (its
            triangulated landmarks) must differ from its own by this fraction before the CM is
            registered at that size to test the CT's scale
            (:func:`~fluoronav.registration.cm.shared_causes.name_scale_cause`).
    """

    max_landmark_residual_mm: float = setting(
        2.0, "a view's registered A or B at most this far from the detected one", unit="mm", ge=0
    )
    min_edge_ncc: float = setting(0.7, "a view's gradient NCC on the registered CM's outline", ge=-1, le=1)
    min_views: int = setting(2, "views that must pass for a CM registration to stand", ge=1)
    max_shape_departure_sigmas: float | None = setting(
        None, "the shape's departure from its measured prior beyond its tolerance; none: unchecked", ge=0
    )
    shape_search_tolerance_deg: float = setting(
        6.0, "a failed view's second registration frees the shape this far from the reading", unit="deg", ge=0
    )
    shape_search_step_deg: float = setting(
        1.0, "the step of the search for the shape the views' centrelines favour", unit="deg", gt=0
    )
    min_scale_departure: float = setting(
        0.03, "the CM's size in the views, off its own by this fraction, is tested as the CT's scale", ge=0
    )


@dataclass(frozen=True, eq=False)
class PredictedCMPose:
    """Where another account puts the CM (after the robot's move: its kinematics), relative to a
    registered reference (the femur), and how far the registration may be from it.

    Attributes:
        world_from_reference: (4, 4) the registered reference (``ct_from_femur``).
        reference_from_cm: (4, 4) the predicted CM pose in the reference's frame
            (``femur_from_cm``).
        max_tip_mm: the registered CM tip (reference frame) may lie at most this far from the
            predicted one.
    """

    world_from_reference: np.ndarray
    reference_from_cm: np.ndarray
    max_tip_mm: float = MAX_MOTION_TIP_MM

    @property
    def world_from_cm(self) -> np.ndarray:
        """(4, 4) the predicted CM pose in the world frame."""
        return np.asarray(self.world_from_reference @ self.reference_from_cm)


@dataclass(frozen=True)
class ViewVerdict:
    """A view's checks: ``passed``, and the failed ``check`` with its ``detail`` otherwise."""

    view: str
    passed: bool
    check: str = ""
    detail: str = ""


def judge_cm_views(
    names: Sequence[str], diagnostics: Sequence[Mapping[str, Any]], config: CMCheckConfig
) -> list[ViewVerdict]:
    """Per view: does the CM registration agree with it (landmark residual, edge NCC)?

    Args:
        names: the views' names.
        diagnostics: per view ``{"landmark_residual_mm": float | None, "edge_ncc": float}``.
        config: thresholds.
    """
    out = []
    for name, d in zip(names, diagnostics, strict=True):
        res = d.get("landmark_residual_mm")
        if res is not None and res > config.max_landmark_residual_mm:
            out.append(
                ViewVerdict(
                    name,
                    False,
                    "landmark_residual",
                    f"registered landmarks {res:.2f} mm from the detected ones "
                    f"(at most {config.max_landmark_residual_mm:g} mm)",
                )
            )
        elif float(d["edge_ncc"]) < config.min_edge_ncc:
            out.append(
                ViewVerdict(
                    name,
                    False,
                    "edge_ncc",
                    f"the registered CM's outline matches the image with NCC {float(d['edge_ncc']):.2f} "
                    f"(at least {config.min_edge_ncc:g})",
                )
            )
        else:
            out.append(ViewVerdict(name, True))
    return out


def shape_departure_sigmas(
    control_points_deg: np.ndarray, reading_deg: np.ndarray, *, sigma_deg: float, tolerance_deg: float
) -> float:
    """The largest departure of registered control points from a reading beyond its tolerance, in
    units of the reading's σ: ``max_i max(|x_i − r_i| − τ, 0) / σ`` (0 within the tolerance)."""
    d = np.abs(np.asarray(control_points_deg, np.float64) - np.asarray(reading_deg, np.float64))
    return float(np.max(np.maximum(d - tolerance_deg, 0.0)) / sigma_deg)


def judge_shape(
    cm: CMRegistrationResult, reading_deg: np.ndarray, config: CMRegistrationConfig, max_sigmas: float
) -> tuple[float, ViewVerdict | None]:
    """The registered shape against the reading its prior is centred on (``config``'s σ and
    tolerance): (departure in σ, :func:`shape_departure_sigmas`; None where within ``max_sigmas``,
    else the failed check ``fbg_shape``).

    Notes:
        A shape pulled away from an accurate reading is a shape bent to make up for something
        else, typically a base tilted or rolled so that the tip still matches the images; the
        first move carries that base's direction over its length. Either the reading (its
        calibration) or the registration is wrong, and the images cannot say which.
    """
    sigma = config.control_point_sigma_deg
    assert sigma is not None
    dep = shape_departure_sigmas(
        cm.control_points_deg, reading_deg, sigma_deg=sigma, tolerance_deg=config.control_point_tolerance_deg
    )
    if dep <= max_sigmas:
        return dep, None
    worst = int(np.argmax(np.abs(np.asarray(cm.control_points_deg) - np.asarray(reading_deg))))
    gap = float(cm.control_points_deg[worst] - reading_deg[worst])
    return dep, ViewVerdict(
        "",
        False,
        "fbg_shape",
        f"the registered CM shape departs from the FBG reading by {gap:+.2f}° at control point {worst} "
        f"({dep:.1f} σ of the reading, at most {max_sigmas:g}): the shape makes up for a base "
        "that is not where the images put it, or the FBG reading is off; check the FBG sensor's "
        "calibration",
    )


def judge_motion(motion: Mapping[str, float], max_tip_mm: float) -> ViewVerdict | None:
    """None where the registration agrees with the predicted pose (:func:`motion_agreement`), else
    the failed check (``robot_motion``)."""
    tip = float(motion["motion_tip_mm"])
    if tip <= max_tip_mm:
        return None
    return ViewVerdict(
        "",
        False,
        "robot_motion",
        f"the CM the images show is {tip:.1f} mm from where the robot's kinematics put it "
        f"(at most {max_tip_mm:g} mm)",
    )


def motion_agreement(
    predicted: PredictedCMPose, cm: CMRegistrationResult, cm_config: CMConfig
) -> dict[str, float]:
    """Agreement of a CM registration with a predicted pose, in the reference's frame:
    ``motion_tip_mm`` (tip distance) and ``motion_rotation_deg``.

    Notes:
        A verification registration that failed disagrees by far more than the robot's and the
        first registration's errors.
    """
    reference = se3.as_transform_array(predicted.world_from_reference, "world_from_reference")
    reg = se3.inv(reference) @ se3.as_transform_array(cm.world_from_cm[0], "world_from_cm")
    pred = predicted.reference_from_cm
    tip = CMKinematics(cm_config).tip_cm(torch.as_tensor(cm.control_points_deg, dtype=torch.float64)).numpy()
    d = np.linalg.inv(pred) @ reg
    c = (np.trace(d[:3, :3]) - 1.0) / 2.0
    return {
        "motion_tip_mm": float(np.linalg.norm(se3.apply(reg, tip) - se3.apply(pred, tip))),
        "motion_rotation_deg": float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))),
    }


def register_cm_checked(
    views: Sequence[CMView],
    landmarks_px: Sequence[np.ndarray | None],
    tries: Sequence[Sequence[np.ndarray]],
    diagnostics: dict[str, Any],
    *,
    initial_control_points_deg: np.ndarray,
    config: CMRegistrationConfig,
    checks: CMCheckConfig,
    seed: int,
    predicted: PredictedCMPose | None = None,
    stage: str = "cm",
) -> CMRegistrationResult:
    """The CM registered and checked (module docstring).

    Args:
        views: the CM views (their names name them in ``diagnostics`` and refusals).
        landmarks_px: per view the detected (2, 2) A, B, or None.
        tries: lists of world-frame start poses; the next list is tried only where the previous
            failed its checks. Within a try, views that disagree with the registration are left
            out and the CM registered again from where it was, while ``checks.min_views`` remain.
        diagnostics: filled in place (JSON-ready): ``cost``, ``converged``, ``reason``, ``views``
            (per view :class:`CMViewDiagnostics`), ``views_used``, ``tries``, the motion
            agreement (:func:`motion_agreement`) and ``left_out`` (view → why).
        initial_control_points_deg: (n_control_points,) the shape's start.
        config: the CM registration's settings.
        checks: thresholds.
        seed: try t's seed is ``seed + t`` (``seed + 17 + t`` without a view).
        predicted: where another account puts the CM; None: no such check.
        stage: the stage named in refusals and log messages.

    Raises:
        RegistrationRefused: no try passed; the reason names the view and the check that failed
            last.
    """
    names = [v.name for v in views]
    spacing = [v.camera.pixel_spacing_mm for v in views]
    left_out: dict[str, str] = {}
    last: ViewVerdict | None = None
    for t, starts in enumerate(tries):
        use = list(range(len(views)))
        cm = register_cm_multistart(
            views,
            starts,
            initial_control_points_deg=initial_control_points_deg,
            config=config,
            seed=seed + t,
        )
        while True:
            verdicts, moved = _judge_recorded(
                cm, use, t, names, landmarks_px, spacing, diagnostics, checks, predicted, config,
                initial_control_points_deg,
            )  # fmt: skip
            failed = [v for v in verdicts if not v.passed]
            if not failed and moved is None:
                if left_out:
                    diagnostics["left_out"] = left_out
                return cm
            last = failed[0] if failed else moved
            if not failed or len(use) - len(failed) < checks.min_views:
                break
            for v in failed:
                left_out[v.view] = f"{v.check}: {v.detail}"
                log.warning("%s: view %s left out (%s: %s)", stage, v.view, v.check, v.detail)
            use = [k for k, v in zip(use, verdicts, strict=True) if v.passed]
            cm = _register_kept(views, use, cm, config, seed + 17 + t, initial_control_points_deg)
        if t + 1 < len(tries):
            log.warning(
                "%s: %s failed (%s); trying the next start",
                stage,
                last.check if last else "",
                last.detail if last else "",
            )
    assert last is not None
    if left_out:
        diagnostics["left_out"] = left_out
    raise RegistrationRefused(stage, last.check, last.detail, view=last.view)


def _judge_recorded(
    cm: CMRegistrationResult,
    use: list[int],
    t: int,
    names: list[str],
    landmarks_px: Sequence[np.ndarray | None],
    spacing: list[float | None],
    diagnostics: dict[str, Any],
    checks: CMCheckConfig,
    predicted: PredictedCMPose | None,
    config: CMRegistrationConfig,
    initial_control_points_deg: np.ndarray,
) -> tuple[list[ViewVerdict], ViewVerdict | None]:
    """Try ``t``'s registration on the views ``use`` judged (:func:`_judge`) and its figures written
    into ``diagnostics``: ``(per-view verdicts, the shape's or the motion's verdict)``."""
    diags, verdicts, motion, moved = _judge(
        cm,
        [names[k] for k in use],
        [landmarks_px[k] for k in use],
        [spacing[k] for k in use],
        checks,
        predicted,
        config,
        np.asarray(initial_control_points_deg, np.float64),
    )
    diagnostics.update(
        cost=float(cm.cost),
        converged=bool(cm.converged),
        reason=cm.reason,
        views={names[k]: d.to_dict() for k, d in zip(use, diags, strict=True)},
        views_used=[names[k] for k in use],
        tries=t + 1,
        **(motion or {}),
    )
    return verdicts, moved


def _register_kept(
    views: Sequence[CMView],
    use: list[int],
    cm: CMRegistrationResult,
    config: CMRegistrationConfig,
    seed: int,
    initial_control_points_deg: np.ndarray,
) -> CMRegistrationResult:
    """The CM registered again on the kept views ``use``, from where ``cm`` left it."""
    return register_cm(
        [views[k] for k in use],
        initial_control_points_deg=cm.control_points_deg,
        initial_world_from_cm=cm.world_from_cm[0],
        config=config,
        seed=seed,
        # the prior stays on the reading: a continued registration must not settle beside it
        prior_control_points_deg=initial_control_points_deg,
    )


def _judge(
    cm: CMRegistrationResult,
    names: list[str],
    landmarks_px: list[np.ndarray | None],
    spacing: list[float | None],
    checks: CMCheckConfig,
    predicted: PredictedCMPose | None,
    config: CMRegistrationConfig,
    reading_deg: np.ndarray,
) -> tuple[list[CMViewDiagnostics], list[ViewVerdict], dict[str, float] | None, ViewVerdict | None]:
    """A registration's per-view diagnostics and verdicts and, where every view passed, its shape
    against the reading of the prior (:func:`judge_shape`, where checked) and, where a pose is
    predicted, its agreement with that pose (:func:`motion_agreement`): those figures and the
    verdict on them."""
    diags = cm_view_diagnostics(cm, landmarks_px, spacing)
    verdicts = judge_cm_views(names, [d.to_dict() for d in diags], checks)
    if not all(v.passed for v in verdicts):
        return diags, verdicts, None, None
    extra: dict[str, float] = {}
    if checks.max_shape_departure_sigmas is not None and config.control_point_sigma_deg is not None:
        dep, shape = judge_shape(cm, reading_deg, config, checks.max_shape_departure_sigmas)
        extra["fbg_departure_sigmas"] = dep
        if shape is not None:
            return diags, verdicts, extra, shape
    if predicted is None:
        return diags, verdicts, extra or None, None
    motion = motion_agreement(predicted, cm, config.cm_config)
    return diags, verdicts, {**extra, **motion}, judge_motion(motion, predicted.max_tip_mm)
