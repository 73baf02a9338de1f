"""Navigation-like scenes for detector training: the views and CM poses of the simulated navigation.

One scene is one image the navigation takes (:mod:`fluoronav.simulation.navigation.scenario`, ``loop``):
the patient and femur posed by the protocol's navigation trial (:func:`~fluoronav.simulation.protocol.
sample_trial`) and one of three stages. ``working``: the first images, the CM at the working pose above
the femoral head, the C-arm centred between the head and the CM. ``approach``: the CM on the plan's axis
(entry point → femoral head) with its tip short of the entry point. ``inserted``: its tip past the entry
point along the drilled path. Both are seen by the verification views: the C-arm slid to centre the
planned CM and the femoral head. Each view is the AP or one of the orbits. World frame: the CT frame
before the patient moved; ``femur`` is the CT frame of the femur.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch

from fluoronav.anatomy.volume import Volume
from fluoronav.geometry import se3
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.carm import centre_on, orbit_camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.navigation.planning import neck_entry_plan, planned_femur_from_cm
from fluoronav.simulation.navigation.scenario import SimulatedNavigationConfig
from fluoronav.simulation.protocol import Trial, perturb_about, sample_trial
from fluoronav.simulation.robot_scene import in_view, verification_view_centre, working_view_centre

__all__ = [
    "NAVIGATION_SIDE",
    "STAGES",
    "NavigationScene",
    "NavigationSceneSettings",
    "sample_navigation_scene",
]

#: the stages of the navigation a scene shows, in the order of ``NavigationSceneSettings.stage_weights``
STAGES = ("working", "approach", "inserted")
#: the femur the navigation works on (its simulator moves this one)
NAVIGATION_SIDE = "left"

_NAV = SimulatedNavigationConfig()


@dataclass(frozen=True)
class NavigationSceneSettings:
    """How navigation-like scenes are drawn (defaults: the simulated navigation's geometry)."""

    #: each control point U(range), degrees: the CM's whole range (the paper's data set)
    control_point_range_deg: tuple[float, float] = (-7.9, 7.9)
    #: orbit angles of the views beside the AP about the patient's long axis, degrees (the navigation's)
    orbit_deg: tuple[float, ...] = _NAV.orbit_deg
    #: relative frequency of the stages working, approach, inserted (:data:`STAGES`)
    stage_weights: tuple[float, float, float] = (1.0, 1.0, 1.0)
    #: approach: the CM tip this far short of the entry point along the plan's axis, U(range) mm
    approach_mm: tuple[float, float] = (2.0, 25.0)
    #: inserted: the CM tip this far past the entry point along the plan's axis, U(range) mm
    inserted_mm: tuple[float, float] = (0.0, 30.0)
    #: the robot's placement error: the CM moved by U(0, e) mm in a random direction
    move_error_mm: float = 2.0
    #: and turned by U(0, e) degrees about a random axis through its tip
    move_error_deg: float = 2.0
    #: the verification C-arm's centre misses its aim by U(−a, a) mm per axis (the navigation's)
    aim_error_mm: float = _NAV.aim_error_mm
    #: landmarks A, B and the tip at least this far inside the image edges, full-detector px
    #: (negative: up to that far outside; None: anywhere, the CM may leave the image)
    margin_px: float | None = 50.0
    #: scenes drawn at most to find one within ``margin_px``
    max_draws: int = 200

    def __post_init__(self) -> None:
        weights = np.asarray(self.stage_weights, np.float64)
        if weights.shape != (len(STAGES),) or np.any(weights < 0) or not weights.sum() > 0:
            raise ValueError(f"stage_weights must be {len(STAGES)} non-negative numbers, not all 0")
        for name in ("control_point_range_deg", "approach_mm", "inserted_mm"):
            lo, hi = getattr(self, name)
            if not lo <= hi:
                raise ValueError(f"{name} must be (low, high) with low <= high, got {(lo, hi)}")
        if self.approach_mm[0] < 0 or self.inserted_mm[0] < 0:
            raise ValueError("approach_mm and inserted_mm are distances from the entry point (>= 0)")
        for name in ("move_error_mm", "move_error_deg", "aim_error_mm"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.max_draws < 1:
            raise ValueError(f"max_draws must be >= 1, got {self.max_draws}")


@dataclass(frozen=True, eq=False)
class NavigationScene:
    """One navigation-like acquisition (world = the CT frame before the patient moved).

    Attributes:
        stage: one of :data:`STAGES`.
        view: ``"AP"`` or ``"orbit ±a"`` (the navigation's view names).
        camera: the nominal full-detector camera (world frame).
        world_from_patient: (4, 4) the pelvis (whole patient) motion.
        world_from_femur: (4, 4) the femur's total motion.
        world_from_cm: (4, 4) the CM base pose, mm.
        control_points_deg: (n,) the CM's shape, degrees.
        insertion_depth_mm: the plan's tip past the entry point before the placement error, mm
            (negative: short of it); NaN for the working stage.
        trial: the protocol's navigation trial the anatomy and the first C-arm come from.
        cm_config: the CM's geometry.
    """

    stage: str
    view: str
    camera: Camera
    world_from_patient: np.ndarray
    world_from_femur: np.ndarray
    world_from_cm: np.ndarray
    control_points_deg: np.ndarray
    insertion_depth_mm: float
    trial: Trial
    cm_config: CMConfig


def _cm_points(kin: CMKinematics, cp: np.ndarray) -> np.ndarray:
    """(3, 3) A, B and the tip in the CM frame, mm."""
    cpt = torch.as_tensor(cp, dtype=torch.float64)
    return np.concatenate([kin.landmarks_cm(cpt).numpy(), kin.tip_cm(cpt).numpy()[None]])


def _placed_on_plan(
    trial: Trial,
    cp: np.ndarray,
    stage: str,
    s: NavigationSceneSettings,
    kin: CMKinematics,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, float]:
    """An approach or inserted CM: (world_from_cm (4, 4), the verification views' centre (3,) world,
    the plan's insertion depth mm)."""
    plan = neck_entry_plan(trial.entry_ct, trial.femoral_head_ct, cp)
    roll = float(rng.uniform(0.0, 360.0))  # the plan leaves the roll free
    femur_from_target = planned_femur_from_cm(plan, kinematics=kin, roll_deg=roll)
    # the person aims the C-arm between the planned CM and the femoral head (the loop's verification)
    centre = se3.apply(
        trial.world_from_femur, verification_view_centre(femur_from_target, trial.femoral_head_ct)
    )
    centre = centre + rng.uniform(-s.aim_error_mm, s.aim_error_mm, 3)
    sign, depth_range = (-1.0, s.approach_mm) if stage == "approach" else (1.0, s.inserted_mm)
    depth = sign * float(rng.uniform(*depth_range))
    placed = planned_femur_from_cm(
        dataclasses.replace(plan, insertion_depth_mm=depth), kinematics=kin, roll_deg=roll
    )
    W = trial.world_from_femur @ placed
    tip = se3.apply(W, kin.tip_cm(torch.as_tensor(cp, dtype=torch.float64)).numpy())
    W = perturb_about(
        W,
        tip,
        rng,
        rotation_deg=float(rng.uniform(0.0, s.move_error_deg)),
        translation_mm=float(rng.uniform(0.0, s.move_error_mm)),
    )
    return W, centre, depth


def _draw(
    volume: Volume, rng: np.random.Generator, s: NavigationSceneSettings, kin: CMKinematics, stage: str
) -> NavigationScene:
    """One scene of ``stage``, whether or not its CM is in view."""
    trial = sample_trial("navigation", volume, rng, side=NAVIGATION_SIDE, cm_config=kin.config)
    cp = rng.uniform(*s.control_point_range_deg, size=kin.config.n_control_points)
    # the first set's AP: the trial's C-arm slid to centre the femoral head and the working CM
    centre = working_view_centre(trial)
    ap = centre_on(trial.cameras[0], centre)
    if stage == "working":
        W, depth = trial.world_from_cm[0], math.nan
    else:
        W, centre, depth = _placed_on_plan(trial, cp, stage, s, kin, rng)
        ap = centre_on(ap, centre)  # the verification C-arm slid from the first AP
    k = int(rng.integers(1 + len(s.orbit_deg)))
    camera = ap if k == 0 else orbit_camera(ap, angle_deg=s.orbit_deg[k - 1], isocenter_world=centre)
    return NavigationScene(
        stage=stage,
        view="AP" if k == 0 else f"orbit {s.orbit_deg[k - 1]:+g}",
        camera=camera,
        world_from_patient=trial.world_from_patient,
        world_from_femur=trial.world_from_femur,
        world_from_cm=np.asarray(W, np.float64),
        control_points_deg=cp,
        insertion_depth_mm=depth,
        trial=trial,
        cm_config=kin.config,
    )


def sample_navigation_scene(
    volume: Volume,
    rng: np.random.Generator,
    *,
    settings: NavigationSceneSettings | None = None,
    cm_config: CMConfig | None = None,
) -> NavigationScene:
    """Draw one navigation-like scene (module docstring), redrawn until its CM is in view.

    The stage is drawn once (the stages keep ``settings.stage_weights``), the rest until the CM is
    within ``settings.margin_px``: far approaches leave the verification views, which the navigation
    aims at the plan, so their distances are skewed to the near end of ``approach_mm``.

    Args:
        volume: the patient (labels and landmarks ``femoral_head_left``, ``entry_left``).
        rng: every draw, in a fixed order (the stage, then per draw the trial, the shape, the
            placement, the view).
        settings: the ranges (default :class:`NavigationSceneSettings`).
        cm_config: the CM's geometry (default :class:`CMConfig`).

    Raises:
        ValueError: no scene with the CM within ``settings.margin_px`` in ``settings.max_draws`` draws,
            or the volume lacks the landmarks.
    """
    s = settings or NavigationSceneSettings()
    kin = CMKinematics(cm_config or CMConfig())
    weights = np.asarray(s.stage_weights, np.float64)
    stage = STAGES[int(rng.choice(len(STAGES), p=weights / weights.sum()))]
    for _ in range(s.max_draws):
        scene = _draw(volume, rng, s, kin, stage)
        if s.margin_px is None:
            return scene
        pts_cm = _cm_points(kin, scene.control_points_deg)
        if in_view(scene.camera, scene.world_from_cm, pts_cm, s.margin_px):
            return scene
    raise ValueError(f"no navigation scene with the CM within margin_px={s.margin_px} in {s.max_draws} draws")
