"""Image files as the detector reads them (docs/data-formats.md, "X-ray images").

The detector's input is a detector image after the log transform, bone and metal bright (as
``simulate`` writes them). :func:`load_image` converts other files to that form:

- ``.npz`` (key ``image``), ``.npy`` and float TIFF: taken as-is.
- 8/16-bit PNG/TIFF/JPEG: raw intensities where dark = attenuating; converted with
  ``−ln((I + 1) / (I_max + 1))``, I_max the type's full scale; colour is averaged to grey.
- DICOM (SimpleITK): values after the modality rescale; MONOCHROME2 as-is, MONOCHROME1 inverted
  (max − value). The pixel spacing is Imager Pixel Spacing (0018,1164), else Pixel Spacing
  (0028,0030), when present.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from fluoronav.errors import InputError

__all__ = ["IMAGE_SUFFIXES", "check_image", "load_image"]

IMAGE_SUFFIXES = (".npz", ".npy", ".png", ".tif", ".tiff", ".jpg", ".jpeg", ".dcm", ".dicom")


def check_image(image: np.ndarray, source: str) -> np.ndarray:
    """``image`` as a (rows, cols) float32 array (a single channel or frame dropped); raises
    :class:`~fluoronav.errors.InputError` naming ``source`` for other shapes, non-numeric or
    non-finite values."""
    arr = np.asarray(image)
    if arr.ndim == 3 and 1 in (arr.shape[0], arr.shape[-1]):
        arr = arr.reshape(arr.shape[1:] if arr.shape[0] == 1 else arr.shape[:-1])
    if arr.ndim != 2 or min(arr.shape) < 8:
        raise InputError(source, f"expected a 2-D image of at least 8×8 pixels, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number):
        raise InputError(source, f"image values must be numeric, got {arr.dtype}")
    arr = arr.astype(np.float32)
    if not np.all(np.isfinite(arr)):
        raise InputError(source, "image contains NaN or infinite values")
    return arr


def load_image(path: str | Path) -> tuple[np.ndarray, float | None]:
    """Read an image file as a float32 log image (bright = attenuating) and its pixel spacing (mm).

    See the module docstring for the conversion rules. Raises InputError for unreadable files.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    suffix = path.suffix.lower()
    spacing: float | None = None
    if suffix == ".npz":
        try:
            with np.load(path) as npz:
                if "image" not in npz.files:
                    raise InputError(path, f"no 'image' array (has {', '.join(npz.files) or 'nothing'})")
                arr = np.asarray(npz["image"])
                if "pixel_spacing_mm" in npz.files:
                    spacing = float(np.mean(npz["pixel_spacing_mm"]))
        except (OSError, ValueError, EOFError) as exc:
            raise InputError(path, f"unreadable .npz ({exc.__class__.__name__})") from exc
    elif suffix == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise InputError(path, f"unreadable .npy ({exc.__class__.__name__})") from exc
    elif suffix in (".png", ".tif", ".tiff", ".jpg", ".jpeg"):
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise InputError(path, "unreadable image file")
        if raw.ndim == 3:
            raw = (
                raw[..., :3].astype(np.float64).mean(axis=2).astype(raw.dtype)
                if raw.shape[2] >= 3
                else raw[..., 0]
            )
        if np.issubdtype(raw.dtype, np.integer):
            full = float(np.iinfo(raw.dtype).max)
            arr = -np.log((raw.astype(np.float64) + 1.0) / (full + 1.0))
        else:
            arr = raw
    else:
        arr, spacing = _load_dicom(path)
    return check_image(arr, str(path)), spacing


def _load_dicom(path: Path) -> tuple[np.ndarray, float | None]:
    import SimpleITK as sitk  # noqa: N813  # heavy: SimpleITK, for DICOM input only

    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    try:
        reader.ReadImageInformation()
        img = reader.Execute()
    except RuntimeError as exc:
        raise InputError(path, "unreadable image (not a DICOM or other format SimpleITK reads)") from exc
    arr = sitk.GetArrayFromImage(img).astype(np.float64)
    if arr.ndim == 3:
        if arr.shape[0] != 1:
            raise InputError(path, f"multi-frame image ({arr.shape[0]} frames); give one frame")
        arr = arr[0]

    def tag(key: str) -> str | None:
        return reader.GetMetaData(key).strip() if reader.HasMetaDataKey(key) else None

    if (tag("0028|0004") or "").upper() == "MONOCHROME1":
        arr = arr.max() - arr
    spacing = None
    for key in ("0018|1164", "0028|0030"):
        value = tag(key)
        if value:
            try:
                spacing = float(np.mean([float(x) for x in value.split("\\")]))
                break
            except ValueError:
                continue
    return arr, spacing
