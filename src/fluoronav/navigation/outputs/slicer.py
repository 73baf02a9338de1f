"""The navigation result as files for 3D Slicer: transforms, surface models and markups.

All positions are in the CT's world frame (LPS, mm, as SimpleITK reads the CT) unless a name says
otherwise; transforms are named ``<to>_from_<from>``. Transforms are ITK files (``.h5``), which
store the *resampling* direction: the file written for ``ct_from_x`` holds ``x_from_ct``
(``sitk.ReadTransform(file).TransformPoint(p_ct) == x_from_ct @ p_ct``), and Slicer loads it as a
transform node whose "to parent" matrix is ``ct_from_x``; it is written as
``AffineTransform_double_3_3`` with a zero centre, as Slicer writes linear transforms. Models are
VTK legacy polydata (``.vtk``, version 4.2) whose header says ``SPACE=LPS``; markups are
``.mrk.json`` (:mod:`fluoronav.anatomy.markups`). docs/navigation.md ("Viewing the result in 3D
Slicer") lists the files.
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Literal

import numpy as np
import SimpleITK as sitk  # noqa: N813
import torch
from scipy import ndimage
from skimage.measure import marching_cubes

from fluoronav.anatomy.markups import write_markups
from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.manipulator.mesh import cm_surface_mesh, mesh_volume

__all__ = [
    "cm_surface",
    "femur_surface",
    "read_model",
    "read_transform",
    "write_model",
    "write_slicer_folder",
    "write_transform",
]

logger = logging.getLogger(__name__)

_TRANSFORM_SUFFIXES = (".h5", ".hdf5", ".tfm", ".txt", ".mat")
_RAS_TO_LPS = np.array([-1.0, -1.0, 1.0])
_SAFE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")


def _affine(T: object, name: str) -> np.ndarray:
    """Validate a (4, 4) invertible affine matrix (last row 0 0 0 1) → float64 copy."""
    M = np.array(T, dtype=np.float64)
    if M.shape != (4, 4):
        raise ValueError(f"{name} must have shape (4, 4), got {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ValueError(f"{name} must be finite")
    if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=1e-12):
        raise ValueError(f"{name} must have last row [0, 0, 0, 1], got {M[3].tolist()}")
    if abs(np.linalg.det(M[:3, :3])) < 1e-12:
        raise ValueError(f"{name} is singular")
    M[3] = (0.0, 0.0, 0.0, 1.0)
    return M


def _apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


# --------------------------------------------------------------------------------------------------
# transforms


def write_transform(path: str | Path, ct_from_x: np.ndarray) -> Path:
    """Write ``ct_from_x`` as an ITK transform file Slicer loads as the "x to CT" transform node.

    The file holds the resampling-direction transform ``x_from_ct = inv(ct_from_x)`` (LPS, mm), as
    ITK and Slicer store transforms: ``sitk.ReadTransform(path).TransformPoint(p_ct)`` gives
    ``x_from_ct @ p_ct``. Placed under the loaded node, data given in frame x show in the CT.

    Args:
        path: output file, ``.h5`` (HDF5) or ``.tfm``/``.txt`` (text).
        ct_from_x: (4, 4) affine map from frame-x points to CT points (LPS, mm).

    Returns:
        ``path``.

    Raises:
        ValueError: an unsupported suffix, or a matrix that is not a finite invertible affine.
    """
    path = Path(path)
    if path.suffix.lower() not in _TRANSFORM_SUFFIXES:
        raise ValueError(f"transform file must end in one of {_TRANSFORM_SUFFIXES}, got {path.name!r}")
    x_from_ct = np.linalg.inv(_affine(ct_from_x, "ct_from_x"))
    tx = sitk.AffineTransform(3)
    tx.SetCenter((0.0, 0.0, 0.0))
    tx.SetMatrix([float(v) for v in x_from_ct[:3, :3].ravel()])
    tx.SetTranslation([float(v) for v in x_from_ct[:3, 3]])
    sitk.WriteTransform(tx, str(path))
    return path


def read_transform(path: str | Path) -> np.ndarray:
    """Read an ITK/Slicer linear transform file → the (4, 4) modelling transform ``ct_from_x``.

    The file's transform maps parent (CT) points to child (x) points, ``x_from_ct`` (see
    :func:`write_transform`); its inverse is returned. Any linear ITK transform type (affine,
    Euler, versor, similarity, ..., or a composite of them) is accepted.

    Raises:
        InputError: a missing or unreadable file, a transform that is not 3D or not linear, or a
            singular one (message names the file).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "transform file not found")
    try:
        tx = sitk.ReadTransform(str(path))
    except RuntimeError:
        raise InputError(path, "not a readable ITK transform file") from None
    if tx.GetDimension() != 3:
        raise InputError(path, f"expected a 3D transform, got {tx.GetDimension()}D")
    if not tx.IsLinear():
        raise InputError(path, f"not a linear (affine) transform ({tx.GetName()})")
    origin = np.asarray(tx.TransformPoint((0.0, 0.0, 0.0)), dtype=np.float64)
    x_from_ct = np.eye(4)
    x_from_ct[:3, 3] = origin
    for j in range(3):
        e = [0.0, 0.0, 0.0]
        e[j] = 1.0
        x_from_ct[:3, j] = np.asarray(tx.TransformPoint(e), dtype=np.float64) - origin
    if not np.all(np.isfinite(x_from_ct)) or abs(np.linalg.det(x_from_ct[:3, :3])) < 1e-12:
        raise InputError(path, "singular or non-finite transform")
    return np.linalg.inv(x_from_ct)


# --------------------------------------------------------------------------------------------------
# surface models


def write_model(
    path: str | Path,
    vertices_mm: np.ndarray,
    faces: np.ndarray,
    *,
    binary: bool = True,
    description: str = "fluoronav surface model",
) -> Path:
    """Write a triangle mesh as a VTK legacy polydata file Slicer loads in LPS (``SPACE=LPS``).

    Args:
        path: output ``.vtk`` file.
        vertices_mm: (V, 3) vertices, LPS mm (stored as float64).
        faces: (F, 3) vertex indices of the triangles.
        binary: big-endian binary data (compact) rather than ASCII.
        description: text put before ``SPACE=LPS`` on the header line.

    Returns:
        ``path``.

    Raises:
        ValueError: wrong shapes, non-finite vertices, or face indices outside the vertices.
    """
    path = Path(path)
    V = np.asarray(vertices_mm, dtype=np.float64)
    F = np.asarray(faces)
    if V.ndim != 2 or V.shape[1] != 3:
        raise ValueError(f"vertices_mm must have shape (V, 3), got {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or (F.size and not np.issubdtype(F.dtype, np.integer)):
        raise ValueError(f"faces must be integer with shape (F, 3), got {F.dtype} {F.shape}")
    if not np.all(np.isfinite(V)):
        raise ValueError("vertices_mm must be finite")
    if F.size and (F.min() < 0 or F.max() >= V.shape[0]):
        raise ValueError("faces index vertices that do not exist")
    title = " ".join(f"{description} SPACE=LPS".split())[:255]
    cells = np.column_stack([np.full(F.shape[0], 3), F]).astype(np.int64)
    with open(path, "wb") as fh:
        fh.write(b"# vtk DataFile Version 4.2\n")
        fh.write(title.encode("ascii", "replace") + b"\n")
        fh.write(b"BINARY\n" if binary else b"ASCII\n")
        fh.write(b"DATASET POLYDATA\n")
        fh.write(f"POINTS {V.shape[0]} double\n".encode())
        if binary:
            fh.write(V.astype(">f8").tobytes() + b"\n")
        else:
            fh.write("".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in V.tolist()).encode())
        fh.write(f"POLYGONS {F.shape[0]} {cells.size}\n".encode())
        if binary:
            fh.write(cells.astype(">i4").tobytes() + b"\n")
        else:
            fh.write("".join(f"3 {a} {b} {c}\n" for _, a, b, c in cells.tolist()).encode())
    return path


_VTK_TYPES = {"float": ">f4", "double": ">f8", "int": ">i4", "vtkidtype": ">i4", "long": ">i8"}


def _next_line(data: bytes, pos: int) -> tuple[str, int]:
    """The next non-empty text line at or after ``pos`` and the position after it."""
    while pos < len(data):
        end = data.find(b"\n", pos)
        end = len(data) if end < 0 else end
        line = data[pos:end].decode("ascii", "replace").strip()
        pos = end + 1
        if line:
            return line, pos
    return "", pos


def read_model(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a VTK legacy polydata triangle mesh (as :func:`write_model` writes) → LPS vertices, faces.

    Reads ASCII and binary files of legacy version ≤ 4.2 with ``POINTS`` and triangle
    ``POLYGONS``; a ``SPACE=RAS`` header converts the vertices to LPS (negated x, y), otherwise LPS
    is assumed (as Slicer does).

    Returns:
        ``(vertices (V, 3) float64 LPS mm, faces (F, 3) int64)``.

    Raises:
        InputError: a missing file, or one that is not such a polydata file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "model file not found")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(path, f"unreadable model file ({exc.__class__.__name__})") from None
    lines = data.split(b"\n", 4)
    if len(lines) < 5 or not lines[0].startswith(b"# vtk DataFile Version"):
        raise InputError(path, "not a VTK legacy file")
    title = lines[1].decode("ascii", "replace")
    mode = lines[2].strip().upper()
    if mode not in (b"ASCII", b"BINARY") or lines[3].strip().upper() != b"DATASET POLYDATA":
        raise InputError(path, "expected an ASCII or BINARY 'DATASET POLYDATA' VTK file")
    binary = mode == b"BINARY"
    pos = sum(len(line) + 1 for line in lines[:4])
    arrays: dict[str, np.ndarray] = {}
    tokens: list[str] = []
    if not binary:
        tokens = data[pos:].decode("ascii", "replace").split()
    t = 0
    try:
        while len(arrays) < 2:
            if binary:
                line, pos = _next_line(data, pos)
                words = line.split()
            else:
                words = tokens[t : t + 3]
                t += 3
            if len(words) != 3 or words[0].upper() not in ("POINTS", "POLYGONS"):
                raise InputError(path, f"expected POINTS and POLYGONS sections, got {' '.join(words)!r}")
            key = words[0].upper()
            n, second = int(words[1]), words[2]
            count = 3 * n if key == "POINTS" else int(second)
            dtype = _VTK_TYPES.get(second.lower(), "") if key == "POINTS" else ">i4"
            if not dtype or n < 0 or count < 0:
                raise InputError(path, f"unsupported {key} section {' '.join(words)!r}")
            if binary:
                size = count * np.dtype(dtype).itemsize
                if pos + size > len(data):
                    raise InputError(path, f"truncated {key} data")
                values = np.frombuffer(data, dtype=dtype, count=count, offset=pos)
                pos += size
            else:
                if t + count > len(tokens):
                    raise InputError(path, f"truncated {key} data")
                values = np.asarray(tokens[t : t + count], dtype=np.float64)
                t += count
            arrays[key] = values.astype(np.float64 if key == "POINTS" else np.int64)
    except ValueError:
        raise InputError(path, "malformed POINTS or POLYGONS data") from None
    vertices = arrays["POINTS"].reshape(-1, 3)
    cells = arrays["POLYGONS"]
    if cells.size % 4 or (cells.size and np.any(cells[::4] != 3)):
        raise InputError(path, "POLYGONS must all be triangles")
    faces = cells.reshape(-1, 4)[:, 1:]
    if faces.size and (faces.min() < 0 or faces.max() >= vertices.shape[0]):
        raise InputError(path, "POLYGONS index points that do not exist")
    if "SPACE=RAS" in title:
        vertices = vertices * _RAS_TO_LPS
    return vertices, faces


def femur_surface(
    volume: Volume, label_name: str, *, max_faces: int = 100_000
) -> tuple[np.ndarray, np.ndarray]:
    """Surface mesh of a labelled structure (e.g. ``"femur_left"``) in the CT world frame.

    Marching cubes (``skimage.measure.marching_cubes``, level 0.5) on the label's binary mask,
    zero-padded so that the surface is closed. The voxel step is the smallest that keeps the mesh
    at most ``max_faces`` triangles. Vertices are mapped from (i, j, k) index to world by
    :attr:`Volume.world_from_index` (direction, anisotropic spacing and origin); faces wind
    outwards (right-hand rule).

    Args:
        volume: the CT with ``labels`` and ``label_names``.
        label_name: name of the label to mesh.
        max_faces: the mesh's triangle budget.

    Returns:
        ``(vertices (V, 3) float64 CT LPS mm, faces (F, 3) int64)``.

    Raises:
        ValueError: no label map, an unknown label name, an empty label, or no surface within the
            budget.
    """
    if volume.labels is None:
        raise ValueError(f"volume {volume.name!r} has no label map")
    value = volume.label_value(label_name)
    if value is None:
        raise ValueError(f"no label named {label_name!r} (labels: {sorted(volume.label_names.values())})")
    mask = volume.labels == value
    if not mask.any():
        raise ValueError(f"label {label_name!r} has no voxels")
    nz = np.nonzero(mask)
    lo = np.array([int(a.min()) for a in nz])
    hi = np.array([int(a.max()) for a in nz]) + 1
    crop = mask[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    padded = np.pad(crop, 1).astype(np.float32)
    boundary = int(np.count_nonzero(crop & ~ndimage.binary_erosion(np.pad(crop, 1))[1:-1, 1:-1, 1:-1]))
    step = max(1, math.ceil(math.sqrt(2.0 * boundary / max(max_faces, 1))))
    while True:
        try:
            verts_kji, faces, _, _ = marching_cubes(padded, level=0.5, step_size=step, allow_degenerate=False)
        except (RuntimeError, ValueError):
            raise ValueError(f"no surface for label {label_name!r} at a step of {step} voxels") from None
        if faces.shape[0] <= max_faces:
            break
        step += 1
    logger.debug("%s: %s surface at step %d: %d faces", volume.name, label_name, step, faces.shape[0])
    ijk = (verts_kji + (lo - 1))[:, ::-1]
    vertices = _apply(volume.world_from_index, ijk.astype(np.float64))
    faces = faces.astype(np.int64)
    if mesh_volume(vertices, faces) < 0:
        faces = faces[:, ::-1].copy()
    return vertices, faces


def cm_surface(
    cm: CMKinematics | CMConfig | None, control_points_deg: np.ndarray | torch.Tensor, *, segments: int = 48
) -> tuple[np.ndarray, np.ndarray]:
    """Surface mesh of the bent CM in its own (base) frame.

    Args:
        cm: the CM model (kinematics or geometry; the paper's CM when None).
        control_points_deg: (n,) control points.
        segments: polygon segments approximating a full circle.

    Returns:
        ``(vertices (V, 3) float64 mm in the CM frame, faces (F, 3) int64)``, outward normals.
    """
    config = cm.config if isinstance(cm, CMKinematics) else cm
    return cm_surface_mesh(config, control_points_deg, segments=segments)


# --------------------------------------------------------------------------------------------------
# the slicer/ folder

_README = """\
3D Slicer scene files of a fluoronav navigation result
=====================================================

Positions are in the CT's coordinate system (LPS, mm) unless noted, so the models and markups load
in place over the CT they were computed for. Drag the CT (your own volume file) and then these
files into Slicer's window:

  cm.vtk              the continuum manipulator (CM) surface, already placed in the CT
  femur.vtk           the femur surface, already placed in the CT
{plan_line}  landmarks.mrk.json  the CT landmarks (point list)
  ct_from_cm.h5       transform node "ct_from_cm": CM frame -> CT
  ct_from_femur.h5    transform node "ct_from_femur": femur frame -> CT
{extra}
Use either cm.vtk on its own, or cm_in_cm_frame.vtk under the transform, not both:

  cm_in_cm_frame.vtk  the same CM surface in the CM's own frame. It shows in the right place only
                      under ct_from_cm: in the Data module, drag cm_in_cm_frame onto ct_from_cm
                      (or in the Transforms module select ct_from_cm and apply it to the model).
                      Editing ct_from_cm then moves the CM in the CT.

Transform files are ITK files in LPS storing the resampling ("from parent") direction, as Slicer
reads them: the node's "to parent" transform is the named map (e.g. CM -> CT). Models are VTK
polydata with SPACE=LPS in the header; markups are Slicer .mrk.json files in LPS.
"""


def _write_plan(out: Path, plan_points: Mapping[str, np.ndarray]) -> tuple[Path, str]:
    """``out/plan.mrk.json`` of the (non-empty) plan: a Line for two points, a Curve for more, a point
    list for one → its path and its line in the folder's README."""
    n_plan = len(plan_points)
    plan_kind: Literal["Fiducial", "Line", "Curve"] = (
        "Line" if n_plan == 2 else ("Curve" if n_plan > 2 else "Fiducial")
    )
    path = write_markups(
        out / "plan.mrk.json", plan_points, name="plan", kind=plan_kind, color=(1.0, 0.9, 0.1)
    )
    shape = {"Line": "a line", "Curve": "a curve", "Fiducial": "a point"}[plan_kind]
    return path, f"  plan.mrk.json       the plan ({shape}: {' -> '.join(plan_points)})\n"


def write_slicer_folder(
    out_dir: str | Path,
    *,
    ct_from_cm: np.ndarray,
    ct_from_femur: np.ndarray,
    cm_vertices_cm: np.ndarray,
    cm_faces: np.ndarray,
    femur_vertices_ct: np.ndarray,
    femur_faces: np.ndarray,
    plan_points: Mapping[str, np.ndarray],
    landmarks: Mapping[str, np.ndarray],
    extra_transforms: Mapping[str, np.ndarray] | None = None,
) -> list[Path]:
    """Write a folder of files a 3D Slicer user drags in to see the navigation result over the CT.

    Files (all LPS, mm; see the folder's ``README.txt``):

    * ``ct_from_cm.h5``, ``ct_from_femur.h5``: transform files (:func:`write_transform`), plus
      ``<name>.h5`` for each of ``extra_transforms`` (name → ``ct_from_x``).
    * ``cm.vtk``: the CM surface mapped into the CT by ``ct_from_cm`` (shows in place as is).
    * ``cm_in_cm_frame.vtk``: the CM surface in its own frame, to place under ``ct_from_cm``.
    * ``femur.vtk``: the femur surface, CT coordinates.
    * ``plan.mrk.json``: ``plan_points`` in order, a Line for two points (e.g. entry point → tip
      target), a Curve for more, a point list for one; not written when there are none.
    * ``landmarks.mrk.json``: the landmarks as a point list.
    * ``README.txt``: what to load and what each file is.

    Args:
        out_dir: the folder (created if needed; files in it are overwritten).
        ct_from_cm: (4, 4) CM frame → CT.
        ct_from_femur: (4, 4) femur frame → CT.
        cm_vertices_cm: (V, 3) CM mesh vertices in the CM frame (see :func:`cm_surface`).
        cm_faces: (F, 3) CM mesh faces.
        femur_vertices_ct: (V', 3) femur mesh vertices, CT (see :func:`femur_surface`).
        femur_faces: (F', 3) femur mesh faces.
        plan_points: label → (3,) CT point, in order (may be empty: no plan file).
        landmarks: name → (3,) CT point.
        extra_transforms: more transforms to write, file stem → (4, 4) ``ct_from_x``.

    Returns:
        The written paths.

    Raises:
        ValueError: invalid matrices, meshes or points, or an extra transform name that is not a
            plain file stem or clashes with another file.
    """
    out = Path(out_dir)
    ct_from_cm = _affine(ct_from_cm, "ct_from_cm")
    ct_from_femur = _affine(ct_from_femur, "ct_from_femur")
    extra = dict(extra_transforms or {})
    for stem in extra:
        if not _SAFE_NAME.fullmatch(stem) or stem in ("ct_from_cm", "ct_from_femur"):
            raise ValueError(f"extra transform name {stem!r} is not a free, plain file stem")
    out.mkdir(parents=True, exist_ok=True)
    written = [
        write_transform(out / "ct_from_cm.h5", ct_from_cm),
        write_transform(out / "ct_from_femur.h5", ct_from_femur),
    ]
    written += [write_transform(out / f"{stem}.h5", T) for stem, T in extra.items()]
    cm_vertices = np.asarray(cm_vertices_cm, dtype=np.float64)
    written.append(write_model(out / "cm.vtk", _apply(ct_from_cm, cm_vertices), cm_faces, description="CM"))
    written.append(
        write_model(out / "cm_in_cm_frame.vtk", cm_vertices, cm_faces, description="CM in the CM frame")
    )
    written.append(write_model(out / "femur.vtk", femur_vertices_ct, femur_faces, description="femur"))
    plan_line = ""
    if plan_points:
        plan_path, plan_line = _write_plan(out, plan_points)
        written.append(plan_path)
    written.append(
        write_markups(out / "landmarks.mrk.json", landmarks, name="landmarks", color=(1.0, 0.5, 0.5))
    )
    extra_lines = "".join(f"  {stem + '.h5':<18}  transform node {stem!r}\n" for stem in extra)
    readme = _README.format(plan_line=plan_line, extra=extra_lines)
    (out / "README.txt").write_text(readme, encoding="utf-8")
    written.append(out / "README.txt")
    logger.info("wrote %d Slicer files to %s", len(written), out)
    return written
