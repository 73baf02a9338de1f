"""Landmark files: 3D Slicer markups (FCSV, ``.mrk.json``) and a small JSON format.

Landmarks are kept as ``name → (3,) float64 world point in mm`` in the CT's LPS frame (the frame
SimpleITK reads). Files in RAS (Slicer's default) are converted on reading by negating x and y.
The formats (docs/data-formats.md, "Landmarks"): an FCSV names a point by its ``label`` column
(else its ``id``) and has, without a ``# columns`` line, Slicer's default column order, without a
coordinate-system line RAS; ``.mrk.json`` is read by :mod:`fluoronav.anatomy.markups`; the JSON
format is ``{"coordinate_system": "LPS" or "RAS" (default LPS), "landmarks": {name: [x, y, z]}}``.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from fluoronav.anatomy.markups import markup_file_stem, read_markups, write_markups
from fluoronav.errors import InputError, read_text_file

__all__ = [
    "read_fcsv",
    "read_landmarks",
    "read_landmarks_json",
    "write_fcsv",
    "write_landmarks",
    "write_landmarks_json",
]

logger = logging.getLogger(__name__)

_DEFAULT_COLUMNS = ["id", "x", "y", "z", "ow", "ox", "oy", "oz", "vis", "sel", "lock", "label", "desc"]
_RAS_TO_LPS = np.array([-1.0, -1.0, 1.0])


def _coordinate_system(value: str, path: Path, where: str) -> str:
    v = value.strip().upper()
    if v in ("LPS", "1"):
        return "LPS"
    if v in ("RAS", "0"):
        return "RAS"
    raise InputError(path, f"{where}: unknown coordinate system {value.strip()!r} (expected LPS or RAS)")


def _read_text(path: Path) -> str:
    return read_text_file(path, what="landmark file")


def read_fcsv(path: str | Path) -> dict[str, np.ndarray]:
    """Read a 3D Slicer FCSV markups file into LPS world points (mm).

    Args:
        path: the ``.fcsv`` file.

    Returns:
        name → (3,) float64 LPS point. Names come from the ``label`` column (``id`` if empty).

    Raises:
        InputError: missing/empty file, unknown coordinate system, a row with too few or
            non-numeric/non-finite coordinates, or a duplicate name (message names file and line).
    """
    path = Path(path)
    text = _read_text(path)
    columns = list(_DEFAULT_COLUMNS)
    system = "RAS"
    out: dict[str, np.ndarray] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        if line.startswith("#"):
            body = line.lstrip("#").strip()
            key, sep, value = body.partition("=")
            if not sep:
                continue
            key = key.strip().lower()
            if key == "coordinatesystem":
                system = _coordinate_system(value, path, f"line {lineno}")
            elif key == "columns":
                columns = [c.strip().lower() for c in value.split(",")]
                if not {"x", "y", "z"} <= set(columns):
                    raise InputError(path, f"line {lineno}: columns must include x, y and z")
            continue
        cells = [c.strip() for c in line.split(",")]
        if len(cells) <= max(columns.index(k) for k in ("x", "y", "z")):
            raise InputError(path, f"line {lineno}: too few comma-separated fields for x, y, z")
        try:
            point = np.array([float(cells[columns.index(k)]) for k in ("x", "y", "z")])
        except ValueError:
            raise InputError(path, f"line {lineno}: coordinates are not numbers") from None
        if not np.all(np.isfinite(point)):
            raise InputError(path, f"line {lineno}: non-finite coordinate")
        name = ""
        if "label" in columns and columns.index("label") < len(cells):
            name = cells[columns.index("label")]
        if not name and "id" in columns:
            name = cells[columns.index("id")]
        if not name:
            name = f"F-{len(out) + 1}"
        if name in out:
            raise InputError(path, f"line {lineno}: duplicate landmark name {name!r}")
        out[name] = point * _RAS_TO_LPS if system == "RAS" else point
    if not out:
        raise InputError(path, "no landmarks in file")
    return out


def write_fcsv(
    path: str | Path, landmarks: Mapping[str, np.ndarray], *, coordinate_system: str = "LPS"
) -> Path:
    """Write LPS landmarks as a Slicer FCSV file (version 4.11 header).

    Args:
        path: output ``.fcsv`` file.
        landmarks: name → (3,) LPS point in mm.
        coordinate_system: ``"LPS"`` (stored as given) or ``"RAS"`` (x, y negated on writing).
    """
    path = Path(path)
    system = coordinate_system.upper()
    if system not in ("LPS", "RAS"):
        raise ValueError(f"coordinate_system must be LPS or RAS, got {coordinate_system!r}")
    lines = [
        "# Markups fiducial file version = 4.11",
        f"# CoordinateSystem = {system}",
        "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID",
    ]
    for i, (name, p) in enumerate(landmarks.items()):
        if "," in name:
            raise ValueError(f"landmark name must not contain a comma: {name!r}")
        q = np.asarray(p, dtype=np.float64).reshape(3)
        if system == "RAS":
            q = q * _RAS_TO_LPS
        xyz = ",".join(repr(float(v)) for v in q)
        lines.append(f"vtkMRMLMarkupsFiducialNode_{i},{xyz},0,0,0,1,1,1,0,{name},,")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def read_landmarks_json(path: str | Path) -> dict[str, np.ndarray]:
    """Read ``{"coordinate_system": "LPS"|"RAS", "landmarks": {name: [x, y, z]}}`` into LPS points (mm).

    Raises:
        InputError: missing/empty file, invalid JSON (with its line), a missing ``landmarks``
            object, or a point that is not three finite numbers.
    """
    path = Path(path)
    text = _read_text(path)
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(path, f"line {exc.lineno}: invalid JSON ({exc.msg})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("landmarks"), dict):
        raise InputError(path, 'expected an object with a "landmarks" object of name → [x, y, z]')
    system = _coordinate_system(str(doc.get("coordinate_system", "LPS")), path, "coordinate_system")
    out: dict[str, np.ndarray] = {}
    for name, value in doc["landmarks"].items():
        ok = (
            isinstance(value, list)
            and len(value) == 3
            and all(
                isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in value
            )
        )
        if not ok:
            raise InputError(path, f"landmark {name!r}: expected three finite numbers [x, y, z]")
        p = np.asarray(value, dtype=np.float64)
        out[str(name)] = p * _RAS_TO_LPS if system == "RAS" else p
    if not out:
        raise InputError(path, "no landmarks in file")
    return out


def write_landmarks_json(
    path: str | Path, landmarks: Mapping[str, np.ndarray], *, coordinate_system: str = "LPS"
) -> Path:
    """Write landmarks (LPS, mm) in the JSON format; ``coordinate_system="RAS"`` negates x and y."""
    path = Path(path)
    system = coordinate_system.upper()
    if system not in ("LPS", "RAS"):
        raise ValueError(f"coordinate_system must be LPS or RAS, got {coordinate_system!r}")
    flip = _RAS_TO_LPS if system == "RAS" else np.ones(3)
    doc = {
        "coordinate_system": system,
        "landmarks": {
            name: [float(v) for v in np.asarray(p, dtype=np.float64).reshape(3) * flip]
            for name, p in landmarks.items()
        },
    }
    path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return path


def read_landmarks(path: str | Path) -> dict[str, np.ndarray]:
    """Read a landmark file by suffix: ``.mrk.json`` (Slicer markups, see
    :func:`~fluoronav.anatomy.markups.read_markups`), ``.fcsv`` (Slicer) or ``.json``."""
    path = Path(path)
    if path.name.lower().endswith(".mrk.json"):
        return read_markups(path)
    suffix = path.suffix.lower()
    if suffix == ".fcsv":
        return read_fcsv(path)
    if suffix == ".json":
        return read_landmarks_json(path)
    raise InputError(path, "unknown landmark file type (expected .mrk.json, .fcsv or .json)")


def write_landmarks(path: str | Path, landmarks: Mapping[str, np.ndarray]) -> Path:
    """Write landmarks (LPS) by suffix: ``.mrk.json`` (a Slicer point list), ``.fcsv`` or ``.json``."""
    path = Path(path)
    if path.name.lower().endswith(".mrk.json"):
        return write_markups(path, landmarks, name=markup_file_stem(path))
    suffix = path.suffix.lower()
    if suffix == ".fcsv":
        return write_fcsv(path, landmarks)
    if suffix == ".json":
        return write_landmarks_json(path, landmarks)
    raise ValueError(f"unknown landmark file type {path.suffix!r} (expected .mrk.json, .fcsv or .json)")
