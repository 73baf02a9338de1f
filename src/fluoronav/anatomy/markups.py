"""3D Slicer markups JSON files (``.mrk.json``): point lists, lines, curves and the other markups.

The format is Slicer's markups schema v1.0.3 as its reader/writer
(``vtkMRMLMarkupsJsonStorageNode``) handles it; the rules applied here are in docs/data-formats.md
("Landmarks"). Points are returned in LPS (the CT world frame SimpleITK reads, mm): RAS positions
are converted by negating x and y, and a markup without ``"coordinateSystem"`` is LPS (the
schema's default). Points whose status is ``"undefined"`` or ``"preview"`` are skipped; a point
without a label is named ``"<markup name>-<n>"`` (1-based, Slicer's default label format).
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from fluoronav.errors import InputError, read_text_file

__all__ = [
    "MARKUPS_SCHEMA_ID",
    "MarkupNode",
    "markup_file_stem",
    "read_markup_nodes",
    "read_markups",
    "write_markups",
]

logger = logging.getLogger(__name__)

#: The ``@schema`` id Slicer writes into markups files (schema v1.0.3).
MARKUPS_SCHEMA_ID = (
    "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/Resources/Schema/"
    "markups-schema-v1.0.3.json#"
)
_ACCEPTED_SCHEMA = re.compile(r"markups-schema-v1\.[0-9]+\.[0-9]+\.json#*$")
_RAS_TO_LPS = np.array([-1.0, -1.0, 1.0])
_POSITION_STATUSES = ("undefined", "preview", "defined")
#: Slicer's default markups colour (the schema's default ``display.color``).
_DEFAULT_COLOR = (0.4, 1.0, 1.0)


@dataclass(frozen=True, eq=False)
class MarkupNode:
    """One markup of a ``.mrk.json`` file, its placed control points in LPS.

    Attributes:
        type: the markup type as written (``"Fiducial"``, ``"Line"``, ``"Curve"``, ...).
        name: the markup's name (``"name"``, else the file name without ``.mrk.json``).
        labels: the control points' labels, in file order (generated for empty labels).
        points_lps: (N, 3) float64 control point positions, LPS mm, in file order.
    """

    type: str
    name: str
    labels: tuple[str, ...]
    points_lps: np.ndarray


def markup_file_stem(path: str | Path) -> str:
    """File name without ``.mrk.json`` (or without its last suffix for other names)."""
    name = Path(path).name
    if name.lower().endswith(".mrk.json"):
        return name[: -len(".mrk.json")]
    return Path(name).stem


def _number(value: object) -> float | None:
    """A finite float from a JSON number, else None (booleans and overflowing integers included)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        f = float(value)
    except OverflowError:
        return None
    return f if math.isfinite(f) else None


def _coordinate_units_ok(units: object) -> bool:
    if isinstance(units, str):
        return units == "mm"
    if isinstance(units, list) and len(units) == 3 and all(isinstance(u, str) for u in units):
        return units[0] == "mm" and units[1] == "UCUM"
    return False


def _read_document(path: Path) -> dict[str, Any]:
    text = read_text_file(path, what="markups file")
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(path, f"not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except RecursionError:
        raise InputError(path, "not valid JSON (nested too deeply)") from None
    if not isinstance(doc, dict):
        raise InputError(path, "a markups file must be a JSON object")
    schema = doc.get("@schema")
    if schema is not None and (
        not isinstance(schema, str) or not _ACCEPTED_SCHEMA.search(schema.strip().lower())
    ):
        raise InputError(path, "'@schema' is not a Slicer markups schema (markups-schema-v1.x.y.json)")
    if not isinstance(doc.get("markups"), list):
        raise InputError(path, "missing 'markups' list")
    return doc


def _read_node(path: Path, index: int, markup: object) -> MarkupNode:
    where = f"markup {index + 1}"
    if not isinstance(markup, dict):
        raise InputError(path, f"{where}: expected an object")
    kind = markup.get("type")
    if not isinstance(kind, str) or not kind.strip():
        raise InputError(path, f"{where}: missing 'type'")
    name = markup.get("name", "")
    if not isinstance(name, str):
        raise InputError(path, f"{where}: 'name' must be a string")
    name = name.strip() or markup_file_stem(path)
    where = f"markup {name!r}"
    system = markup.get("coordinateSystem", "LPS")
    if not isinstance(system, str) or system.strip().upper() not in ("LPS", "RAS"):
        raise InputError(path, f"{where}: unknown coordinate system {system!r} (expected LPS or RAS)")
    flip = _RAS_TO_LPS if system.strip().upper() == "RAS" else np.ones(3)
    if "coordinateUnits" in markup and not _coordinate_units_ok(markup["coordinateUnits"]):
        raise InputError(path, f"{where}: coordinate units {markup['coordinateUnits']!r} (expected mm)")
    cps = markup.get("controlPoints", [])
    if not isinstance(cps, list):
        raise InputError(path, f"{where}: 'controlPoints' must be a list")
    labels: list[str] = []
    points: list[np.ndarray] = []
    for n, cp in enumerate(cps, start=1):
        if not isinstance(cp, dict):
            raise InputError(path, f"{where} control point {n}: expected an object")
        status = cp.get("positionStatus", "defined")
        if status not in _POSITION_STATUSES:
            raise InputError(path, f"{where} control point {n}: unknown positionStatus {status!r}")
        if status != "defined":
            logger.debug("%s: %s control point %d is %s, skipped", path, where, n, status)
            continue
        label = cp.get("label", "")
        if not isinstance(label, str):
            raise InputError(path, f"{where} control point {n}: 'label' must be a string")
        position = cp.get("position")
        xyz = [_number(v) for v in position] if isinstance(position, list) and len(position) == 3 else []
        if len(xyz) != 3 or any(v is None for v in xyz):
            raise InputError(path, f"{where} control point {n}: 'position' must be three finite numbers")
        labels.append(label.strip() or f"{name}-{n}")
        points.append(np.asarray(xyz, dtype=np.float64) * flip)
    array = np.stack(points) if points else np.zeros((0, 3))
    return MarkupNode(type=kind.strip(), name=name, labels=tuple(labels), points_lps=array)


def read_markup_nodes(path: str | Path) -> list[MarkupNode]:
    """Every markup of a Slicer ``.mrk.json`` file, with its placed control points in LPS (mm).

    Args:
        path: the markups file.

    Returns:
        One :class:`MarkupNode` per entry of ``"markups"``, in file order.

    Raises:
        InputError: missing, empty or unreadable file, invalid JSON, a foreign ``@schema``, no
            ``markups`` list, a markup without ``type``, an unknown coordinate system or units, or
            a placed control point without a three-number position (message names the file).
    """
    path = Path(path)
    doc = _read_document(path)
    return [_read_node(path, i, m) for i, m in enumerate(doc["markups"])]


def read_markups(path: str | Path) -> dict[str, np.ndarray]:
    """Every placed control point of a Slicer ``.mrk.json`` file → label → (3,) LPS point (mm).

    All markups in the file contribute (point lists, lines, curves, ... anything with control
    points), in file order. Unlabelled points are named ``"<markup name>-<n>"`` (see the module
    documentation).

    Raises:
        InputError: as :func:`read_markup_nodes`, plus a label used twice in the file or a file
            without any placed control point.
    """
    path = Path(path)
    out: dict[str, np.ndarray] = {}
    for node in read_markup_nodes(path):
        for label, point in zip(node.labels, node.points_lps, strict=True):
            if label in out:
                raise InputError(path, f"duplicate control point label {label!r}")
            out[label] = point.copy()
    if not out:
        raise InputError(path, "no placed control points in markups file")
    return out


def _control_points(
    points: Mapping[str, np.ndarray], flip: np.ndarray, orientation: Sequence[float] | np.ndarray
) -> list[dict[str, Any]]:
    """The file's control point entries, in order: ``points`` (label → (3,) LPS mm) times ``flip``
    (the file's coordinate system), each with the identity's ``orientation`` (9 values).

    Raises:
        ValueError: a point that is not three finite numbers.
    """
    control_points = []
    for i, (label, p) in enumerate(points.items(), start=1):
        q = np.asarray(p, dtype=np.float64).reshape(-1)
        if q.shape != (3,) or not np.all(np.isfinite(q)):
            raise ValueError(f"point {label!r} must be three finite numbers, got {p!r}")
        control_points.append(
            {
                "id": str(i),
                "label": str(label),
                "description": "",
                "associatedNodeID": "",
                "position": [float(v) for v in q * flip],
                "orientation": [float(v) for v in orientation],
                "selected": True,
                "locked": False,
                "visibility": True,
                "positionStatus": "defined",
            }
        )
    return control_points


def write_markups(
    path: str | Path,
    points: Mapping[str, np.ndarray],
    *,
    name: str,
    kind: Literal["Fiducial", "Line", "Curve"] = "Fiducial",
    coordinate_system: Literal["LPS", "RAS"] = "LPS",
    color: tuple[float, float, float] | None = None,
    locked: bool = False,
) -> Path:
    """Write one markup as a Slicer ``.mrk.json`` file (schema v1.0.3).

    Args:
        path: output file (``.mrk.json`` so that Slicer recognises it by name).
        points: label → (3,) LPS point in mm, in control point order.
        name: the markup's name (shown in Slicer's Data module).
        kind: ``"Fiducial"`` (point list), ``"Line"`` (exactly two points) or ``"Curve"`` (an
            open curve through the points in order).
        coordinate_system: ``"LPS"`` (positions as given) or ``"RAS"`` (x, y negated).
        color: RGB in [0, 1] for the markup and its selected points; Slicer's default when None.
        locked: lock the markup against editing in Slicer.

    Returns:
        ``path``.

    Raises:
        ValueError: an unknown kind or coordinate system, a line without exactly two points, a
            point that is not three finite numbers, or a colour outside [0, 1].
    """
    path = Path(path)
    if kind not in ("Fiducial", "Line", "Curve"):
        raise ValueError(f"kind must be 'Fiducial', 'Line' or 'Curve', got {kind!r}")
    system = coordinate_system.upper()
    if system not in ("LPS", "RAS"):
        raise ValueError(f"coordinate_system must be LPS or RAS, got {coordinate_system!r}")
    if kind == "Line" and len(points) != 2:
        raise ValueError(f"a Line markup needs exactly two points, got {len(points)}")
    rgb = tuple(float(c) for c in (color if color is not None else _DEFAULT_COLOR))
    if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):
        raise ValueError(f"color must be three numbers in [0, 1], got {color!r}")
    flip = _RAS_TO_LPS if system == "RAS" else np.ones(3)
    # orientation of the identity (RAS scene) as Slicer writes it in the file's coordinate system
    orientation = [-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0] if system == "LPS" else np.eye(3).ravel()
    control_points = _control_points(points, flip, orientation)
    markup = {
        "type": kind,
        "name": name,
        "coordinateSystem": system,
        "coordinateUnits": "mm",
        "locked": bool(locked),
        "fixedNumberOfControlPoints": False,
        "labelFormat": "%N-%d",
        "lastUsedControlPointNumber": len(control_points),
        "controlPoints": control_points,
        "display": {
            "visibility": True,
            "opacity": 1.0,
            "color": list(rgb),
            "selectedColor": list(rgb),
            "propertiesLabelVisibility": kind != "Fiducial",
            "pointLabelsVisibility": True,
            "glyphType": "Sphere3D",
        },
    }
    doc = {"@schema": MARKUPS_SCHEMA_ID, "markups": [markup]}
    path.write_text(json.dumps(doc, indent=4) + "\n", encoding="utf-8")
    return path
