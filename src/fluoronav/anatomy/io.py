"""Reading and writing CT volumes with their label maps and landmarks (docs/data-formats.md).

Formats: NIfTI, NRRD, MetaImage and DICOM series (a directory; the series with the most files is
read). Geometry is kept exactly as SimpleITK reads it (world = LPS, mm): spacing, origin and
direction cosines. Sibling files next to the CT (``<stem>``: the file name without its format
suffix, or the DICOM directory's name): ``<stem>_labels.<ext>`` (a label map on the CT's grid),
``<stem>.labels.json`` (label names) and ``<stem>_landmarks.fcsv`` or ``<stem>_landmarks.json``
(landmarks, :mod:`fluoronav.anatomy.landmarks`; the FCSV wins when both exist).
"""

from __future__ import annotations

import gzip
import json
import logging
import re
import struct
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import SimpleITK as sitk  # noqa: N813

import fluoronav.anatomy.phantom as phantom
from fluoronav.anatomy.landmarks import read_landmarks, write_landmarks_json
from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError

__all__ = ["VOLUME_SUFFIXES", "load_ct", "load_label_map", "resolve_ct", "save_volume", "split_stem"]

logger = logging.getLogger(__name__)

#: Volume file suffixes understood by :func:`load_ct` (longest first so ``.nii.gz`` wins over ``.gz``).
VOLUME_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd")

_DIRECTION_TOL = 1e-4


def split_stem(path: str | Path) -> tuple[str, str]:
    """``(stem, suffix)``: ``ct.nii.gz`` → ``("ct", ".nii.gz")``, a folder → ``(name, "")``."""
    path = Path(path)
    name = path.name
    for suffix in VOLUME_SUFFIXES:
        if name.lower().endswith(suffix):
            return name[: -len(suffix)], name[len(name) - len(suffix) :]
    return (path.stem, path.suffix) if path.suffix and not path.is_dir() else (name, "")


# ---------------------------------------------------------------------------------------------
# Header sniffing: ITK silently turns a missing spacing into 1 and a negative one into a flipped
# direction, so the declared spacing is checked in the header itself where the format allows.
# ---------------------------------------------------------------------------------------------


def _text_header(path: Path, limit: int = 65536) -> str:
    with open(path, "rb") as f:
        head = f.read(limit)
    return head.decode("latin-1")


def _declared_spacing(path: Path) -> list[float] | None:
    """Spacing values the header declares, or None where the header does not say / is not parsed."""
    suffix = split_stem(path)[1].lower()
    try:
        if suffix in (".mha", ".mhd"):
            header = _text_header(path)
            m = re.search(r"^\s*Element(?:Spacing|Size)\s*=\s*(.+)$", header, re.MULTILINE)
            return [float(v) for v in m.group(1).split()] if m else None
        if suffix in (".nrrd", ".nhdr"):
            header = _text_header(path).split("\n\n", 1)[0]
            m = re.search(r"^space directions:\s*(.+)$", header, re.MULTILINE)
            if m:
                vecs = re.findall(r"\(([^)]*)\)", m.group(1))
                return [float(np.linalg.norm([float(c) for c in v.split(",")])) for v in vecs]
            m = re.search(r"^spacings:\s*(.+)$", header, re.MULTILINE)
            if m:
                return [float(v) for v in m.group(1).split() if v.lower() != "nan"]
            return None
        if suffix in (".nii", ".nii.gz"):
            opener = gzip.open if suffix == ".nii.gz" else open
            with opener(path, "rb") as f:
                raw = f.read(540)
            for endian in "<>":
                if len(raw) >= 348 and struct.unpack(endian + "i", raw[:4])[0] == 348:
                    return list(struct.unpack(endian + "8f", raw[76:108])[1:4])
                if len(raw) >= 540 and struct.unpack(endian + "i", raw[:4])[0] == 540:
                    return list(struct.unpack(endian + "8d", raw[104:168])[1:4])
            return None
    except (OSError, ValueError, EOFError, struct.error):
        return None
    return None


# ---------------------------------------------------------------------------------------------
# Reading
# ---------------------------------------------------------------------------------------------


def _read_image(path: Path) -> sitk.Image:
    """Read a volume file or a DICOM directory with SimpleITK, turning failures into InputError."""
    if not path.exists():
        raise InputError(path, "file not found")
    if path.is_dir():
        reader = sitk.ImageSeriesReader()
        try:
            series = reader.GetGDCMSeriesIDs(str(path)) or ()
            files = [reader.GetGDCMSeriesFileNames(str(path), sid) for sid in series]
        except RuntimeError:
            files = []
        files = [f for f in files if f]
        if not files:
            raise InputError(path, "no DICOM series found in directory")
        chosen = max(files, key=len)
        if len(files) > 1:
            logger.info("%s: %d DICOM series, reading the largest (%d files)", path, len(files), len(chosen))
        reader.SetFileNames(chosen)
        try:
            return reader.Execute()
        except RuntimeError as exc:
            raise InputError(path, f"unreadable DICOM series ({_itk_reason(exc)})") from None
    if path.stat().st_size == 0:
        raise InputError(path, "empty file")
    declared = _declared_spacing(path)
    if declared is not None and any(not np.isfinite(s) or s <= 0 for s in declared[:3]):
        raise InputError(path, f"invalid voxel spacing {declared[:3]} (must be positive)")
    try:
        return sitk.ReadImage(str(path))
    except RuntimeError as exc:
        raise InputError(path, f"unreadable image ({_itk_reason(exc)})") from None


def _itk_reason(exc: RuntimeError) -> str:
    """The useful last line of an ITK exception, shortened to one line."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    text = lines[-1] if lines else "unknown error"
    text = re.sub(r"^.*ITK ERROR:\s*", "", text)
    return text[:160]


def _check_geometry(image: sitk.Image, source: Path, what: str) -> None:
    if image.GetNumberOfComponentsPerPixel() != 1:
        raise InputError(source, f"not a {what}: {image.GetNumberOfComponentsPerPixel()}-channel image")
    dim = image.GetDimension()
    if dim != 3:
        raise InputError(source, f"not a {what}: {dim}D image (expected a 3D volume)")
    size = image.GetSize()
    if min(size) == 0:
        raise InputError(source, "empty image (zero voxels)")
    if min(size) < 2:
        raise InputError(source, f"not a {what}: volume of size {size} has a singleton dimension")
    spacing = np.asarray(image.GetSpacing(), dtype=np.float64)
    if not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
        raise InputError(source, f"invalid voxel spacing {tuple(spacing)} (must be positive)")
    origin = np.asarray(image.GetOrigin(), dtype=np.float64)
    if not np.all(np.isfinite(origin)):
        raise InputError(source, "non-finite origin")
    direction = np.asarray(image.GetDirection(), dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(direction)) or not np.allclose(
        direction.T @ direction, np.eye(3), atol=_DIRECTION_TOL
    ):
        raise InputError(source, "direction cosines are not orthonormal")


def _geometry(image: sitk.Image) -> tuple[tuple[float, ...], tuple[float, ...], np.ndarray]:
    return (
        tuple(image.GetSpacing()),
        tuple(image.GetOrigin()),
        np.asarray(image.GetDirection(), dtype=np.float64).reshape(3, 3),
    )


def _find_sibling(base: Path, stem: str, tails: tuple[str, ...]) -> Path | None:
    for tail in tails:
        candidate = base / f"{stem}{tail}"
        if candidate.is_file():
            return candidate
    return None


def _read_label_names(path: Path) -> dict[int, str]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise InputError(path, f"line {exc.lineno}: invalid JSON ({exc.msg})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"unreadable label-name file ({exc.__class__.__name__})") from None
    if isinstance(doc, dict) and isinstance(doc.get("labels"), dict):
        doc = doc["labels"]
    if not isinstance(doc, dict):
        raise InputError(path, 'expected an object of label value → name, e.g. {"1": "pelvis"}')
    names: dict[int, str] = {}
    for key, value in doc.items():
        try:
            names[int(key)] = str(value)
        except ValueError:
            raise InputError(path, f"label value {key!r} is not an integer") from None
    return names


def load_label_map(path: str | Path, *, like: Volume | None = None) -> np.ndarray:
    """Read an integer label map, (nz, ny, nx), checking it lies on ``like``'s grid when given.

    Returns the smallest of uint8 / uint16 / int32 that holds the values.
    """
    path = Path(path)
    image = _read_image(path)
    _check_geometry(image, path, "label map")
    data = sitk.GetArrayFromImage(image)
    if not np.all(np.isfinite(data)) or np.any(data != np.round(data)):
        raise InputError(path, "label map values must be integers")
    if like is not None:
        spacing, origin, direction = _geometry(image)
        same = (
            data.shape == like.data.shape
            and np.allclose(spacing, like.spacing_mm, rtol=1e-4, atol=1e-5)
            and np.allclose(origin, like.origin_mm, rtol=1e-5, atol=1e-3)
            and np.allclose(direction, like.direction, atol=_DIRECTION_TOL)
        )
        if not same:
            raise InputError(
                path, "label map is not on the CT's voxel grid (shape, spacing, origin or direction)"
            )
    lo, hi = int(data.min()), int(data.max())
    if lo < 0:
        raise InputError(path, "label map has negative values")
    dtype = np.uint8 if hi < 256 else np.uint16 if hi < 65536 else np.int32
    return data.astype(dtype)


def load_ct(
    path: str | Path,
    *,
    labels_path: str | Path | None = None,
    landmarks_path: str | Path | None = None,
) -> Volume:
    """Load a CT volume (HU, float32) with optional labels and landmarks.

    Args:
        path: a NIfTI / NRRD / MetaImage file or a DICOM series directory.
        labels_path: an integer label map on the same grid; default: the sibling
            ``<stem>_labels.<ext>`` when present. Names come from ``<stem>.labels.json`` (the CT's
            stem, or else the label file's own stem) when present, else ``label_<value>``.
        landmarks_path: ``.fcsv`` or ``.json`` landmarks; default: ``<stem>_landmarks.fcsv|.json``.

    Returns:
        a :class:`Volume` named ``<stem>``, geometry exactly as SimpleITK reads it (LPS, mm).

    Raises:
        InputError: missing / empty / unreadable file, not a 3D scalar volume (2D image, singleton
            dimension, colour), non-positive or missing spacing, non-orthonormal direction,
            non-finite values, or bad sibling files. The message names the file.
    """
    path = Path(path)
    image = _read_image(path)
    _check_geometry(image, path, "CT")
    data = sitk.GetArrayFromImage(image)
    if data.size == 0:
        raise InputError(path, "empty image (zero voxels)")
    if not np.all(np.isfinite(data)):
        raise InputError(path, "non-finite voxel values (NaN or inf)")
    data = np.ascontiguousarray(data, dtype=np.float32)
    spacing, origin, direction = _geometry(image)
    stem, suffix = split_stem(path)
    base = path.parent
    volume = Volume(
        data=data,
        spacing_mm=spacing,  # type: ignore[arg-type]
        origin_mm=origin,  # type: ignore[arg-type]
        direction=direction,
        name=stem,
    )

    if labels_path is None:
        tails = tuple(f"_labels{s}" for s in ((suffix,) if suffix else ()) + VOLUME_SUFFIXES)
        labels_path = _find_sibling(base, stem, tails)
    if labels_path is not None:
        labels_path = Path(labels_path)
        labels = load_label_map(labels_path, like=volume)
        names_path = _find_sibling(base, stem, (".labels.json",))
        if names_path is None:
            names_path = _find_sibling(
                labels_path.parent, split_stem(labels_path)[0], (".labels.json", ".json")
            )
        present = sorted(int(v) for v in np.unique(labels) if v != 0)
        names = _read_label_names(names_path) if names_path is not None else {}
        label_names = {v: names.get(v, f"label_{v}") for v in present}
        label_names.update({v: n for v, n in names.items() if v not in label_names})
        volume = volume.replace(labels=labels, label_names=label_names)
        logger.debug("%s: labels from %s (%s)", path, labels_path, label_names)

    if landmarks_path is None:
        landmarks_path = _find_sibling(base, stem, ("_landmarks.fcsv", "_landmarks.json"))
    if landmarks_path is not None:
        volume = volume.replace(landmarks_world=read_landmarks(landmarks_path))
    return volume


def resolve_ct(spec: str | Path, *, seed: int = 0) -> Volume:
    """``"phantom"`` → :func:`~fluoronav.anatomy.phantom.hip_phantom` (``seed``), else :func:`load_ct`."""
    if str(spec).strip().lower() == "phantom":
        return phantom.hip_phantom(seed=seed)
    return load_ct(spec)


# ---------------------------------------------------------------------------------------------
# Writing
# ---------------------------------------------------------------------------------------------


def _to_image(array: np.ndarray, volume: Volume) -> sitk.Image:
    image = sitk.GetImageFromArray(np.ascontiguousarray(array))
    image.SetSpacing([float(s) for s in volume.spacing_mm])
    image.SetOrigin([float(o) for o in volume.origin_mm])
    image.SetDirection([float(d) for d in np.asarray(volume.direction, dtype=np.float64).ravel()])
    return image


def save_volume(volume: Volume, path: str | Path, *, compress: bool = True) -> list[Path]:
    """Write a volume (float32) and, when present, its label map, label names and landmarks.

    Args:
        volume: the volume to write.
        path: ``.nii.gz``, ``.nii``, ``.nrrd``, ``.nhdr``, ``.mha`` or ``.mhd`` file.
        compress: compress the voxel data where the format allows.

    Returns:
        the files written: the volume, then ``<stem>_labels.<ext>``, ``<stem>.labels.json`` and
        ``<stem>_landmarks.json`` as applicable; :func:`load_ct` of the first finds the others.
    """
    path = Path(path)
    stem, suffix = split_stem(path)
    if suffix.lower() not in VOLUME_SUFFIXES:
        raise ValueError(f"unsupported volume format {path.name!r}; use one of {', '.join(VOLUME_SUFFIXES)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    written = [path]
    sitk.WriteImage(_to_image(volume.data.astype(np.float32, copy=False), volume), str(path), compress)
    if volume.labels is not None:
        labels_file = path.parent / f"{stem}_labels{suffix}"
        sitk.WriteImage(_to_image(_label_array(volume.labels), volume), str(labels_file), compress)
        written.append(labels_file)
        names_file = path.parent / f"{stem}.labels.json"
        names: Mapping[int, str] = volume.label_names
        names_file.write_text(
            json.dumps({str(k): v for k, v in sorted(names.items())}, indent=2) + "\n", encoding="utf-8"
        )
        written.append(names_file)
    if volume.landmarks_world:
        written.append(write_landmarks_json(path.parent / f"{stem}_landmarks.json", volume.landmarks_world))
    return written


def _label_array(labels: np.ndarray) -> np.ndarray:
    hi = int(labels.max()) if labels.size else 0
    dtype = np.uint8 if hi < 256 else np.uint16 if hi < 65536 else np.int32
    return labels.astype(dtype, copy=False)
