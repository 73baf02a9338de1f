"""The parts of a navigation case file: values, files, views and their cameras.

Used by :func:`fluoronav.navigation.case.model.load_navigation_case` and
:func:`~fluoronav.navigation.case.model.write_navigation_case`. Every reading problem is an
:class:`~fluoronav.errors.InputError` naming the case file and the key at fault (e.g.
``case.json: views[1].camera: missing (...)``); problems inside another file name that file too.

Cameras: a camera file or an inline camera holds ``camera_from_world`` with world = the CT frame
(LPS, mm). ``"dicom"`` builds the camera from the image's own geometry tags
(:func:`fluoronav.geometry.dicom.camera_from_dicom`), whose world is the C-arm isocentre frame with
patient LPS axes; the case's isocentre point ``isocenter_ct_mm`` (CT, mm) places the CT in it:
``camera_from_ct = camera_from_iso @ translate(−isocenter_ct_mm)``. This assumes the CT's LPS axes
and the isocentre frame's axes coincide (a supine patient scanned and imaged head first).
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
from pydantic import ValidationError

from fluoronav.detection.image_io import load_image
from fluoronav.errors import InputError, read_json_object
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.dicom import camera_from_dicom
from fluoronav.manipulator.config import CMConfig, load_cm_config
from fluoronav.manipulator.robot import SerialRobot, load_robot
from fluoronav.navigation.case.view import CaseView

__all__ = [
    "ROBOT_KEYS",
    "VIEW_KEYS",
    "keyed",
    "parse_cm_config",
    "parse_joints",
    "parse_robot",
    "parse_views",
    "read_mask",
    "require_file",
    "rigid_matrix",
    "vector",
    "write_views",
]

logger = logging.getLogger(__name__)

#: Keys of one view entry.
VIEW_KEYS = (
    "name",
    "image",
    "camera",
    "landmarks_px",
    "mask",
    "isocenter_ct_mm",
    "moved_from",
    "same_camera_as",
)
#: Keys of the ``robot`` object.
ROBOT_KEYS = ("model", "joints_deg", "ee_from_cm")

_CAMERA_HINT = 'give a camera file, an inline camera or "dicom"'


@contextmanager
def keyed(src: str, key: str) -> Iterator[None]:
    """Re-raise an :class:`InputError` from inside as one naming the case file ``src`` and ``key``
    (and the other file at fault, when the error came from one)."""
    try:
        yield
    except InputError as exc:
        detail = exc.problem if exc.source == src else f"{exc.source}: {exc.problem}"
        raise InputError(src, f"{key}: {detail}") from None


def require_file(src: str, root: Path, value: Any, key: str, *, what: str = "a file name") -> Path:
    """``root / value`` for a non-empty string ``value`` naming an existing file or folder."""
    if value is None:
        raise InputError(src, f"{key}: missing ({what})")
    if not isinstance(value, str) or not value.strip():
        raise InputError(src, f"{key} must be {what}, got {value!r}")
    path = root / value
    if not path.exists():
        raise InputError(src, f"{key} file not found: {value}")
    return path


def vector(value: Any, key: str, src: str, *, n: int, why: str) -> np.ndarray:
    """(n,) float64 from a list of ``n`` finite numbers; ``why`` says where ``n`` comes from."""
    if value is None:
        raise InputError(src, f"{key}: missing ({n} numbers)")
    if not isinstance(value, list) or not all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in value
    ):
        raise InputError(src, f"{key} must be a list of {n} numbers")
    if len(value) != n:
        raise InputError(src, f"{key} has {len(value)} values, {why}")
    arr = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise InputError(src, f"{key} must hold finite numbers")
    return arr


def rigid_matrix(value: Any, key: str, src: str, *, tol: float = 1e-4) -> np.ndarray:
    """(4, 4) float64 rigid transform (orthonormal rotation with det +1 to ``tol``, last row 0 0 0 1)."""
    try:
        T = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(src, f"{key} must be a 4x4 matrix of numbers") from None
    if T.shape != (4, 4):
        raise InputError(src, f"{key} must be a 4x4 matrix, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise InputError(src, f"{key} has non-finite entries")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=tol) or np.linalg.det(R) < 0:
        raise InputError(src, f"{key} is not a rigid transform (rotation part not orthonormal)")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise InputError(src, f"{key} is not a rigid transform (last row must be [0, 0, 0, 1])")
    return T


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
    entry: dict[str, Any], key: str, src: str, root: Path, image_path: Path, isocenter_ct_mm: np.ndarray
) -> Camera:
    value = entry.get("camera")
    if value is None:
        raise InputError(src, f"{key}: missing ({_CAMERA_HINT})")
    if isinstance(value, dict):
        with keyed(src, key):
            return Camera.from_dict(value, source=src)
    if value == "dicom":
        with keyed(src, f'{key} "dicom"'):
            cam_iso = camera_from_dicom(image_path)
        return cam_iso.with_pose(cam_iso.camera_from_world @ _translation(-isocenter_ct_mm))
    if isinstance(value, str) and value.strip():
        path = require_file(src, root, value, key)
        with keyed(src, key):
            return Camera.load(path)
    raise InputError(src, f'{key} must be a camera file, an inline camera or "dicom", got {value!r}')


def _landmarks(value: Any, key: str, src: str, rows: int, cols: int) -> np.ndarray:
    try:
        lm = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(src, f"{key} must be [[uA, vA], [uB, vB]] (pixels)") from None
    if lm.shape != (2, 2) or not np.all(np.isfinite(lm)):
        raise InputError(src, f"{key} must be [[uA, vA], [uB, vB]] of finite pixels, got shape {lm.shape}")
    inside = (lm[:, 0] >= -0.5) & (lm[:, 0] <= cols - 0.5) & (lm[:, 1] >= -0.5) & (lm[:, 1] <= rows - 0.5)
    if not inside.all():
        raise InputError(src, f"{key} lies outside the {rows}x{cols} image (u = column, v = row)")
    return lm


def _view(
    entry: Any, k: int, key: str, src: str, root: Path, isocenter_ct_mm: np.ndarray, default_name: str
) -> CaseView:
    vk = f"{key}[{k}]"
    if not isinstance(entry, dict):
        raise InputError(src, f"{vk} must be an object with 'image' and 'camera'")
    unknown = sorted(set(entry) - set(VIEW_KEYS))
    if unknown:
        raise InputError(src, f"{vk}: unknown key(s) {unknown}; allowed: {list(VIEW_KEYS)}")
    name = entry.get("name", default_name)
    if not isinstance(name, str) or not name.strip():
        raise InputError(src, f"{vk}.name must be a non-empty string, got {name!r}")
    image_path = require_file(src, root, entry.get("image"), f"{vk}.image", what="an image file")
    with keyed(src, f"{vk}.image"):
        image, spacing = load_image(image_path)
    if entry.get("isocenter_ct_mm") is not None:  # this view's own isocentre (the C-arm moved)
        isocenter_ct_mm = vector(
            entry["isocenter_ct_mm"], f"{vk}.isocenter_ct_mm", src, n=3, why="a CT point has 3"
        )
    camera = _camera(entry, f"{vk}.camera", src, root, image_path, isocenter_ct_mm)
    if image.shape != (camera.rows, camera.cols):
        raise InputError(
            src,
            f"{vk}: the image is {image.shape[0]}x{image.shape[1]} pixels (rows x cols), "
            f"its camera {camera.rows}x{camera.cols}",
        )
    if camera.pixel_spacing_mm is None and spacing is not None:
        camera = Camera(camera.rows, camera.cols, camera.K, camera.camera_from_world, spacing)
    landmarks = None
    if entry.get("landmarks_px") is not None:
        landmarks = _landmarks(entry["landmarks_px"], f"{vk}.landmarks_px", src, camera.rows, camera.cols)
    mask = None
    if entry.get("mask") is not None:
        if landmarks is None:
            raise InputError(src, f"{vk}.mask is given without landmarks_px (a mask comes with them)")
        mask_path = require_file(src, root, entry["mask"], f"{vk}.mask", what="a mask image file")
        with keyed(src, f"{vk}.mask"):
            mask = read_mask(mask_path)
        if mask.shape != image.shape:
            raise InputError(
                src,
                f"{vk}.mask is {mask.shape[0]}x{mask.shape[1]}, the image {image.shape[0]}x{image.shape[1]}",
            )
    moved_from, motion = _carm_relation(entry, vk, src)
    return CaseView(
        name=name,
        image=image,
        camera=camera,
        landmarks_px=landmarks,
        mask=mask,
        moved_from=moved_from,
        carm_motion=motion,
    )


def _carm_relation(entry: dict[str, Any], vk: str, src: str) -> tuple[str | None, np.ndarray | None]:
    """A view's C-arm relation to a first view: ``same_camera_as`` (a view name: the C-arm did not
    move) or ``moved_from`` ({``view``, ``carm_after_from_carm_before``: 4×4 mm})."""
    same, moved = entry.get("same_camera_as"), entry.get("moved_from")
    if same is not None and moved is not None:
        raise InputError(src, f"{vk}: give same_camera_as or moved_from, not both")
    if same is not None:
        if not isinstance(same, str) or not same.strip():
            raise InputError(src, f"{vk}.same_camera_as must be a view name, got {same!r}")
        return same, np.eye(4)
    if moved is None:
        return None, None
    if not isinstance(moved, dict) or set(moved) != {"view", "carm_after_from_carm_before"}:
        raise InputError(src, f"{vk}.moved_from must be {{'view': NAME, 'carm_after_from_carm_before': 4x4}}")
    view = moved["view"]
    if not isinstance(view, str) or not view.strip():
        raise InputError(src, f"{vk}.moved_from.view must be a view name, got {view!r}")
    motion = rigid_matrix(
        moved["carm_after_from_carm_before"], f"{vk}.moved_from.carm_after_from_carm_before", src
    )
    return view, motion


def parse_views(
    entries: Any,
    *,
    key: str,
    src: str,
    root: Path,
    isocenter_ct_mm: np.ndarray,
    default_prefix: str = "view",
) -> tuple[CaseView, ...]:
    """Read a ``views`` list (paths relative to ``root``) → views with unique names.

    Args:
        entries: the JSON value.
        key: its key path for messages (``"views"``, ``"verification.views"``).
        src: the case file, for messages.
        root: the case file's folder.
        isocenter_ct_mm: (3,) the CT point at the C-arm isocentre, for ``"camera": "dicom"``.
        default_prefix: a view without ``name`` is ``<default_prefix><k>``.
    """
    if entries is None:
        raise InputError(src, f"{key}: missing (a non-empty list of views)")
    if not isinstance(entries, list) or not entries:
        raise InputError(src, f"{key} must be a non-empty list of views")
    views = tuple(
        _view(e, k, key, src, root, isocenter_ct_mm, f"{default_prefix}{k}") for k, e in enumerate(entries)
    )
    seen: set[str] = set()
    for k, v in enumerate(views):
        if v.name in seen:
            raise InputError(src, f"{key}[{k}].name {v.name!r} is used twice (view names must be unique)")
        seen.add(v.name)
    return views


def _file_stem(name: str, used: set[str]) -> str:
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or "view"
    out, n = stem, 1
    while out in used:
        n += 1
        out = f"{stem}_{n}"
    used.add(out)
    return out


def write_views(views: Sequence[CaseView], directory: Path, *, prefix: str = "") -> list[dict[str, Any]]:
    """Write views as ``<prefix><name>.npz`` (``image`` float32, ``pixel_spacing_mm`` when known),
    ``<prefix><name>_camera.json`` and ``<prefix><name>_mask.png`` → their case entries."""
    used: set[str] = set()
    entries: list[dict[str, Any]] = []
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
                entry["moved_from"] = {
                    "view": v.moved_from,
                    "carm_after_from_carm_before": np.asarray(v.carm_motion, np.float64).tolist(),
                }
        if v.mask is not None:
            cv2.imwrite(
                str(directory / f"{stem}_mask.png"), np.where(np.asarray(v.mask), 255, 0).astype(np.uint8)
            )
            entry["mask"] = f"{stem}_mask.png"
        entries.append(entry)
    return entries


def parse_cm_config(value: Any, src: str, root: Path) -> CMConfig:
    """``cm``: a CM config file, an inline object, or None (the paper's CM)."""
    if value is None:
        return CMConfig()
    if isinstance(value, str):
        path = require_file(src, root, value, "'cm'", what="a CM config file")
        with keyed(src, "'cm'"):
            return load_cm_config(path)
    if not isinstance(value, dict):
        raise InputError(src, f"'cm' must be a CM config file or an inline object, got {value!r}")
    try:
        return CMConfig(**value)
    except ValidationError as exc:
        first = exc.errors()[0]
        loc = ".".join(str(x) for x in first["loc"]) or "config"
        raise InputError(src, f"'cm': invalid CM config: {loc}: {first['msg']}") from None


def parse_joints(value: Any, key: str, robot: SerialRobot, src: str) -> np.ndarray:
    """(n_joints,) joint readings in degrees, within the robot's limits."""
    n = robot.n_joints
    q = vector(value, key, src, n=n, why=f"the {robot.name} has {n} joints")
    for j, (lo, hi) in enumerate(robot.joint_limits_deg):
        if not lo <= q[j] <= hi:
            raise InputError(
                src, f"{key}[{j}] = {q[j]:g} is outside the {robot.name}'s limits [{lo:g}, {hi:g}]"
            )
    return q


def _ee_from_cm(value: Any, src: str, root: Path) -> np.ndarray:
    key = "robot.ee_from_cm"
    if value is None:
        raise InputError(src, f"{key}: missing (a 4x4 matrix or a `calibrate` output file)")
    if not isinstance(value, str):
        return rigid_matrix(value, key, src)
    path = require_file(src, root, value, key, what="a 4x4 matrix or a `calibrate` output file")
    with keyed(src, key):
        doc = read_json_object(path, what="hand-eye file")
        if doc.get("ok") is False:
            raise InputError(path, f"a failed calibration ({doc.get('reason') or 'no reason given'})")
        if "ee_from_cm" not in doc:
            raise InputError(path, "holds no 'ee_from_cm' (a `calibrate` output or {\"ee_from_cm\": 4x4})")
        return rigid_matrix(doc["ee_from_cm"], "ee_from_cm", str(path))


def parse_robot(d: dict[str, Any], src: str, root: Path) -> tuple[SerialRobot, np.ndarray, np.ndarray]:
    """``robot`` → (model, joints_deg (n,), ee_from_cm (4, 4))."""
    r = d.get("robot")
    if r is None:
        raise InputError(src, "'robot': missing (an object with model, joints_deg and ee_from_cm)")
    if not isinstance(r, dict):
        raise InputError(src, "'robot' must be an object with model, joints_deg and ee_from_cm")
    unknown = sorted(set(r) - set(ROBOT_KEYS))
    if unknown:
        raise InputError(src, f"robot: unknown key(s) {unknown}; allowed: {list(ROBOT_KEYS)}")
    model = r.get("model")
    if model is None:
        raise InputError(src, 'robot.model: missing ("UR10" or a DH file)')
    if not isinstance(model, str) or not model.strip():
        raise InputError(src, f'robot.model must be "UR10" or a DH file name, got {model!r}')
    if model.strip().upper() != "UR10" and not (root / model).is_file():
        raise InputError(src, f'robot.model {model!r} is neither "UR10" nor an existing DH file')
    with keyed(src, "robot.model"):
        robot = load_robot(model if model.strip().upper() == "UR10" else root / model, source=src)
    q = parse_joints(r.get("joints_deg"), "robot.joints_deg", robot, src)
    return robot, q, _ee_from_cm(r.get("ee_from_cm"), src, root)
