"""Whether an input every view shares explains a CM registration's refusal: the FBG reading, the CT's scale.

Where the FBG reading or the CT's spacing is wrong, every view is wrong together and the view a
check names is only the worst. Before such a refusal stands, the CM is registered once more with each
shared input free: its shape within ``shape_search_tolerance_deg`` of the reading, from the shape the
views' centrelines favour (:func:`name_fbg_cause`); its size scaled by the factor its triangulated
landmarks give (:func:`name_scale_cause`). A fit of every view names the input (check
``fbg_reading`` or ``ct_scale``) with the value found; otherwise the view's refusal stands.

NOTE: a CT whose spacing reads ``s`` times the true one makes the registered scene, cameras included,
``s`` times larger (the bones absorb it as depth, exactly): the CM looks ``s`` times its size.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fluoronav.errors import RegistrationRefused
from fluoronav.geometry.camera import triangulate_points
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.registration.cm.checks import CMCheckConfig, judge_shape, register_cm_checked
from fluoronav.registration.cm.config import CMRegistrationConfig
from fluoronav.registration.cm.result import CMRegistrationResult
from fluoronav.registration.cm.views import CMView

__all__ = [
    "SHARED_CAUSE_CHECKS",
    "RefusedCM",
    "centreline_shape",
    "landmark_scale",
    "name_fbg_cause",
    "name_scale_cause",
    "name_shared_cause",
    "scaled_cm_config",
]

log = logging.getLogger(__name__)

#: the view checks whose failure may be a shared input's
SHARED_CAUSE_CHECKS = ("edge_ncc", "landmark_residual")


@dataclass(frozen=True, eq=False)
class RefusedCM:
    """A refused CM registration and what it was run on (:func:`register_cm_checked`'s inputs).

    Attributes:
        refused: its refusal.
        views, landmarks_px, tries, seed, stage: as :func:`register_cm_checked`.
        reading_deg: (n_control_points,) the FBG reading its shape was held to.
        config: the registration's settings (its control-point σ is the reading's).
        checks: its thresholds.
        starts_for: where given, a shape's starts and their centreline cost (px): the multi-view
            initialisation with that shape (:func:`centreline_shape` searches the shape by it).
    """

    refused: RegistrationRefused
    views: Sequence[CMView]
    landmarks_px: Sequence[np.ndarray | None]
    tries: Sequence[Sequence[np.ndarray]]
    reading_deg: np.ndarray
    config: CMRegistrationConfig
    checks: CMCheckConfig
    seed: int
    stage: str = "cm"
    starts_for: Callable[[np.ndarray], tuple[list[list[np.ndarray]], float]] | None = None

    def subset(self, keep: Sequence[int]) -> RefusedCM:
        """The same with only the views ``keep`` (their landmarks with them; no ``starts_for``)."""
        return dataclasses.replace(
            self,
            views=[self.views[k] for k in keep],
            landmarks_px=[self.landmarks_px[k] for k in keep],
            starts_for=None,
        )

    def register_again(
        self,
        config: CMRegistrationConfig,
        checks: CMCheckConfig,
        seed: int,
        *,
        tries: Sequence[Sequence[np.ndarray]] | None = None,
        shape_deg: np.ndarray | None = None,
    ) -> CMRegistrationResult:
        """The same registration with other settings, starts or shape (the shape's prior centred on
        it; default: the reading) (raises :class:`RegistrationRefused`)."""
        return register_cm_checked(
            self.views,
            self.landmarks_px,
            self.tries if tries is None else tries,
            {},
            initial_control_points_deg=self.reading_deg if shape_deg is None else shape_deg,
            config=config,
            checks=checks,
            seed=seed,
            stage=self.stage,
        )


def name_fbg_cause(failed: RefusedCM, record: dict[str, Any] | None = None) -> RegistrationRefused:
    """The refusal of a registration whose shape was held to an FBG reading, with its cause named
    where the reading is it (check ``fbg_reading``); otherwise ``refused``.

    The CM is registered once more with its shape free within ``checks.shape_search_tolerance_deg``
    of the reading (flat, then the prior's σ), from the starts of the shape the views' centrelines
    favour (:func:`centreline_shape`; the reading's own where ``failed.starts_for`` is None), and
    where that fits nothing, from a straight CM's starts with its shape free as far about straight:
    where one passes every view's check with a shape further from the reading than its stated
    accuracy allows (:func:`judge_shape`), the reading is the cause.

    Args:
        failed: the registration held to the reading (its ``checks.max_shape_departure_sigmas`` set).
        record: filled in place where given: ``fits`` (the free shape passed every view),
            ``departure_sigmas`` and ``control_points_deg`` of the free shape.
    """
    refused, config, checks = failed.refused, failed.config, failed.checks
    sigma, max_sigmas = config.control_point_sigma_deg, checks.max_shape_departure_sigmas
    if sigma is None or max_sigmas is None or refused.check not in SHARED_CAUSE_CHECKS:
        return refused
    free = config.with_(control_point_tolerance_deg=checks.shape_search_tolerance_deg)
    searched = dataclasses.replace(checks, max_shape_departure_sigmas=None)  # the views' checks alone
    rec = record if record is not None else {}
    cm = _free_shape(failed, free, searched, rec)
    if cm is None:
        rec["fits"] = False
        return refused
    dep, verdict = judge_shape(cm, failed.reading_deg, config, max_sigmas)
    rec.update(
        fits=True,
        departure_sigmas=float(dep),
        control_points_deg=[float(x) for x in np.asarray(cm.control_points_deg)],
    )
    if verdict is None:
        return refused
    log.warning(
        "%s: with its shape free the CM fits every view, %.1f σ from the FBG reading", failed.stage, dep
    )
    detail = (
        f"{verdict.detail}: with its shape free the CM fits every view, held to the reading it "
        f"fails ({refused})"
    )
    return RegistrationRefused(failed.stage, "fbg_reading", detail)


def _free_shape(
    failed: RefusedCM, free: CMRegistrationConfig, searched: CMCheckConfig, rec: dict[str, Any]
) -> CMRegistrationResult | None:
    """The CM with its shape free (:func:`name_fbg_cause`): from the starts of the shape the
    centrelines favour (``rec["centreline_shape_deg"]``), else from a straight CM's; None where
    neither fits every view."""
    reading = np.asarray(failed.reading_deg, np.float64)
    if failed.starts_for is None:
        tries, shape = failed.tries, reading
    else:
        shape, tries = centreline_shape(
            failed.starts_for,
            reading,
            failed.checks.shape_search_tolerance_deg,
            failed.checks.shape_search_step_deg,
        )
        rec["centreline_shape_deg"] = [round(float(x), 3) for x in shape]
        tries = tries or failed.tries
    try:
        return failed.register_again(free, searched, failed.seed, tries=tries, shape_deg=shape)
    except RegistrationRefused:
        pass
    straight = np.zeros_like(reading)
    tries = [] if failed.starts_for is None else failed.starts_for(straight)[0]
    if not tries:
        return None
    try:
        return failed.register_again(free, searched, failed.seed + 2, tries=tries, shape_deg=straight)
    except RegistrationRefused:
        return None


def centreline_shape(
    starts_for: Callable[[np.ndarray], tuple[list[list[np.ndarray]], float]],
    reading_deg: np.ndarray,
    tolerance_deg: float,
    step_deg: float,
) -> tuple[np.ndarray, list[list[np.ndarray]]]:
    """The shape within ``tolerance_deg`` of the reading whose multi-view centreline initialisation
    (``starts_for``) costs least, and its starts: one offset of every control point on a
    ``step_deg`` grid, then each control point moved by ±``step_deg``, then ±``step_deg``/2, while
    that lowers the cost.

    Why: a registration started from the reading's roll minima stays in their basin when the reading
    is off (a reading 3° off at every point leaves its best start 40° from the CM); the centrelines
    tell the shape apart before any rendering (0.24 px at the true shape, 1.07 px at such a reading).
    Some 30–60 initialisations (< 1 s each).
    """
    reading = np.asarray(reading_deg, np.float64)
    seen: dict[tuple[float, ...], tuple[float, list[list[np.ndarray]]]] = {}

    def key(shape: np.ndarray) -> tuple[float, ...]:
        return tuple(np.round(shape, 6))

    def cost(shape: np.ndarray) -> float:
        if key(shape) not in seen:
            tries, c = starts_for(shape)
            seen[key(shape)] = (c if tries else math.inf, tries)
        return seen[key(shape)][0]

    n = math.floor(tolerance_deg / step_deg)
    best = min((reading + k * step_deg for k in range(-n, n + 1)), key=cost)
    for step in (step_deg, step_deg / 2):
        moved = True
        while moved:  # each move lowers the cost on a finite grid: it ends
            moved = False
            for i, sign in itertools.product(range(len(reading)), (1.0, -1.0)):
                trial = best.copy()
                trial[i] = np.clip(
                    trial[i] + sign * step, reading[i] - tolerance_deg, reading[i] + tolerance_deg
                )
                if cost(trial) < cost(best):
                    best, moved = trial, True
    return best, seen[key(best)][1]


def landmark_scale(
    views: Sequence[CMView], landmarks_px: Sequence[np.ndarray | None], reading_deg: np.ndarray, cm: CMConfig
) -> float | None:
    """The CM's size in the views' frame over its size in mm: the distance of its landmarks A and B
    triangulated over the views with both, over their distance at the reading's shape; None with
    fewer than two such views."""
    seen = [(v.camera, np.asarray(lm, np.float64)) for v, lm in zip(views, landmarks_px, strict=True)]
    seen = [(c, lm) for c, lm in seen if lm is not None and lm.shape == (2, 2) and np.isfinite(lm).all()]
    if len(seen) < 2:
        return None
    ab = triangulate_points([c for c, _ in seen], np.stack([lm for _, lm in seen]))
    model = CMKinematics(cm).landmarks_cm(torch.as_tensor(reading_deg, dtype=torch.float64)).numpy()
    return float(np.linalg.norm(ab[1] - ab[0]) / np.linalg.norm(model[1] - model[0]))


def scaled_cm_config(cm: CMConfig, factor: float) -> CMConfig:
    """The CM ``factor`` times its size (every length); its density over ``factor``, so that a ray's
    line integral through it is the one of the CM itself."""
    values = {k: getattr(cm, k) for k in type(cm).model_fields if k.endswith("_mm")}
    lengths = {k: v * factor for k, v in values.items() if v is not None}
    return cm.model_copy(update={**lengths, "density_g_cm3": cm.density_g_cm3 / factor})


def name_scale_cause(failed: RefusedCM, record: dict[str, Any] | None = None) -> RegistrationRefused:
    """``failed.refused`` named as the CT's scale (check ``ct_scale``) where the CM, registered (seed
    ``failed.seed + 1``) at the size its landmarks give (:func:`landmark_scale`, at least
    ``checks.min_scale_departure`` from 1), passes every view's check; otherwise ``failed.refused``.

    Args: as :func:`name_fbg_cause`; ``record`` gets ``factor`` (the CM's size in the CT's frame over
    its size; None where it cannot be measured) and ``fits``.
    """
    rec = record if record is not None else {}
    refused, config = failed.refused, failed.config
    if refused.check not in SHARED_CAUSE_CHECKS:
        return refused
    factor = landmark_scale(failed.views, failed.landmarks_px, failed.reading_deg, config.cm_config)
    rec["factor"] = factor
    if factor is None or abs(factor - 1.0) < failed.checks.min_scale_departure:
        return refused
    scaled = config.with_(cm_config=scaled_cm_config(config.cm_config, factor))
    try:
        failed.register_again(scaled, failed.checks, failed.seed + 1)
    except RegistrationRefused:
        rec["fits"] = False
        return refused
    rec["fits"] = True
    log.warning("%s: at %.3f× its size the CM fits every view: the CT's scale", failed.stage, factor)
    detail = (
        f"the CM fits every view at {factor:.3f}× its size: the CT's spacing reads {factor:.3f}× the "
        f"true one (check its spacing and unit); at its size it fails ({refused})"
    )
    return RegistrationRefused(failed.stage, "ct_scale", detail)


def name_shared_cause(failed: RefusedCM, record: dict[str, Any] | None = None) -> RegistrationRefused:
    """``refused`` named as the FBG reading's (:func:`name_fbg_cause`), else the CT's scale's
    (:func:`name_scale_cause`), else as it was with "neither … explains it" added to its detail.

    Args: as :func:`name_fbg_cause`; ``record`` gets ``fbg_reading`` and ``ct_scale`` (each one's
    record).
    """
    refused = failed.refused
    if refused.check not in SHARED_CAUSE_CHECKS:
        return refused
    rec = record if record is not None else {}
    named = name_fbg_cause(failed, rec.setdefault("fbg_reading", {}))
    if named is refused:
        named = name_scale_cause(failed, rec.setdefault("ct_scale", {}))
    if named is not refused:
        return named
    factor = rec["ct_scale"].get("factor")
    size = "" if factor is None else f" (the CM's size in the views {factor:.3f}×)"
    detail = f"{refused.detail}; neither the FBG reading nor the CT's scale{size} explains it"
    return RegistrationRefused(refused.stage, refused.check, detail, view=refused.view)
