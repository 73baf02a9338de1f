"""What a study's trials need of a CT given as a file, checked once before any trial runs.

A study on a CT without the labels and landmarks its simulated scene needs would fail every trial
on it; :func:`check_study_ct` refuses it up front with one :class:`~fluoronav.errors.InputError`
naming what is needed and what is missing. The phantom has all of them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError

__all__ = ["HANDEYE_CT", "NAVIGATION_CT", "TRIAL_CT", "StudyCTNeeds", "check_study_ct"]


@dataclass(frozen=True)
class StudyCTNeeds:
    """The labels and landmarks a study's trials need of its CT, and why (the error's opening)."""

    labels: tuple[str, ...]
    landmarks: tuple[str, ...]
    why: str


#: the registration studies: the simulator moves the left femur by its label, the protocol aims the
#: C-arm and the CM at its landmarks (:func:`~fluoronav.simulation.protocol.sample_trial`)
TRIAL_CT = StudyCTNeeds(
    ("femur_left",), ("femoral_head_left", "entry_left"), "a study's trials move the left femur and aim at it"
)
#: the hand-eye study's robot scene (:mod:`fluoronav.simulation.robot_scene`): the same femur and aim
HANDEYE_CT = StudyCTNeeds(
    ("femur_left",),
    ("femoral_head_left", "entry_left"),
    "the hand-eye study's scene moves the left femur and aims the C-arm and the CM at it",
)
#: the navigation study: the same scene, a plan from the entry point along the neck to the head
#: (:mod:`fluoronav.simulation.navigation.scenario`), and the pipeline registers pelvis and femur
NAVIGATION_CT = StudyCTNeeds(
    ("pelvis", "femur_left"),
    ("femoral_head_left", "entry_left"),
    "the navigation study's scene moves the left femur and plans a path into it, and its navigation "
    "registers the pelvis and the femur",
)


def _has_label(volume: Volume, name: str) -> bool:
    value = volume.label_value(name)
    return volume.labels is not None and value is not None and bool(np.any(volume.labels == value))


def check_study_ct(volume: Volume, source: str, needs: StudyCTNeeds) -> None:
    """Refuse, before any trial, a CT without the labels and landmarks of ``needs`` (an
    :class:`~fluoronav.errors.InputError` from ``source`` naming them), rather than fail every trial."""
    missing = [f"label {name!r}" for name in needs.labels if not _has_label(volume, name)]
    missing += [f"landmark {name!r}" for name in needs.landmarks if name not in volume.landmarks_world]
    if missing:
        needed = [f"label {n!r}" for n in needs.labels] + [f"landmark {n!r}" for n in needs.landmarks]
        raise InputError(
            source,
            f"{needs.why}, so the CT needs {', '.join(needed)}; this one lacks {', '.join(missing)} "
            "(labels and landmarks: docs/data-formats.md)",
        )
