"""A CM registration case: the views, the initial estimate and the settings, with optional truth.

:class:`CMCase` is what :func:`~fluoronav.registration.cm.problem.register_cm` needs; case files
(``fluoronav register``) and simulated cases
(:func:`fluoronav.simulation.cm_case.simulate_cm_case`, assembled by
:func:`~fluoronav.simulation.cm_case.cm_case_from_simulation`)
give one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fluoronav.registration.cm.config import CMRegistrationConfig
from fluoronav.registration.cm.views import CMView

__all__ = ["CMCase"]


@dataclass(frozen=True, eq=False)
class CMCase:
    """Everything :func:`~fluoronav.registration.cm.register_cm` needs, plus optional ground truth.

    Attributes:
        workflow: "single-view", "multi-view" or "multi-cm"
            (:data:`~fluoronav.simulation.cm_case.CM_WORKFLOWS`).
        views: the images.
        initial_world_from_cm: (4, 4) initial pose (multiple-CM: of the CM in ``views[0]``).
        initial_control_points_deg: (5,).
        base_from_cm: (M, 4, 4) multiple-CM relative poses (robot FK × hand-eye), else None.
        world_from_cm_true: (M, 4, 4) true poses or None; control_points_true_deg: (5,) or None.
        config: registration settings.
        source: file the case came from ("" for simulated cases).
    """

    workflow: str
    views: list[CMView]
    initial_world_from_cm: np.ndarray
    initial_control_points_deg: np.ndarray
    base_from_cm: np.ndarray | None = None
    world_from_cm_true: np.ndarray | None = None
    control_points_true_deg: np.ndarray | None = None
    config: CMRegistrationConfig = field(default_factory=CMRegistrationConfig)
    source: str = ""
