"""Reader of the DeepFluoro data set: real cadaver X-rays with ground-truth poses (HDF5, read lazily).

The user downloads ``ipcai_2020_full_res_data.h5`` (Grupp et al., IJCARS 15(5), 2020; CC BY-NC
4.0); fluoronav ships none of it. The file's layout and what a study does with it: docs/real-data.md.

Frames (docs/conventions.md, "DeepFluoro frames"): a projection's camera is returned in fluoronav's
convention (OpenCV, ``camera_from_world`` with world = the specimen's CT, LPS mm, the pelvis at its
CT pose), its image and 2D landmarks flipped to match (:mod:`fluoronav.anatomy.deepfluoro_frames`).
A femur's pose is ``world_from_femur``: the CT's femur moved to where the image shows it. Labels
become fluoronav's ``pelvis`` (what moves with the pelvis), ``femur_left`` and ``femur_right``.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fluoronav.anatomy.deepfluoro_frames import ImageFlip, df_camera_from_ct, fluoronav_camera
from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError
from fluoronav.geometry.camera import Camera

__all__ = [
    "BONE_LABELS",
    "COLLIMATOR_BORDER_PX",
    "FULL_SIZE_PX",
    "LANDMARK_ALIASES",
    "SPECIMEN_IDS",
    "DeepFluoroFile",
    "DeepFluoroProjection",
    "ProjectionParameters",
    "line_integral",
]

log = logging.getLogger(__name__)

#: the paper's specimens 1–6 (the repository's README maps them so)
SPECIMEN_IDS = ("17-1882", "18-1109", "18-0725", "18-2799", "18-2800", "17-1905")
#: fluoronav's label values of the volumes the reader returns
BONE_LABELS = {1: "pelvis", 2: "femur_left", 3: "femur_right"}
#: the data set's label values by the README (1–6) and xReg's pelvis sample (7: lower sacrum)
_LABELS_BY_VALUE = {
    1: "pelvis",
    2: "pelvis",
    3: "pelvis",
    4: "pelvis",
    5: "femur_left",
    6: "femur_right",
    7: "pelvis",
}
#: landmark names fluoronav's registrations look for, from the data set's
LANDMARK_ALIASES = {
    "FH-l": "femoral_head_left",
    "FH-r": "femoral_head_right",
    "ASIS-l": "asis_left",
    "ASIS-r": "asis_right",
}
#: the data set's image side; its preprocessing crops 50 pixels of collimator from each border
FULL_SIZE_PX = 1536
COLLIMATOR_BORDER_PX = 50


def _array(node: Any, name: str, source: str) -> np.ndarray:
    try:
        return np.asarray(node[name][()])
    except KeyError:
        raise InputError(source, f"missing {name!r} (not the DeepFluoro full-resolution layout)") from None


def _scalar(node: Any, name: str, source: str, default: float | None = None) -> float:
    if default is not None and name not in node:
        return default
    return float(_array(node, name, source).reshape(-1)[0])


def _text(value: Any) -> str:
    v = value.reshape(-1)[0] if isinstance(value, np.ndarray) else value
    return v.decode("utf-8") if isinstance(v, bytes) else str(v)


def line_integral(intensity: np.ndarray) -> np.ndarray:
    """Stored detector intensities (bone dark) → −ln(I / I_max), float32 (bone bright), as the
    data set's preprocessing log-transforms them (Beer–Lambert); non-positive pixels are clipped."""
    a = np.asarray(intensity, np.float64)
    top = float(a.max()) if a.size else 1.0
    if not np.isfinite(top) or top <= 0:
        raise ValueError("the image has no positive intensity")
    return (-np.log(np.clip(a, top * 1e-9, None) / top)).astype(np.float32)


@dataclass(frozen=True)
class ProjectionParameters:
    """``proj-params``: DeepFluoro's intrinsics (negative focal lengths), extrinsic, image size and
    pixel pitch (mm), shared by all images."""

    intrinsic: np.ndarray
    extrinsic: np.ndarray
    rows: int
    cols: int
    pixel_spacing_mm: float


@dataclass(frozen=True, eq=False)
class DeepFluoroProjection:
    """One image with its ground truth, in fluoronav's frames.

    Attributes:
        specimen, index: where it is in the file (``projections/<index:03d>``).
        image: (rows, cols) float32 stored intensities (bone dark), flipped to the camera.
        camera: the ground-truth camera (``camera_from_world``: world = the specimen's CT, LPS).
        flip: the flips applied to the stored image and pixels.
        rot_180_for_up: the stored ``rot-180-for-up`` flag.
        landmarks_px: name → (2,) ground-truth 2D landmark in ``image``'s pixels (may lie outside).
        world_from_femur: side → (4, 4) the femur's ground-truth pose (CT femur → world).
        femur_good_fov: side → the data set's flag that enough femur shows for its pose to hold.
    """

    specimen: str
    index: int
    image: np.ndarray
    camera: Camera
    flip: ImageFlip
    rot_180_for_up: bool
    landmarks_px: dict[str, np.ndarray] = field(default_factory=dict)
    world_from_femur: dict[str, np.ndarray] = field(default_factory=dict)
    femur_good_fov: dict[str, bool] = field(default_factory=dict)

    def cropped_line_integral(self, border_px: int | None = None) -> tuple[np.ndarray, Camera]:
        """The image as −ln(I/I_max) without its collimator border, and the matching camera.

        ``border_px``: pixels cropped from each side; default the data set's 50 of 1536, scaled to
        this image's size.
        """
        b = round(COLLIMATOR_BORDER_PX * self.camera.cols / FULL_SIZE_PX) if border_px is None else border_px
        if b < 0 or 2 * b >= min(self.camera.rows, self.camera.cols):
            raise ValueError(f"border of {b} px does not fit a {self.camera.rows}x{self.camera.cols} image")
        r, c = self.camera.rows - 2 * b, self.camera.cols - 2 * b
        cam = self.camera.crop(row0=b, col0=b, rows=r, cols=c)
        return line_integral(self.image[b : b + r, b : b + c]), cam

    def landmark_residual_px(self, landmarks_world: dict[str, np.ndarray]) -> float | None:
        """Mean |camera.project(3D landmark) − 2D landmark| over the landmarks inside the image (px):
        ~0 when the frames are read right (the 2D landmarks are the 3D ones projected with the
        ground-truth poses); None when none is inside."""
        names = [n for n in self.landmarks_px if n in landmarks_world]
        if not names:
            return None
        uv = np.stack([self.landmarks_px[n] for n in names])
        inside = (
            (uv[:, 0] >= 0)
            & (uv[:, 1] >= 0)
            & (uv[:, 0] <= self.camera.cols - 1)
            & (uv[:, 1] <= self.camera.rows - 1)
        )
        if not inside.any():
            return None
        proj = self.camera.project(np.stack([landmarks_world[n] for n in names]))
        return float(np.linalg.norm(proj[inside] - uv[inside], axis=1).mean())


class DeepFluoroFile:
    """The DeepFluoro full-resolution HDF5 file, opened read-only; arrays are read on demand.

    Args:
        path: the user's ``ipcai_2020_full_res_data.h5`` (or a file of the same layout).
        xreg_texture_correction: apply to every ground-truth pose the −0.5 mm shift per CT axis that
            xReg's pelvis sample programs apply to ``cam-to-pelvis-vol`` ("an inconsistency with
            linear interpolation texture indexing between when the ground truth was constructed and
            now"); off by default, as the file documents the poses (see docs/real-data.md).

    Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, path: str | Path, *, xreg_texture_correction: bool = False) -> None:
        import h5py  # optional at import time: only the DeepFluoro reader needs it

        self.path = Path(path)
        self.source = str(self.path)
        self.xreg_texture_correction = xreg_texture_correction
        try:
            self._h5 = h5py.File(self.path, "r")
        except FileNotFoundError:
            raise InputError(self.path, "DeepFluoro file not found") from None
        except OSError as exc:
            raise InputError(self.path, f"not an HDF5 file ({exc})") from None
        if "proj-params" not in self._h5:
            self._h5.close()
            raise InputError(self.path, "no proj-params group: not the DeepFluoro full-resolution file")
        self._params: ProjectionParameters | None = None

    def close(self) -> None:
        self._h5.close()

    def __enter__(self) -> DeepFluoroFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----- what the file holds ---------------------------------------------------------------
    @property
    def specimens(self) -> tuple[str, ...]:
        """Specimen groups, in the paper's order where known."""
        names = [k for k in self._h5 if k != "proj-params"]
        order = {s: i for i, s in enumerate(SPECIMEN_IDS)}
        return tuple(sorted(names, key=lambda s: (order.get(s, len(order)), s)))

    def resolve_specimen(self, name: str) -> str:
        """A specimen ID from an ID or the paper's number (1–6)."""
        s = str(name).strip()
        if s in self._h5 and s != "proj-params":
            return s
        if s.isdigit() and 1 <= int(s) <= len(SPECIMEN_IDS) and SPECIMEN_IDS[int(s) - 1] in self._h5:
            return SPECIMEN_IDS[int(s) - 1]
        raise InputError(self.path, f"no specimen {name!r} (has {', '.join(self.specimens)})")

    def projection_indices(self, specimen: str) -> tuple[int, ...]:
        """The projection numbers of a specimen, ascending."""
        g = self._group(specimen)
        if "projections" not in g:
            return ()
        return tuple(sorted(int(k) for k in g["projections"] if k.isdigit()))

    @property
    def parameters(self) -> ProjectionParameters:
        """``proj-params`` (read once)."""
        if self._params is None:
            g = self._h5["proj-params"]
            col = _scalar(g, "pixel-col-spacing", self.source)
            row = _scalar(g, "pixel-row-spacing", self.source)
            if not np.isclose(col, row, rtol=1e-6):
                raise InputError(self.path, f"non-square pixels ({col} × {row} mm) are not supported")
            self._params = ProjectionParameters(
                intrinsic=_array(g, "intrinsic", self.source).astype(np.float64).reshape(3, 3),
                extrinsic=_array(g, "extrinsic", self.source).astype(np.float64).reshape(4, 4),
                rows=int(_scalar(g, "num-rows", self.source)),
                cols=int(_scalar(g, "num-cols", self.source)),
                pixel_spacing_mm=col,
            )
        return self._params

    def _group(self, specimen: str) -> Any:
        return self._h5[self.resolve_specimen(specimen)]

    # ----- 3D ----------------------------------------------------------------------------------
    def landmarks_world(self, specimen: str) -> dict[str, np.ndarray]:
        """The specimen's 3D landmarks (file names, e.g. ``FH-l``), LPS mm."""
        g = self._group(specimen)
        if "vol-landmarks" not in g:
            return {}
        lm = g["vol-landmarks"]
        return {name: _array(lm, name, self.source).astype(np.float64).reshape(3) for name in lm}

    def _image_geometry(self, g: Any) -> tuple[tuple[float, ...], tuple[float, ...], np.ndarray]:
        spacing = tuple(_array(g, "spacing", self.source).astype(np.float64).reshape(-1))
        origin = tuple(_array(g, "origin", self.source).astype(np.float64).reshape(-1))
        direction = _array(g, "dir-mat", self.source).astype(np.float64) if "dir-mat" in g else np.eye(3)
        return spacing, origin, direction.reshape(3, 3)

    def _bone_lut(self, g: Any) -> np.ndarray:
        """Label value → fluoronav label value (0: background), by name where defined."""
        names: dict[int, str] = {}
        if "vol-seg/labels-def" in g:
            defs = g["vol-seg/labels-def"]
            names = {int(k): _text(defs[k][()]).lower() for k in defs if k.isdigit()}
        value_of = {v: k for k, v in BONE_LABELS.items()}
        lut = np.zeros(256, np.uint8)
        for value in set(names) | set(_LABELS_BY_VALUE):
            bone = _bone_by_name(names[value]) if value in names else None
            bone = bone or _LABELS_BY_VALUE.get(value)
            if bone is not None and 0 <= value < 256:
                lut[value] = value_of[bone]
        return lut

    def volume(self, specimen: str) -> Volume:
        """The specimen's CT (HU, float32) with fluoronav's labels (:data:`BONE_LABELS`) and landmarks
        (the file's names, their aliases (:data:`LANDMARK_ALIASES`) and ``pelvis_center``, the
        midpoint of the femoral heads)."""
        sid = self.resolve_specimen(specimen)
        g = self._h5[sid]
        spacing, origin, direction = self._image_geometry(g["vol"])
        data = _array(g["vol"], "pixels", self.source).astype(np.float32, copy=False)
        labels = None
        if "vol-seg/image" in g:
            s_spacing, s_origin, s_dir = self._image_geometry(g["vol-seg/image"])
            seg = _array(g["vol-seg/image"], "pixels", self.source)
            if seg.shape != data.shape or not (
                np.allclose(s_spacing, spacing)
                and np.allclose(s_origin, origin)
                and np.allclose(s_dir, direction)
            ):
                raise InputError(self.path, f"{sid}: vol-seg/image is not on the grid of vol")
            if seg.dtype != np.uint8:  # the data set's are uint8; other label types are clipped
                seg = np.clip(seg, 0, 255).astype(np.uint8)
            labels = self._bone_lut(g)[seg]
        marks = self.landmarks_world(sid)
        for name, alias in LANDMARK_ALIASES.items():
            if name in marks:
                marks[alias] = marks[name]
        if "FH-l" in marks and "FH-r" in marks:
            marks["pelvis_center"] = 0.5 * (marks["FH-l"] + marks["FH-r"])
        return Volume(
            data=data,
            spacing_mm=spacing,  # type: ignore[arg-type]
            origin_mm=origin,  # type: ignore[arg-type]
            direction=direction,
            labels=labels,
            label_names=dict(BONE_LABELS) if labels is not None else {},
            landmarks_world=marks,
            name=f"deepfluoro-{sid}",
        )

    def _front_point(self, sid: str) -> np.ndarray:
        marks = self.landmarks_world(sid)
        if marks:
            return np.mean(np.stack(list(marks.values())), axis=0)
        spacing, origin, direction = self._image_geometry(self._h5[sid]["vol"])
        shape = self._h5[sid]["vol"]["pixels"].shape  # (z, y, x): metadata, no voxels read
        half = (np.asarray(shape[::-1], np.float64) - 1.0) / 2.0
        return np.asarray(origin) + direction @ (np.asarray(spacing) * half)

    # ----- 2D ----------------------------------------------------------------------------------
    def _pose(self, poses: Any, name: str) -> np.ndarray:
        G = _array(poses, name, self.source).astype(np.float64).reshape(4, 4)
        if self.xreg_texture_correction:
            G = G.copy()
            G[:3, 3] -= 0.5
        return G

    def projection(self, specimen: str, index: int) -> DeepFluoroProjection:
        """One image with its camera and ground truth (see :class:`DeepFluoroProjection`)."""
        sid = self.resolve_specimen(specimen)
        key = f"projections/{int(index):03d}"
        if key not in self._h5[sid]:
            raise InputError(self.path, f"{sid} has no projection {int(index):03d}")
        g = self._h5[sid][key]
        p = self.parameters
        stored = _array(g["image"], "pixels", self.source)
        if stored.shape != (p.rows, p.cols):
            raise InputError(self.path, f"{sid}/{key}: image {stored.shape} is not {p.rows}x{p.cols}")
        rot = bool(_scalar(g, "rot-180-for-up", self.source, default=0.0))
        poses = g["gt-poses"]
        G_pelvis = self._pose(poses, "cam-to-pelvis-vol")
        camera, flip = fluoronav_camera(
            p.intrinsic,
            df_camera_from_ct(p.extrinsic, G_pelvis),
            rows=p.rows,
            cols=p.cols,
            rot_180_for_up=rot,
            point_in_front_ct=self._front_point(sid),
            pixel_spacing_mm=p.pixel_spacing_mm,
            source=f"{self.source}: {sid}/{key}",
        )
        femurs: dict[str, np.ndarray] = {}
        fov: dict[str, bool] = {}
        for side in ("left", "right"):
            if f"cam-to-{side}-femur-vol" in poses:
                femurs[side] = G_pelvis @ np.linalg.inv(self._pose(poses, f"cam-to-{side}-femur-vol"))
                fov[side] = bool(_scalar(poses, f"{side}-femur-good-fov", self.source, default=0.0))
        lm2d: dict[str, np.ndarray] = {}
        if "gt-landmarks" in g:
            lm = g["gt-landmarks"]
            lm2d = {n: flip.pixels(_array(lm, n, self.source).astype(np.float64).reshape(2)) for n in lm}
        return DeepFluoroProjection(
            specimen=sid,
            index=int(index),
            image=flip.image(stored.astype(np.float32)),
            camera=camera,
            flip=flip,
            rot_180_for_up=rot,
            landmarks_px=lm2d,
            world_from_femur=femurs,
            femur_good_fov=fov,
        )

    def projections(self, specimen: str) -> Iterator[DeepFluoroProjection]:
        """Every projection of a specimen, in order, one at a time."""
        for i in self.projection_indices(specimen):
            yield self.projection(specimen, i)


def _bone_by_name(name: str) -> str | None:
    """fluoronav's bone of a DeepFluoro label name (e.g. ``left-hemipelvis``), or None."""
    n = name.replace("_", "-").replace(" ", "-")
    if "femur" in n:
        if "left" in n or n.endswith("-l"):
            return "femur_left"
        if "right" in n or n.endswith("-r"):
            return "femur_right"
        return None
    if any(k in n for k in ("pelvis", "sacrum", "vertebra")):
        return "pelvis"
    return None
