"""Navigation cases: everything ``fluoronav navigate`` needs, as data.

A case is the CT (with labels and landmarks), the plan, the CM, the robot's state while imaging and
its hand-eye matrix, and the C-arm views; optionally the views taken after the robot moved
(verification). On disk it is one JSON file whose paths are relative to it (docs/data-formats.md,
"Navigation case"; its models in :mod:`.schema`); :func:`load_navigation_case` reads and validates
it, :func:`write_navigation_case` writes one (the demo's simulated cases).

Frames: ``ct`` is the CT's physical frame (LPS, mm, as SimpleITK reads it). Every view's camera holds
``camera_from_ct`` as known before registration, which the pelvis registration corrects per view;
``"dicom"`` cameras are placed by ``isocenter_ct_mm`` (default: the femoral head landmark; :mod:`.parse`).
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np

from fluoronav.anatomy.io import load_ct, resolve_ct, save_volume
from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError, read_json_object
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.robot import UR10, SerialRobot, robot_to_dict
from fluoronav.navigation.case.parse import (
    keyed,
    parse_cm_config,
    parse_joints,
    parse_robot,
    parse_views,
    readings,
    require_file,
    write_views,
)
from fluoronav.navigation.case.schema import (
    COMMENT_KEYS,
    CaseFile,
    RobotEntry,
    Side,
    Verification,
    is_comment_key,
    validate_case,
)
from fluoronav.navigation.case.view import CaseView
from fluoronav.navigation.planning import Plan, load_plan, plan_from_dict, plan_side, save_plan

__all__ = [
    "CASE_KEYS",
    "COMMENT_KEYS",
    "CaseView",
    "NavigationCase",
    "VerificationViews",
    "load_navigation_case",
    "write_navigation_case",
]

logger = logging.getLogger(__name__)

#: Top-level keys of a navigation case file (besides the comment keys :data:`COMMENT_KEYS`).
CASE_KEYS = tuple(CaseFile.model_fields)


@dataclass(frozen=True, eq=False)
class VerificationViews:
    """The images taken after the robot moved to the commanded pose.

    Attributes:
        joints_deg: (n_joints,) the robot's joint readings while these images were taken.
        views: the images; their cameras' ``camera_from_ct`` is again only an initial estimate.
    """

    joints_deg: np.ndarray
    views: tuple[CaseView, ...]


@dataclass(frozen=True, eq=False)
class NavigationCase:
    """A navigation case (module docstring).

    Attributes:
        volume: the CT in HU with labels ``pelvis`` and ``femur_<side>`` and landmark
            ``femoral_head_<side>`` (``pelvis_center`` optional).
        plan: the planned target in the CT frame.
        side: the femur ("left" / "right") the plan is in: the case file's ``side``, else inferred
            from the plan.
        cm_config: the CM's geometry.
        fbg_control_points_deg: (n_control_points,) the CM shape from its FBG sensor, or None (then
            straight).
        fbg_sigma_deg: the FBG reading's stated accuracy, one standard deviation per control point
            (degrees): the CM registration holds its shape to the reading with a Gaussian prior of
            this σ; None: the reading is taken as accurate to about ±0.5° (the paper's simulated
            reading) and the shape is free within ±1° of it.
        robot: the kinematic model the robot controller uses.
        joints_deg: (n_joints,) joint readings while the views were taken.
        ee_from_cm: (4, 4) hand-eye matrix (mm).
        views: the C-arm images taken with the robot at ``joints_deg``.
        verification: images after the move, or None.
        source: the case file (for messages), or None for a case built in memory.
        side_inferred_from: where the case file gives no ``side``: how it was inferred from the plan
            (:func:`~fluoronav.navigation.planning.plan_side`; the preflight records it); None where
            given.
    """

    volume: Volume
    plan: Plan
    side: str
    cm_config: CMConfig
    fbg_control_points_deg: np.ndarray | None
    robot: SerialRobot
    joints_deg: np.ndarray
    ee_from_cm: np.ndarray
    views: tuple[CaseView, ...]
    verification: VerificationViews | None = None
    source: Path | None = None
    fbg_sigma_deg: float | None = None
    side_inferred_from: str | None = None


# ----- reading ---------------------------------------------------------------------------------
def _volume(spec: CaseFile, src: str, root: Path) -> tuple[Volume, str]:
    """The CT with labels and landmarks → (volume, the ``ct`` value for messages)."""
    if spec.is_phantom():
        seed = 0 if spec.phantom_seed is None else spec.phantom_seed
        return resolve_ct("phantom", seed=seed), "phantom"
    ct = spec.ct
    if not (root / ct).exists():
        raise InputError(src, f"'ct' file not found: {ct}")
    labels = landmarks = None
    if spec.labels is not None:
        labels = require_file(src, root, spec.labels, "'labels'")
    if spec.landmarks is not None:
        landmarks = require_file(src, root, spec.landmarks, "'landmarks'")
    try:
        volume = load_ct(root / ct, labels_path=labels, landmarks_path=landmarks)
    except InputError as exc:  # name the key of the file at fault
        key = {str(labels): "'labels'", str(landmarks): "'landmarks'"}.get(exc.source, "'ct'")
        raise InputError(src, f"{key}: {exc.source}: {exc.problem}") from None
    return volume, ct


def _side(side: str | None, volume: Volume, plan: Plan, src: str, ct: str) -> tuple[str, str | None]:
    """The plan's side (given, or the femur the plan is on: :func:`plan_side`), its anatomy checked
    → (side, how it was inferred; None where given)."""
    lms = volume.landmarks_world
    inferred = None
    if side is None:
        found = plan_side(plan, volume)
        if found.side is None:
            raise InputError(
                src, f"'ct' {ct} has no landmark femoral_head_left or femoral_head_right (give 'landmarks')"
            )
        side, inferred = found.side, found.how
        logger.info("%s: side %s inferred from the plan (%s)", src, side, inferred)
    missing = []
    for label in ("pelvis", f"femur_{side}"):
        value = volume.label_value(label)
        if volume.labels is None or value is None or not np.any(volume.labels == value):
            missing.append(f"label {label!r}")
    if f"femoral_head_{side}" not in lms:
        missing.append(f"landmark 'femoral_head_{side}'")
    if missing:
        raise InputError(
            src,
            f"'ct' {ct} lacks {', '.join(missing)} (navigating the {side} femur needs labels 'pelvis' "
            f"and 'femur_{side}' and landmark 'femoral_head_{side}')",
        )
    return str(side), inferred


def load_navigation_case(path: str | Path) -> NavigationCase:
    """Read and validate a navigation case file (docs/data-formats.md, "Navigation case").

    Args:
        path: the case JSON; paths inside are relative to its folder.

    Returns:
        the case, with ``source`` = ``path``; cameras hold ``camera_from_ct``.

    Raises:
        InputError: for any missing, unreadable or inconsistent entry, naming the case file and the
            key (and the other file at fault, where there is one). Unknown top-level keys are errors
            (except ``description``, ``notes`` and keys starting with ``_``).
    """
    p = Path(path)
    src = str(p)
    root = p.parent
    spec = validate_case(read_json_object(p, what="navigation case"), src)
    volume, ct = _volume(spec, src, root)
    plan = _plan(spec.plan, src, root)
    cm_config = parse_cm_config(spec.cm, src, root)
    n_cp = cm_config.n_control_points
    if plan.control_points_deg is not None and len(plan.control_points_deg) != n_cp:
        raise InputError(
            src, f"'plan' control_points_deg has {len(plan.control_points_deg)} values, the CM has {n_cp}"
        )
    fbg = None
    if spec.fbg_control_points_deg is not None:
        fbg = readings(
            spec.fbg_control_points_deg, "fbg_control_points_deg", src, n=n_cp, why=f"the CM has {n_cp}"
        )
    fbg_sigma = None if spec.fbg_sigma_deg is None else float(spec.fbg_sigma_deg)
    side, side_inferred_from = _side(spec.side, volume, plan, src, ct)
    robot, joints, ee_from_cm = parse_robot(spec.robot, src, root)

    if spec.isocenter_ct_mm is not None:
        iso = np.asarray(spec.isocenter_ct_mm, dtype=np.float64)
    else:
        iso = np.asarray(volume.landmarks_world[f"femoral_head_{side}"], dtype=np.float64)
    views = parse_views(spec.views, key="views", src=src, root=root, isocenter_ct_mm=iso)
    verification = None
    if spec.verification is not None:
        verification = _verification(spec.verification, robot, src, root, iso)
    n_verify = 0 if verification is None else len(verification.views)
    logger.info("%s: %s side, %d view(s), %d verification view(s)", src, side, len(views), n_verify)
    return NavigationCase(
        volume=volume,
        plan=plan,
        side=side,
        cm_config=cm_config,
        fbg_control_points_deg=fbg,
        robot=robot,
        joints_deg=joints,
        ee_from_cm=ee_from_cm,
        views=views,
        verification=verification,
        source=p,
        fbg_sigma_deg=fbg_sigma,
        side_inferred_from=side_inferred_from,
    )


def _plan(value: str | dict[str, Any], src: str, root: Path) -> Plan:
    """``plan``: a plan file or the plan object inline (both checked by the planning module)."""
    if isinstance(value, dict):
        with keyed(src, "'plan'"):
            return plan_from_dict(value, source=src)
    plan_path = require_file(src, root, value, "'plan'")
    with keyed(src, "'plan'"):
        return load_plan(plan_path)


def _verification(
    spec: Verification, robot: SerialRobot, src: str, root: Path, isocenter_ct_mm: np.ndarray
) -> VerificationViews:
    """``verification``: its joint readings (for ``robot``) and its views."""
    return VerificationViews(
        joints_deg=parse_joints(spec.joints_deg, "verification.joints_deg", robot, src),
        views=parse_views(
            spec.views,
            key="verification.views",
            src=src,
            root=root,
            isocenter_ct_mm=isocenter_ct_mm,
            default_prefix="verify",
        ),
    )


# ----- writing ---------------------------------------------------------------------------------
def _relative(path: Path, directory: Path) -> str:
    try:
        return Path(os.path.relpath(path.resolve(), directory.resolve())).as_posix()
    except ValueError:  # another drive
        return str(path.resolve())


def write_navigation_case(
    case: NavigationCase,
    directory: str | Path,
    *,
    ct_path: str | None = None,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write ``case`` as ``directory/navigation.json`` and the files it names.

    Files: ``ct.nii.gz`` (+ ``ct_labels.nii.gz``, ``ct.labels.json``, ``ct_landmarks.json``, as
    :func:`~fluoronav.anatomy.io.save_volume` writes them) unless ``ct_path`` is given,
    ``plan.json``, ``robot_dh.json`` (only for a robot other than the UR10), per view
    ``<name>.npz`` (``image`` float32, ``pixel_spacing_mm`` when the camera has one),
    ``<name>_camera.json`` (``camera_from_world`` = camera_from_ct) and ``<name>_mask.png``;
    verification views likewise with the prefix ``verification_``. The CM config is written inline.
    The file is the dump of :class:`~fluoronav.navigation.case.schema.CaseFile` (not validated here:
    the reader checks); :func:`load_navigation_case` of it gives back an equal case (float32 images,
    NIfTI geometry to float32 precision).

    Args:
        case: the case.
        directory: created if needed.
        ct_path: an existing CT (as ``ct`` reads it, or ``"phantom"``) holding ``case.volume``, with
            its label and landmark siblings; the case then points to it (relative to ``directory``
            where possible) instead of writing the volume.
        extra: more top-level keys: comment keys (``description``, ``notes``, ``_…``) or case keys
            the writer does not set itself (``phantom_seed``, ``isocenter_ct_mm``).

    Returns:
        the path of ``navigation.json``.

    Raises:
        ValueError: ``extra`` keys that the reader would reject or that the writer sets itself; a
            view with a mask but no landmarks.
        FileNotFoundError: ``ct_path`` does not exist.
    """
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    ct = _write_ct(case.volume, out, ct_path)
    plan = save_plan(case.plan, out / "plan.json").name
    fbg = None if case.fbg_control_points_deg is None else [float(v) for v in case.fbg_control_points_deg]
    sigma = None if fbg is None or case.fbg_sigma_deg is None else float(case.fbg_sigma_deg)
    robot = _write_robot(case, out)
    views = write_views(case.views, out)
    verification = None
    if case.verification is not None:
        verification = Verification.model_construct(
            joints_deg=[float(v) for v in case.verification.joints_deg],
            views=write_views(case.verification.views, out, prefix="verification_"),
        )
    spec = CaseFile.model_construct(
        ct=ct["ct"],
        labels=ct.get("labels"),
        landmarks=ct.get("landmarks"),
        plan=plan,
        side=cast(Side, case.side),  # written as the case holds it
        cm=case.cm_config,
        fbg_control_points_deg=fbg,
        fbg_sigma_deg=sigma,
        robot=robot,
        views=views,
        verification=verification,
    )
    d = spec.model_dump(mode="json")  # the models' order; absent keys left out
    for key, value in (extra or {}).items():
        if key in d:
            raise ValueError(f"extra key {key!r} is written from the case itself")
        if key not in CASE_KEYS and not is_comment_key(key):
            raise ValueError(
                f"extra key {key!r} would not load; use {list(COMMENT_KEYS)}, a key starting with '_', "
                f"or one of {list(CASE_KEYS)}"
            )
        d[key] = value
    path = out / "navigation.json"
    path.write_text(json.dumps(d, indent=2) + "\n", encoding="utf-8")
    logger.info("wrote navigation case %s (%d view(s))", path, len(case.views))
    return path


def _write_robot(case: NavigationCase, out: Path) -> RobotEntry:
    """The case's ``robot`` (its DH file ``robot_dh.json`` written unless the robot is the UR10)."""
    if case.robot == UR10:
        model = "UR10"
    else:
        model = "robot_dh.json"
        (out / model).write_text(json.dumps(robot_to_dict(case.robot), indent=2) + "\n", encoding="utf-8")
    return RobotEntry.model_construct(
        model=model,
        joints_deg=[float(v) for v in case.joints_deg],
        ee_from_cm=np.asarray(case.ee_from_cm, dtype=np.float64).tolist(),
    )


def _write_ct(volume: Volume, out: Path, ct_path: str | None) -> dict[str, str]:
    """The case's ``ct`` (and ``labels``, ``landmarks``): ``volume`` written to ``out``, or ``ct_path``."""
    if ct_path is None:
        written = save_volume(volume, out / "ct.nii.gz")
        d = {"ct": written[0].name}
        for f in written[1:]:
            if f.name.endswith("_labels.nii.gz"):
                d["labels"] = f.name
            elif f.name.endswith("_landmarks.json"):
                d["landmarks"] = f.name
        return d
    if ct_path.strip().lower() == "phantom":
        return {"ct": "phantom"}
    if not Path(ct_path).exists():
        raise FileNotFoundError(f"ct_path {ct_path} does not exist")
    return {"ct": _relative(Path(ct_path), out)}
