"""Surgical plans: where the CM should go relative to the femur, and the planned CM pose.

A plan file (JSON, CT world frame: LPS mm, or RAS with ``"coordinate_system": "RAS"``) holds
``target_name``, ``entry_point_mm``, ``direction`` (the insertion direction, normalised on reading),
optional ``insertion_depth_mm`` (default 0), ``bending_direction`` and ``control_points_deg``
(docs/robot-and-calibration.md, "Plan file"). The planned CM base frame has +z along ``direction``
and +y along the part of ``bending_direction`` orthogonal to it; without it the CM's roll is free
and the navigation chooses it (:func:`fluoronav.navigation.targeting.least_motion_target`). The CM
**tip** is placed at ``entry_point + insertion_depth · direction``. A 3D Slicer markups file is a plan too
(:func:`plan_from_markups`: a Line, or points labelled ``entry`` and ``target``). Femur frame: the plan's CT
world frame (the femur registration estimates ``carm_from_femur``), or ``femur_from_world``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fluoronav.anatomy.markups import read_markup_nodes
from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError
from fluoronav.geometry import se3
from fluoronav.manipulator.kinematics import CMKinematics

__all__ = [
    "Plan",
    "PlanSide",
    "load_plan",
    "plan_from_dict",
    "plan_from_markups",
    "plan_side",
    "planned_femur_from_cm",
    "save_plan",
]

_KNOWN_KEYS = {
    "target_name",
    "entry_point_mm",
    "direction",
    "insertion_depth_mm",
    "bending_direction",
    "control_points_deg",
    "coordinate_system",
}


@dataclass(frozen=True)
class Plan:
    """A planned CM target.

    Attributes:
        target_name: label of the target (e.g. a landmark name).
        entry_point_world_mm: (3,) entry point, world (LPS) mm.
        direction_world: (3,) unit insertion direction, world.
        insertion_depth_mm: distance of the CM tip beyond the entry point along the direction.
        bending_direction_world: (3,) or None; the CM +y axis is its part orthogonal to ``direction``.
            None leaves the roll about the insertion axis free (:attr:`roll_free`).
        control_points_deg: (n,) or None; CM shape at the target (straight when None).
    """

    target_name: str
    entry_point_world_mm: np.ndarray
    direction_world: np.ndarray
    insertion_depth_mm: float = 0.0
    bending_direction_world: np.ndarray | None = None
    control_points_deg: np.ndarray | None = None

    @property
    def roll_free(self) -> bool:
        """True where the plan does not fix the CM's roll about the insertion axis.

        Notes:
            A plan that fixes no bending direction says nothing about the roll; fixing it to a world
            axis anyway can cost the robot a large turn of its joints near the patient.
        """
        return self.bending_direction_world is None

    @property
    def tip_target_world_mm(self) -> np.ndarray:
        """(3,) where the CM tip should be."""
        return self.entry_point_world_mm + self.insertion_depth_mm * self.direction_world

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "target_name": self.target_name,
            "entry_point_mm": [float(v) for v in self.entry_point_world_mm],
            "direction": [float(v) for v in self.direction_world],
            "insertion_depth_mm": float(self.insertion_depth_mm),
            "coordinate_system": "LPS",
        }
        if self.bending_direction_world is not None:
            d["bending_direction"] = [float(v) for v in self.bending_direction_world]
        if self.control_points_deg is not None:
            d["control_points_deg"] = [float(v) for v in self.control_points_deg]
        return d


def _vector(d: Mapping[str, Any], key: str, source: str, n: int | None = 3) -> np.ndarray:
    value = d[key]
    if not isinstance(value, list | tuple) or (n is not None and len(value) != n):
        raise InputError(source, f"'{key}' must be a list of {n if n is not None else 'some'} numbers")
    try:
        arr = np.array([float(v) for v in value], dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(source, f"'{key}' must contain only numbers") from None
    if not np.all(np.isfinite(arr)):
        raise InputError(source, f"'{key}' must contain finite numbers")
    return arr


def plan_from_dict(d: Mapping[str, Any], *, source: str | Path = "<plan>") -> Plan:
    """Validate a plan mapping (the JSON object) → :class:`Plan`; errors name ``source``."""
    src = str(source)
    if not isinstance(d, Mapping):
        raise InputError(src, "a plan must be a JSON object")
    unknown = sorted(set(d) - _KNOWN_KEYS)
    if unknown:
        raise InputError(src, f"unknown key(s) {unknown}; allowed: {sorted(_KNOWN_KEYS)}")
    for key in ("target_name", "entry_point_mm", "direction"):
        if key not in d:
            raise InputError(src, f"missing '{key}'")
    name = d["target_name"]
    if not isinstance(name, str) or not name.strip():
        raise InputError(src, "'target_name' must be a non-empty string")
    system = d.get("coordinate_system", "LPS")
    if system not in ("LPS", "RAS"):
        raise InputError(src, f"'coordinate_system' must be 'LPS' or 'RAS', got {system!r}")
    flip = np.array([-1.0, -1.0, 1.0]) if system == "RAS" else np.ones(3)
    entry = _vector(d, "entry_point_mm", src) * flip
    direction = _vector(d, "direction", src) * flip
    norm = float(np.linalg.norm(direction))
    if norm < 1e-9:
        raise InputError(src, "'direction' must be a non-zero vector")
    direction = direction / norm
    depth = d.get("insertion_depth_mm", 0.0)
    if isinstance(depth, bool) or not isinstance(depth, int | float) or not math.isfinite(depth) or depth < 0:
        raise InputError(src, "'insertion_depth_mm' must be a finite number ≥ 0")
    bend = None
    if d.get("bending_direction") is not None:
        bend = _vector(d, "bending_direction", src) * flip
        if np.linalg.norm(np.cross(bend, direction)) < 1e-6 * max(1.0, float(np.linalg.norm(bend))):
            raise InputError(src, "'bending_direction' must not be parallel to 'direction'")
    cps = None
    if d.get("control_points_deg") is not None:
        cps = _vector(d, "control_points_deg", src, n=None)
    return Plan(
        target_name=name,
        entry_point_world_mm=entry,
        direction_world=direction,
        insertion_depth_mm=float(depth),
        bending_direction_world=bend,
        control_points_deg=cps,
    )


_POINT_LIST_TYPES = ("Fiducial", "PointList")


def plan_from_markups(path: str | Path) -> Plan:
    """A plan from a Slicer ``.mrk.json`` file (positions in LPS, mm).

    The file must hold exactly one of: a ``Line`` markup with two placed control points (entry
    point, then a point further along the insertion direction), or a point list (``Fiducial``)
    with points labelled ``entry`` and ``target`` (case-insensitive; direction entry → target).
    Other markups in the file are ignored. ``target_name`` is the markup's name; the insertion
    depth is 0.

    Raises:
        InputError: an unreadable or malformed markups file, no or several such markups, a line
            without exactly two placed points, or coincident points (message names the file).
    """
    p = Path(path)
    nodes = read_markup_nodes(p)
    lines = [n for n in nodes if n.type == "Line"]
    lists = []
    for n in nodes:
        if n.type not in _POINT_LIST_TYPES:
            continue
        keys = [label.strip().lower() for label in n.labels]
        if "entry" in keys or "target" in keys:
            if keys.count("entry") != 1 or keys.count("target") != 1:
                raise InputError(
                    p, f"point list {n.name!r} needs one point labelled 'entry' and one 'target'"
                )
            lists.append((n, n.points_lps[keys.index("entry")], n.points_lps[keys.index("target")]))
    if len(lines) + len(lists) != 1:
        raise InputError(
            p,
            f"a plan needs exactly one Line markup or one point list with 'entry' and 'target' points; "
            f"found {len(lines)} line(s) and {len(lists)} such point list(s)",
        )
    if lines:
        node = lines[0]
        if node.points_lps.shape[0] != 2:
            raise InputError(p, f"line {node.name!r} has {node.points_lps.shape[0]} placed points, needs 2")
        entry, further = node.points_lps[0], node.points_lps[1]
    else:
        node, entry, further = lists[0]
    direction = further - entry
    norm = float(np.linalg.norm(direction))
    if norm < 1e-9:
        raise InputError(p, f"markup {node.name!r}: the two points coincide, no insertion direction")
    return Plan(
        target_name=node.name,
        entry_point_world_mm=np.array(entry, dtype=np.float64),
        direction_world=direction / norm,
    )


def load_plan(path: str | Path) -> Plan:
    """Read and validate a plan file (JSON, or a Slicer ``.mrk.json`` as :func:`plan_from_markups`);
    every problem raises :class:`InputError` naming the file."""
    p = Path(path)
    if p.name.lower().endswith(".mrk.json"):
        return plan_from_markups(p)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(p, f"cannot read plan file ({exc.__class__.__name__})") from None
    if not text.strip():
        raise InputError(p, "empty plan file")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(p, f"not valid JSON (line {exc.lineno}: {exc.msg})") from None
    return plan_from_dict(data, source=p)


def save_plan(plan: Plan, path: str | Path) -> Path:
    """Write ``plan`` as JSON (LPS) and return the path."""
    p = Path(path)
    p.write_text(json.dumps(plan.to_dict(), indent=2) + "\n", encoding="utf-8")
    return p


@dataclass(frozen=True)
class PlanSide:
    """The femur a plan is on, and how that was told.

    Attributes:
        side: ``"left"`` or ``"right"``; None where the CT has neither femur label nor head landmark.
        how: one phrase saying why (for messages and the log).
        by_label: whether the plan's path runs through that femur's label (else: the nearest head).
    """

    side: str | None
    how: str
    by_label: bool = False


#: the plan's path is sampled this far beyond its tip target, mm (into the femoral neck)
_PATH_BEYOND_MM = 20.0


def plan_side(plan: Plan, volume: Volume) -> PlanSide:
    """Which femur ``plan`` is on: the ``femur_<side>`` label its path runs through, else the
    ``femoral_head_<side>`` landmark nearest its entry point.

    The path is sampled every millimetre from the entry point to
    :data:`_PATH_BEYOND_MM` beyond the tip target along the insertion direction (a core
    decompression's tip rests on the entry, its path goes on into the neck); the label that holds
    most samples wins.
    """
    femurs = {s: volume.label_value(f"femur_{s}") for s in ("left", "right")}
    if volume.labels is not None and any(v is not None for v in femurs.values()):
        depth = float(plan.insertion_depth_mm) + _PATH_BEYOND_MM
        t = np.arange(0.0, depth + 0.5, 1.0)
        pts = plan.entry_point_world_mm + t[:, None] * plan.direction_world
        ijk = np.rint(pts @ volume.index_from_world[:3, :3].T + volume.index_from_world[:3, 3]).astype(int)
        kji = ijk[:, ::-1]
        on = np.all((kji >= 0) & (kji < np.asarray(volume.labels.shape)), axis=1)
        values = volume.labels[tuple(kji[on].T)]
        hits = {s: int(np.count_nonzero(values == v)) for s, v in femurs.items() if v is not None}
        best = max(hits, key=lambda s: hits[s])
        if hits[best] > 0 and list(hits.values()).count(hits[best]) == 1:
            return PlanSide(best, f"its path runs through the femur_{best} label", by_label=True)
    lms = volume.landmarks_world
    heads = {s: lms[f"femoral_head_{s}"] for s in ("left", "right") if f"femoral_head_{s}" in lms}
    if not heads:
        return PlanSide(None, "the CT has no femur label on the plan's path and no femoral head landmark")
    near = min(heads, key=lambda s: float(np.linalg.norm(heads[s] - plan.entry_point_world_mm)))
    return PlanSide(near, f"the femoral_head_{near} landmark is the nearest to its entry point")


def _frame_axes(direction: np.ndarray, bending: np.ndarray | None) -> np.ndarray:
    """(3, 3) rotation with columns x, y, z: z = direction, y ⟂ z towards ``bending``."""
    z = direction / np.linalg.norm(direction)
    if bending is None:
        bending = np.eye(3)[int(np.argmin(np.abs(z)))]
    y = bending - np.dot(bending, z) * z
    y = y / np.linalg.norm(y)
    x = np.cross(y, z)
    return np.stack([x, y, z], axis=1)


def neck_entry_plan(
    entry_ct_mm: np.ndarray, femoral_head_ct_mm: np.ndarray, control_points_deg: np.ndarray | None = None
) -> Plan:
    """The core-decompression plan of the studies and the demo (femur = CT frame): the CM tip on the
    entry point, its axis along the femoral neck towards the head centre."""
    direction = np.asarray(femoral_head_ct_mm, np.float64) - np.asarray(entry_ct_mm, np.float64)
    return Plan(
        target_name="entry",
        entry_point_world_mm=np.asarray(entry_ct_mm, np.float64),
        direction_world=direction / np.linalg.norm(direction),
        control_points_deg=None if control_points_deg is None else np.asarray(control_points_deg),
    )


def planned_femur_from_cm(
    plan: Plan,
    *,
    femur_from_world: np.ndarray | None = None,
    kinematics: CMKinematics | None = None,
    roll_deg: float = 0.0,
) -> np.ndarray:
    """The CM base pose in the femur frame that realises ``plan`` → (4, 4) ``femur_from_cm``.

    Rotation: CM +z along the planned direction, +y towards the bending direction. Translation:
    chosen so that the CM tip (``kinematics.tip_cm`` at the planned control points, straight by
    default) lands on ``plan.tip_target_world_mm``.

    Args:
        plan: the plan (world coordinates).
        femur_from_world: (4, 4) femur frame from the CT world frame; identity by default.
        kinematics: CM kinematics (paper CM by default).
        roll_deg: the pose turned by this angle (right-handed, degrees) about the line through the
            tip target along the direction: the roll family of a plan whose roll is free
            (:attr:`Plan.roll_free`). The tip target and the insertion axis stay where they are,
            for a bent CM too. 0 gives the plan's own pose exactly.
    """
    kin = kinematics or CMKinematics()
    n_cp = kin.config.n_control_points
    cps = np.zeros(n_cp) if plan.control_points_deg is None else plan.control_points_deg
    if cps.shape != (n_cp,):
        raise ValueError(f"plan has {cps.shape[0]} control points, the CM model needs {n_cp}")
    tip_cm = kin.tip_cm(torch.as_tensor(cps, dtype=torch.float64)).numpy()
    R = _frame_axes(plan.direction_world, plan.bending_direction_world)
    if roll_deg != 0.0:  # R's +z is the direction: a turn about it is a turn about the CM's own z
        c, s = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
        R = R @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    world_from_cm = se3.make(R, plan.tip_target_world_mm - R @ tip_cm)
    F = (
        np.eye(4)
        if femur_from_world is None
        else se3.as_transform_array(femur_from_world, "femur_from_world")
    )
    return F @ world_from_cm
