"""The checks a registration must pass before the robot may act on it.

A surgical navigation must know when it is wrong. Each CM registration is checked per view
(:mod:`fluoronav.registration.cm.diagnostics`): the registered landmarks against the detected ones and
the registered CM's outline against the image. A view that fails is left out and the CM registered
again without it while enough views remain; otherwise the navigation refuses. The verification's CM
is also checked against the robot's own account of the move: the first registration moved by the
nominal kinematics between the two joint readings must agree with what the verification images show
(:func:`fluoronav.navigation.pipeline.motion_consistency`); where it does not, a second start from
that prediction is tried, and a verification that still fails gives no corrective command.

The thresholds live in :class:`SafetyConfig`; docs/navigation.md ("Checks") gives the data they
were chosen on.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ["SafetyConfig", "ViewVerdict", "judge_cm_views", "judge_motion"]


@dataclass(frozen=True)
class SafetyConfig:
    """Thresholds of the registration checks.

    Attributes:
        max_landmark_residual_mm: a view's registered A or B may lie at most this far (mm at the
            detector) from the detected one.
        min_edge_ncc: a view's gradient NCC on the registered CM's outline must reach this.
        max_motion_tip_mm: the verification's CM tip (femur frame) may differ at most this much from
            the kinematic prediction (the robot's and the first registration's errors together).
        min_views: views that must pass for a CM registration to stand.
    """

    max_landmark_residual_mm: float = 2.0
    min_edge_ncc: float = 0.7
    max_motion_tip_mm: float = 3.0
    min_views: int = 2


@dataclass(frozen=True)
class ViewVerdict:
    """A view's checks: ``passed``, and the failed ``check`` with its ``detail`` otherwise."""

    view: str
    passed: bool
    check: str = ""
    detail: str = ""


def judge_cm_views(
    names: Sequence[str], diagnostics: Sequence[Mapping[str, Any]], config: SafetyConfig
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


def judge_motion(motion: Mapping[str, float], config: SafetyConfig) -> ViewVerdict | None:
    """None where the verification agrees with the robot's kinematics, else the failed check."""
    tip = float(motion["motion_tip_mm"])
    if tip <= config.max_motion_tip_mm:
        return None
    return ViewVerdict(
        "",
        False,
        "robot_motion",
        f"the CM the images show is {tip:.1f} mm from where the robot's kinematics put it "
        f"(at most {config.max_motion_tip_mm:g} mm)",
    )
