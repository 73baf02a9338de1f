"""C-arm cameras from the geometry tags of X-ray DICOM files (e.g. Siemens CIOS Fusion).

Tags (all optional except the image size; missing ones fall back to the CIOS Fusion preset; see
docs/data-formats.md, "X-ray images"): Imager Pixel Spacing (0018,1164) else Pixel Spacing
(0028,0030), Distance Source to Detector (0018,1110), Distance Source to Patient (0018,1111; else
450/1020 of the SDD), Positioner Primary (0018,1510) and Secondary (0018,1511) Angle.

World frame of the returned camera: the C-arm's isocentre frame, patient LPS axes for a supine
patient (the frame of :func:`~fluoronav.geometry.carm.carm_camera`). The DICOM angles give the
detector's position (LAO: to the patient's left; CRA: to the head), hence ``lao_rao_deg = −primary`` and
``cran_caud_deg = 90 + secondary``. Principal point: the image centre (a camera file is more accurate).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fluoronav.errors import InputError
from fluoronav.geometry.camera import CIOS_FUSION, Camera, DetectorSpec
from fluoronav.geometry.carm import carm_camera_from_world

__all__ = ["camera_from_dicom", "camera_from_dicom_tags"]


def _number(tags: dict[str, str], key: str, source: str) -> float | None:
    value = tags.get(key)
    if value is None or not value.strip():
        return None
    try:
        x = float(np.mean([float(v) for v in value.split("\\")]))
    except ValueError:
        raise InputError(source, f"DICOM tag ({key.replace('|', ',')}) is not numeric: {value!r}") from None
    if not np.isfinite(x):
        raise InputError(source, f"DICOM tag ({key.replace('|', ',')}) is not finite")
    return x


def camera_from_dicom_tags(
    tags: dict[str, str], rows: int, cols: int, *, source: str = "DICOM", fallback: DetectorSpec = CIOS_FUSION
) -> Camera:
    """A camera from DICOM geometry tags (keys as ``"0018|1110"``; see the module docstring).

    Raises:
        InputError: a tag that is not a number, or distances that do not make a C-arm (source to
            detector ≤ source to isocentre, non-positive values).
    """
    spacing = _number(tags, "0018|1164", source) or _number(tags, "0028|0030", source)
    if spacing is None:  # the preset's pitch, scaled to this image size
        spacing = fallback.pixel_spacing_mm * fallback.cols / cols
    sdd = _number(tags, "0018|1110", source) or fallback.sdd_mm
    sid = _number(tags, "0018|1111", source) or sdd * 450.0 / 1020.0  # the simulations' mid value
    primary = _number(tags, "0018|1510", source) or 0.0
    secondary = _number(tags, "0018|1511", source) or 0.0
    if spacing <= 0 or sdd <= 0 or sid <= 0 or sid >= sdd:
        raise InputError(
            source,
            f"implausible C-arm geometry: pixel {spacing} mm, source-detector {sdd} mm, "
            f"source-isocentre {sid} mm",
        )
    spec = DetectorSpec(rows=rows, cols=cols, pixel_spacing_mm=spacing, sdd_mm=sdd)
    T = carm_camera_from_world(
        lao_rao_deg=-primary, cran_caud_deg=90.0 + secondary, source_to_isocenter_mm=sid
    )
    return Camera.from_detector(spec, T)


def camera_from_dicom(path: str | Path) -> Camera:
    """Read a single-frame X-ray DICOM's geometry tags and build its camera (module docstring)."""
    import SimpleITK as sitk  # noqa: N813  # heavy: SimpleITK, for DICOM input only

    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    try:
        reader.ReadImageInformation()
    except RuntimeError:
        raise InputError(path, "unreadable DICOM (no image information)") from None
    size = reader.GetSize()
    if len(size) < 2 or (len(size) == 3 and size[2] != 1):
        raise InputError(path, f"expected one 2-D frame, got size {size}")
    tags = {k: reader.GetMetaData(k) for k in reader.GetMetaDataKeys()}
    return camera_from_dicom_tags(tags, rows=int(size[1]), cols=int(size[0]), source=str(path))
