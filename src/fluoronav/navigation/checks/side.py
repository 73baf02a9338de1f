"""Pre-registration check of which femur: the plan's, the case's ``side`` and the one the views show.

A plan on the other femur is otherwise either refused for its target outside the case side's femur
(``side`` given) or, with no ``side``, navigates the plan's femur in views of the other hip and is
refused at the femur registration, blaming a view. The plan's femur is told from its path through
the femur labels (:func:`~fluoronav.navigation.planning.plan_side`); the views' from where the two
femoral-head landmarks project at the views' initial cameras.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fluoronav.navigation.case.model import NavigationCase
from fluoronav.navigation.case.view import CaseView
from fluoronav.navigation.checks.preflight_config import PreflightFinding, finding
from fluoronav.navigation.planning import plan_side

__all__ = [
    "check_side",
    "views_showing",
]


def views_showing(views: Sequence[CaseView], point_world: np.ndarray) -> list[str]:
    """The names of the views whose image holds ``point_world`` (3,) mm at its initial camera."""
    out = []
    for v in views:
        cam = v.camera
        if float(cam.to_camera(point_world)[2]) <= 0.0:
            continue
        u, w = cam.project(np.asarray(point_world, np.float64))
        if -0.5 <= u <= cam.cols - 0.5 and -0.5 <= w <= cam.rows - 0.5:
            out.append(v.name)
    return out


def check_side(case: NavigationCase) -> list[PreflightFinding]:
    """The plan's femur against the case's ``side`` and the views.

    Findings: ``side_inferred`` (a ``"note"``: no ``side`` given, the one inferred from the plan,
    for the record); ``plan_side`` (``"input"``): the plan's path runs through the other femur's
    label than ``side`` names; ``femur_in_views`` (``"input"``): the case side's femoral head lies
    outside every first view while the other side's lies inside one (the views show the other hip).
    """
    subject = f"plan {case.plan.target_name!r}"
    out: list[PreflightFinding] = []
    side = case.side
    if case.side_inferred_from is not None:
        text = f" not given: the {side} femur, inferred from the plan ({case.side_inferred_from})"
        out.append(finding("note", "'side'", text, "side_inferred"))
    else:
        found = plan_side(case.plan, case.volume)
        if found.by_label and found.side is not None and found.side != side:
            text = (
                f" is on the {found.side} femur ({found.how}), but the case's 'side' is {side!r}: check "
                f"the plan, or 'side' (\"{found.side}\" for this plan)"
            )
            return [finding("input", subject, text, "plan_side")]
    lms = case.volume.landmarks_world
    other = "right" if side == "left" else "left"
    head, other_head = lms.get(f"femoral_head_{side}"), lms.get(f"femoral_head_{other}")
    if head is None or other_head is None or views_showing(case.views, head):
        return out
    shown = views_showing(case.views, other_head)
    if shown:
        given = "inferred from the plan" if case.side_inferred_from is not None else "the case's 'side'"
        text = (
            f" is on the {side} femur ({given}), but no view shows it: the femoral_head_{side} landmark "
            f"projects outside every view, the femoral_head_{other} landmark into view {shown[0]!r}: "
            f"are the views of the other hip? Check the plan's side and the views"
        )
        out.append(finding("input", subject, text, "femur_in_views"))
    return out
