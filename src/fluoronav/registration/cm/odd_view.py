"""Which one view a refused CM registration's failure belongs to, where none of the inputs every view
shares explains it: each view left out in turn.

A view whose image is not of this CM and patient as the others are (another patient's image, a
patient or C-arm that moved, a wrong camera) pulls the CM registered on every view away from all of
them, and the view a check names is only the worst fitted, often not the odd one. Registered on the
others alone, the CM fits them and lies off the odd view's landmarks; where exactly one view does
that, the refusal names it (check ``odd_view``). Two views or more that do it: no single view is odd.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Any

import numpy as np

from fluoronav.errors import RegistrationRefused
from fluoronav.registration.cm.diagnostics import FULL_PIXEL_SPACING_MM
from fluoronav.registration.cm.result import CMRegistrationResult
from fluoronav.registration.cm.shared_causes import SHARED_CAUSE_CHECKS, RefusedCM

__all__ = ["landmark_miss_mm", "name_odd_view"]

log = logging.getLogger(__name__)


def landmark_miss_mm(cm: CMRegistrationResult, failed: RefusedCM, k: int) -> float | None:
    """How far the registered CM's A and B project from view ``k``'s landmarks (the larger, mm at
    the detector); None where the view has none."""
    lm = failed.landmarks_px[k]
    if lm is None or not np.isfinite(np.asarray(lm, np.float64)).all():
        return None
    camera = failed.views[k].camera
    d_px = np.linalg.norm(camera.project(cm.landmarks_world[0]) - np.asarray(lm, np.float64), axis=1)
    spacing = camera.pixel_spacing_mm if camera.pixel_spacing_mm is not None else FULL_PIXEL_SPACING_MM
    return float(d_px.max() * spacing)


def name_odd_view(failed: RefusedCM, record: dict[str, Any] | None = None) -> RegistrationRefused:
    """``failed.refused`` named as one view's (check ``odd_view``, that view) where the CM registered
    on every other view passes their checks and misses that view's landmarks by more than
    ``checks.max_landmark_residual_mm``, and leaving out no other view does the same; otherwise
    ``failed.refused``.

    Needs ``checks.min_views`` views with landmarks besides the one left out. View ``k``'s
    registration has seed ``failed.seed + 3 + k``; every remaining view must pass (none is left out
    again).

    Args:
        failed: the refused registration (a view's check: ``landmark_residual``, ``edge_ncc``).
        record: filled in place where given: per view left out, ``fits`` (the others passed) and
            ``miss_mm`` (:func:`landmark_miss_mm`).
    """
    refused, checks = failed.refused, failed.checks
    seen = [k for k, lm in enumerate(failed.landmarks_px) if lm is not None]
    if refused.check not in SHARED_CAUSE_CHECKS or len(seen) < checks.min_views + 1:
        return refused
    rec = record if record is not None else {}
    odd: list[tuple[int, float]] = []
    for k in seen:
        name = failed.views[k].name
        others = [i for i in range(len(failed.views)) if i != k]
        kept = dataclasses.replace(checks, min_views=len(others))
        try:
            cm = failed.subset(others).register_again(failed.config, kept, failed.seed + 3 + k)
        except RegistrationRefused as exc:
            rec[name] = {"fits": False, "check": exc.check}
            continue
        miss = landmark_miss_mm(cm, failed, k)
        rec[name] = {"fits": True, "miss_mm": miss}
        if miss is not None and miss > checks.max_landmark_residual_mm:
            odd.append((k, miss))
    if len(odd) != 1:
        return refused
    k, miss = odd[0]
    name = failed.views[k].name
    log.warning(
        "%s: registered on the other views the CM misses view %s by %.2f mm", failed.stage, name, miss
    )
    detail = (
        f"registered on the other views, which it fits, the CM lies {miss:.2f} mm from this view's "
        f"landmarks (at most {checks.max_landmark_residual_mm:g} mm): this view does not show the CM "
        "and patient as the others do (another patient's image, a patient or C-arm that moved, a "
        f"wrong camera); re-take it ({refused})"
    )
    return RegistrationRefused(failed.stage, "odd_view", detail, view=name)
