"""The files a navigation case names: views (images, cameras, masks), CM config, robot, hand-eye.

Used by :func:`~fluoronav.navigation.case.model.load_navigation_case` on the checked case file
(:mod:`.schema`) and by :func:`~fluoronav.navigation.case.model.write_navigation_case`. A reading
problem is an :class:`~fluoronav.errors.InputError` naming the case file and the key (e.g.
``case.json: 'ct' file not found: ct.nii.gz``); problems inside another file name that file too.

Cameras: ``camera_from_world`` is camera_from_ct. ``"dicom"`` builds the camera from the image's
geometry tags (:func:`fluoronav.geometry.dicom.camera_from_dicom`; world = the C-arm isocentre frame,
patient LPS axes) and places the CT by ``isocenter_ct_mm``: ``camera_from_ct = camera_from_iso @
translate(−isocenter_ct_mm)`` (the CT's and the isocentre frame's axes taken to coincide: supine).
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from fluoronav.detection.image_io import load_image
from fluoronav.errors import InputError, read_json_object
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.dicom import camera_from_dicom
from fluoronav.manipulator.config import CMConfig, load_cm_config
from fluoronav.manipulator.robot import SerialRobot, load_robot
from fluoronav.navigation.case.schema import (
    InlineCamera,
    MovedFrom,
    RobotEntry,
    ViewEntry,
    rigid_matrix,
    view_names,
)
from fluoronav.navigation.case.view import CaseView

__all__ = [
    "keyed",
    "parse_cm_config",
    "parse_joints",
    "parse_robot",
    "parse_views",
    "read_mask",
    "readings",
    "require_file",
    "write_views",
]

logger = logging.getLogger(__name__)


@contextmanager
def keyed(src: str, key: str) -> Iterator[None]:
    """Re-raise an :class:`InputError` from inside as one naming the case file ``src`` and ``key``
    (and the other file at fault, when the error came from one)."""
    try:
        yield
    except InputError as exc:
        detail = exc.problem if exc.source == src else f"{exc.source}: {exc.problem}"
        raise InputError(src, f"{key}: {detail}") from None


def require_file(src: str, root: Path, value: str, key: str) -> Path:
    """``root / value`` (``value`` a file name the schema checked), which must exist."""
    path = root / value
    if not path.exists():
        raise InputError(src, f"{key} file not found: {value}")
    return path


def readings(values: list[float], key: str, src: str, *, n: int, why: str) -> np.ndarray:
    """(n,) float64 from ``n`` readings; ``why`` says where ``n`` comes from (the robot, the CM)."""
    if len(values) != n:
        raise InputError(src, f"{key} has {len(values)} values, {why}")
    return np.asarray(values, dtype=np.float64)


def read_mask(path: Path) -> np.ndarray:
    """A CM mask file → (rows, cols) bool, True where the file is nonzero.

    PNG / TIFF / JPEG (any bit depth; colour: nonzero in any channel), ``.npy``, or ``.npz`` (key
    ``mask``, else ``image``).
    """
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            arr = np.load(path, allow_pickle=False)
        elif suffix == ".npz":
            with np.load(path, allow_pickle=False) as npz:
                key = "mask" if "mask" in npz.files else "image" if "image" in npz.files else None
                if key is None:
                    raise InputError(path, "no 'mask' or 'image' array in the .npz")
                arr = np.asarray(npz[key])
        else:
            raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if raw is None:
                raise InputError(path, "unreadable mask image")
            arr = raw if raw.ndim == 2 else np.any(raw != 0, axis=2)
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(path, f"unreadable mask ({exc.__class__.__name__})") from None
    arr = np.asarray(arr)
    if arr.ndim != 2 or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise InputError(path, f"a mask must be a 2-D numeric image, got shape {arr.shape}")
    mask = arr != 0
    if not mask.any():
        raise InputError(path, "empty mask (no nonzero pixel)")
    return np.asarray(mask, dtype=bool)


def _translation(t_mm: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = t_mm
    return T


def _camera(
    value: str | InlineCamera, key: str, src: str, root: Path, image_path: Path, isocenter_ct_mm: np.ndarray
) -> Camera:
    """A view's camera: inline, ``"dicom"`` (placed by ``isocenter_ct_mm``) or a camera file."""
    if isinstance(value, InlineCamera):
        with keyed(src, key):
            return Camera.from_dict(value.model_dump(), source=src)
    if value == "dicom":
        with keyed(src, f'{key} "dicom"'):
            cam_iso = camera_from_dicom(image_path)
        return cam_iso.with_pose(cam_iso.camera_from_world @ _translation(-isocenter_ct_mm))
    path = require_file(src, root, value, key)
    with keyed(src, key):
        return Camera.load(path)


def _landmarks(value: list[list[float]], key: str, src: str, rows: int, cols: int) -> np.ndarray:
    """(2, 2) landmarks A, B (u, v), which must lie on the image."""
    lm = np.asarray(value, dtype=np.float64)
    inside = (lm[:, 0] >= -0.5) & (lm[:, 0] <= cols - 0.5) & (lm[:, 1] >= -0.5) & (lm[:, 1] <= rows - 0.5)
    if not inside.all():
        raise InputError(src, f"{key} lies outside the {rows}x{cols} image (u = column, v = row)")
    return lm


def _view(
    entry: ViewEntry, vk: str, name: str, src: str, root: Path, isocenter_ct_mm: np.ndarray
) -> CaseView:
    """Read view ``vk`` (its key path, e.g. ``views[1]``) named ``name``."""
    image_path = require_file(src, root, entry.image, f"{vk}.image")
    with keyed(src, f"{vk}.image"):
        image, spacing = load_image(image_path)
    if entry.isocenter_ct_mm is not None:  # this view's own isocentre (the C-arm moved)
        isocenter_ct_mm = np.asarray(entry.isocenter_ct_mm, dtype=np.float64)
    camera = _camera(entry.camera, f"{vk}.camera", src, root, image_path, isocenter_ct_mm)
    if image.shape != (camera.rows, camera.cols):
        raise InputError(
            src,
            f"{vk}: the image is {image.shape[0]}x{image.shape[1]} pixels (rows x cols), "
            f"its camera {camera.rows}x{camera.cols}",
        )
    if camera.pixel_spacing_mm is None and spacing is not None:
        camera = Camera(camera.rows, camera.cols, camera.K, camera.camera_from_world, spacing)
    landmarks = None
    if entry.landmarks_px is not None:
        landmarks = _landmarks(entry.landmarks_px, f"{vk}.landmarks_px", src, camera.rows, camera.cols)
    mask = None
    if entry.mask is not None:
        mask_path = require_file(src, root, entry.mask, f"{vk}.mask")
        with keyed(src, f"{vk}.mask"):
            mask = read_mask(mask_path)
        if mask.shape != image.shape:
            raise InputError(
                src,
                f"{vk}.mask is {mask.shape[0]}x{mask.shape[1]}, the image {image.shape[0]}x{image.shape[1]}",
            )
    moved_from, motion = entry.carm_relation()
    return CaseView(
        name=name,
        image=image,
        camera=camera,
        landmarks_px=landmarks,
        mask=mask,
        moved_from=moved_from,
        carm_motion=motion,
    )


def parse_views(
    entries: list[ViewEntry],
    *,
    key: str,
    src: str,
    root: Path,
    isocenter_ct_mm: np.ndarray,
    default_prefix: str = "view",
) -> tuple[CaseView, ...]:
    """Read a checked ``views`` list (paths relative to ``root``; names unique, as the schema holds).

    Args:
        entries: the views' entries.
        key: their key path for messages (``"views"``, ``"verification.views"``).
        src: the case file, for messages.
        root: the case file's folder.
        isocenter_ct_mm: (3,) the CT point at the C-arm isocentre, for ``"camera": "dicom"``.
        default_prefix: a view without ``name`` is ``<default_prefix><k>``.
    """
    names = view_names(entries, default_prefix)
    return tuple(
        _view(e, f"{key}[{k}]", name, src, root, isocenter_ct_mm)
        for k, (e, name) in enumerate(zip(entries, names, strict=True))
    )


def _file_stem(name: str, used: set[str]) -> str:
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or "view"
    out, n = stem, 1
    while out in used:
        n += 1
        out = f"{stem}_{n}"
    used.add(out)
    return out


def write_views(views: Sequence[CaseView], directory: Path, *, prefix: str = "") -> list[ViewEntry]:
    """Write views as ``<prefix><name>.npz`` (``image`` float32, ``pixel_spacing_mm`` when known),
    ``<prefix><name>_camera.json`` and ``<prefix><name>_mask.png`` → their case entries (not
    validated: the reader checks what it reads)."""
    used: set[str] = set()
    entries: list[ViewEntry] = []
    for v in views:
        if v.mask is not None and v.landmarks_px is None:
            raise ValueError(f"view {v.name!r}: a case file keeps a mask only with landmarks_px")
        stem = prefix + _file_stem(v.name, used)
        arrays: dict[str, np.ndarray] = {"image": np.asarray(v.image, dtype=np.float32)}
        if v.camera.pixel_spacing_mm is not None:
            arrays["pixel_spacing_mm"] = np.asarray(v.camera.pixel_spacing_mm, dtype=np.float64)
        np.savez_compressed(directory / f"{stem}.npz", **arrays)  # type: ignore[arg-type]
        v.camera.save(directory / f"{stem}_camera.json")
        entry: dict[str, Any] = {"name": v.name, "image": f"{stem}.npz", "camera": f"{stem}_camera.json"}
        if v.landmarks_px is not None:
            entry["landmarks_px"] = [[float(x) for x in row] for row in np.asarray(v.landmarks_px)]
        if v.moved_from is not None and v.carm_motion is not None:
            if np.array_equal(v.carm_motion, np.eye(4)):
                entry["same_camera_as"] = v.moved_from
            else:
                entry["moved_from"] = MovedFrom.model_construct(
                    view=v.moved_from,
                    carm_after_from_carm_before=np.asarray(v.carm_motion, np.float64).tolist(),
                )
        if v.mask is not None:
            cv2.imwrite(
                str(directory / f"{stem}_mask.png"), np.where(np.asarray(v.mask), 255, 0).astype(np.uint8)
            )
            entry["mask"] = f"{stem}_mask.png"
        entries.append(ViewEntry.model_construct(**entry))
    return entries


def parse_cm_config(value: str | CMConfig | None, src: str, root: Path) -> CMConfig:
    """``cm``: a CM config file, the inline config (checked with the case), or None (the paper's CM)."""
    if value is None:
        return CMConfig()
    if isinstance(value, CMConfig):
        return value
    path = require_file(src, root, value, "'cm'")
    with keyed(src, "'cm'"):
        return load_cm_config(path)


def parse_joints(values: list[float], key: str, robot: SerialRobot, src: str) -> np.ndarray:
    """(n_joints,) joint readings in degrees: one per joint of ``robot``, within its limits."""
    n = robot.n_joints
    q = readings(values, key, src, n=n, why=f"the {robot.name} has {n} joints")
    for j, (lo, hi) in enumerate(robot.joint_limits_deg):
        if not lo <= q[j] <= hi:
            raise InputError(
                src, f"{key}[{j}] = {q[j]:g} is outside the {robot.name}'s limits [{lo:g}, {hi:g}]"
            )
    return q


def _ee_from_cm(value: str | list[list[float]], src: str, root: Path) -> np.ndarray:
    """``robot.ee_from_cm``: the checked inline matrix, or the ``ee_from_cm`` of a (``calibrate``) file."""
    key = "robot.ee_from_cm"
    if not isinstance(value, str):
        return np.asarray(value, dtype=np.float64)
    path = require_file(src, root, value, key)
    with keyed(src, key):
        doc = read_json_object(path, what="hand-eye file")
        if doc.get("ok") is False:
            raise InputError(path, f"a failed calibration ({doc.get('reason') or 'no reason given'})")
        if "ee_from_cm" not in doc:
            raise InputError(path, "holds no 'ee_from_cm' (a `calibrate` output or {\"ee_from_cm\": 4x4})")
        return rigid_matrix(doc["ee_from_cm"], "ee_from_cm", str(path))


def parse_robot(entry: RobotEntry, src: str, root: Path) -> tuple[SerialRobot, np.ndarray, np.ndarray]:
    """``robot`` → (model, joints_deg (n,), ee_from_cm (4, 4))."""
    model = entry.model
    if model.strip().upper() != "UR10" and not (root / model).is_file():
        raise InputError(src, f'robot.model {model!r} is neither "UR10" nor an existing DH file')
    with keyed(src, "robot.model"):
        robot = load_robot(model if model.strip().upper() == "UR10" else root / model, source=src)
    q = parse_joints(entry.joints_deg, "robot.joints_deg", robot, src)
    return robot, q, _ee_from_cm(entry.ee_from_cm, src, root)
