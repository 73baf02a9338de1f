"""A small synthetic file in the DeepFluoro layout, simulated from the phantom (tests, trying the study).

It has the names and shapes of the real file (docs/real-data.md): the phantom's CT (coarse voxels,
its own HU), physics-simulated images (never the registration's renderer), 14 landmarks under the
data set's names placed on the phantom's pelvis, and known poses. The geometry is written from the
layout's description alone (no code shared with the reader): a stored image is the simulated one
mirrored left-right, the frame is the simulated camera's turned by ``diag(−1, 1, −1)`` and the
intrinsics have negative focal lengths with the principal point mirrored; a ``rot-180-for-up`` view
is simulated with the C-arm rolled by 180° about its axis. Stored intensities are
``I0 · exp(−line integral)`` (bone dark) with a dark collimator border; matrices and points are
float64 by default (``matrix_dtype``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.carm import carm_camera
from fluoronav.simulation.articulated import ArticulatedSimulator
from fluoronav.simulation.xray import SimulationConfig

__all__ = [
    "DEFAULT_SYNTHETIC_VIEWS",
    "LABELS_DEF",
    "SyntheticDeepFluoro",
    "SyntheticView",
    "write_synthetic_deepfluoro",
]

#: label names of the synthetic file (the README's 1–6, xReg's 7)
LABELS_DEF = {
    1: "left-hemipelvis",
    2: "right-hemipelvis",
    3: "vertebra",
    4: "upper-sacrum",
    5: "left-femur",
    6: "right-femur",
    7: "lower-sacrum",
}
#: stored intensity of an unattenuated ray, and the line integral behind the collimator
RAW_I0 = 65535.0
COLLIMATOR_LINE_INTEGRAL = 9.0
#: DeepFluoro's projective frame from the simulated (OpenCV) camera's: x and z reversed
_DF_FROM_CV = np.diag([-1.0, 1.0, -1.0, 1.0])
#: a C-arm rolled by 180° about its axis
_ROLL_180 = np.diag([-1.0, -1.0, 1.0, 1.0])


@dataclass(frozen=True)
class SyntheticView:
    """One C-arm view: angles (:func:`~fluoronav.geometry.carm.carm_camera`), the phantom landmark
    it is centred on (± 10 mm) and the roll flag."""

    lao_rao_deg: float
    cran_caud_deg: float
    rot_180_for_up: bool = False
    center: str = "pelvis_center"


DEFAULT_SYNTHETIC_VIEWS = (
    SyntheticView(0.0, 90.0),
    SyntheticView(20.0, 96.0, center="femoral_head_left"),
    SyntheticView(-15.0, 86.0, rot_180_for_up=True),
)


@dataclass(frozen=True, eq=False)
class SyntheticDeepFluoro:
    """What was written, in fluoronav's frames (the reader must give these back).

    Attributes:
        path, specimen: the file and its one specimen.
        volume: the CT as written (HU, fluoronav labels), in the file's CT frame (LPS).
        landmarks_world: the 14 landmarks under the data set's names (CT frame).
        cameras: per projection the upright fluoronav camera (``camera_from_world`` = from the CT).
        images: per projection the simulated line integral, upright (the camera's orientation).
        world_from_femur_left: per projection the left femur's pose (the right one does not move).
        rot_180_for_up: per projection the flag written.
        intrinsic, extrinsic: ``proj-params`` as written.
    """

    path: Path
    specimen: str
    volume: Volume
    landmarks_world: dict[str, np.ndarray]
    cameras: tuple[Camera, ...]
    images: tuple[np.ndarray, ...]
    world_from_femur_left: tuple[np.ndarray, ...]
    rot_180_for_up: tuple[bool, ...]
    intrinsic: np.ndarray
    extrinsic: np.ndarray


def _deepfluoro_landmarks(marks: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The data set's 14 names on the phantom's pelvis (ASIS and femoral heads are the phantom's;
    the others are placed near where they lie, relative to its acetabula and pubic symphysis)."""
    ps = marks["pubic_symphysis"]
    out: dict[str, np.ndarray] = {}
    for tag, side, sgn in (("l", "left", 1.0), ("r", "right", -1.0)):
        ac = marks[f"acetabulum_{side}"]
        out[f"ASIS-{tag}"] = marks[f"asis_{side}"]
        out[f"FH-{tag}"] = marks[f"femoral_head_{side}"]
        out[f"GSN-{tag}"] = ac + np.array([-sgn * 15.0, 35.0, 25.0])
        out[f"IOF-{tag}"] = 0.5 * (ac + ps) + np.array([0.0, 0.0, -22.0])
        out[f"MOF-{tag}"] = 0.6 * ps + 0.4 * ac + np.array([0.0, -4.0, -12.0])
        out[f"SPS-{tag}"] = ps + np.array([sgn * 6.0, 0.0, 8.0])
        out[f"IPS-{tag}"] = ps + np.array([sgn * 6.0, 0.0, -12.0])
    return {k: np.asarray(v, np.float64) for k, v in sorted(out.items())}


def _phantom(seed: int, spacing_mm: float, origin_shift_mm: Sequence[float]) -> Volume:
    """The phantom moved by ``origin_shift_mm`` (real CTs have origins far from zero)."""
    v = hip_phantom(seed=seed, spacing_mm=spacing_mm)
    shift = np.asarray(origin_shift_mm, np.float64)
    return v.replace(
        origin_mm=tuple(np.asarray(v.origin_mm) + shift),
        landmarks_world={k: p + shift for k, p in v.landmarks_world.items()},
    )


def _deepfluoro_labels(volume: Volume) -> np.ndarray:
    """fluoronav labels → the data set's: hemipelves split at the mid-sagittal plane (x of the
    pelvis centre; +x is the patient's left), femurs 5 and 6."""
    assert volume.labels is not None
    nz, ny, nx = volume.labels.shape
    x = volume.origin_mm[0] + volume.spacing_mm[0] * np.arange(nx)
    left = np.broadcast_to(x >= volume.landmarks_world["pelvis_center"][0], (nz, ny, nx))
    out = np.zeros(volume.labels.shape, np.uint8)
    pelvis = volume.labels == volume.label_value("pelvis")
    out[pelvis & left] = 1
    out[pelvis & ~left] = 2
    out[volume.labels == volume.label_value("femur_left")] = 5
    out[volume.labels == volume.label_value("femur_right")] = 6
    return out


def _femur_motion(head: np.ndarray, rng: np.random.Generator, max_deg: float) -> np.ndarray:
    axis = rng.normal(size=3)
    R = Rotation.from_rotvec(np.radians(rng.uniform(-max_deg, max_deg)) * axis / np.linalg.norm(axis))
    T = np.eye(4)
    T[:3, :3] = R.as_matrix()
    T[:3, 3] = head - T[:3, :3] @ head
    return T


def _image_group(
    g: Any, pixels: np.ndarray, spacing: Sequence[float], origin: Sequence[float], dtype: str
) -> None:
    n = len(spacing)
    g.create_dataset("pixels", data=pixels)
    g.create_dataset("spacing", data=np.asarray(spacing, dtype).reshape(n, 1))
    g.create_dataset("origin", data=np.asarray(origin, dtype).reshape(n, 1))
    g.create_dataset("dir-mat", data=np.eye(n, dtype=dtype))


def _write_specimen(
    f: Any, specimen: str, volume: Volume, labels: np.ndarray, marks: dict[str, np.ndarray], dtype: str
) -> Any:
    s = f.create_group(specimen)
    _image_group(
        s.create_group("vol"), volume.data.astype(np.float32), volume.spacing_mm, volume.origin_mm, dtype
    )
    seg = s.create_group("vol-seg")
    _image_group(seg.create_group("image"), labels, volume.spacing_mm, volume.origin_mm, dtype)
    defs = seg.create_group("labels-def")
    for value, name in LABELS_DEF.items():
        defs.create_dataset(str(value), data=name)
    lm = s.create_group("vol-landmarks")
    for name, p in marks.items():
        lm.create_dataset(name, data=np.asarray(p, dtype).reshape(3, 1))
    return s.create_group("projections")


def _write_projection(
    g: Any,
    line_integral: np.ndarray,
    camera: Camera,
    world_from_femur_left: np.ndarray,
    marks: dict[str, np.ndarray],
    trochanters: dict[str, np.ndarray],
    extrinsic: np.ndarray,
    dtype: str,
) -> np.ndarray:
    """One ``projections/NNN`` group (but its flag) from a simulated image and its camera; returns
    the intrinsics it implies. ``trochanters``: side → the lesser trochanter where the image shows it
    (for the femur's field-of-view flag)."""
    K0, n = camera.K, camera.cols
    K_df = np.array([[-K0[0, 0], 0.0, n - 1.0 - K0[0, 2]], [0.0, -K0[1, 1], K0[1, 2]], [0.0, 0.0, 1.0]])
    stored = np.ascontiguousarray(line_integral[:, ::-1])  # the detector seen from behind
    raw = (RAW_I0 * np.exp(-stored.astype(np.float64))).astype(np.float32)
    b = round(50 * n / 1536)
    dark = np.float32(RAW_I0 * np.exp(-COLLIMATOR_LINE_INTEGRAL))
    raw[:b], raw[-b:], raw[:, :b], raw[:, -b:] = dark, dark, dark, dark
    pitch = float(camera.pixel_spacing_mm or 0.194 * 1536 / n)
    _image_group(g.create_group("image"), raw, (pitch, pitch), (0.0, 0.0), dtype)
    _image_group(g.create_group("gt-seg"), np.zeros(raw.shape, np.uint8), (pitch, pitch), (0.0, 0.0), dtype)
    lm = g.create_group("gt-landmarks")
    for name, p in marks.items():
        u0, v0 = camera.project(p)
        lm.create_dataset(name, data=np.asarray([n - 1.0 - u0, v0], dtype).reshape(2, 1))
    poses = g.create_group("gt-poses")
    df_from_ct = _DF_FROM_CV @ camera.camera_from_world
    for name, df_from_bone in (
        ("cam-to-pelvis-vol", df_from_ct),
        ("cam-to-left-femur-vol", df_from_ct @ world_from_femur_left),
        ("cam-to-right-femur-vol", df_from_ct),
    ):
        poses.create_dataset(name, data=(np.linalg.inv(df_from_bone) @ extrinsic).astype(dtype))
    for side in ("left", "right"):
        good = _femur_in_view(camera, marks[f"FH-{side[0]}"], trochanters[side])
        poses.create_dataset(f"{side}-femur-good-fov", data=np.uint8(good))
    return K_df


def _femur_in_view(camera: Camera, head: np.ndarray, trochanter: np.ndarray) -> bool:
    """The synthetic file's ``*-femur-good-fov``: the femoral head and the neck below it (halfway to
    the lesser trochanter) at least a tenth of the image inside its edges."""
    uv = camera.project(np.stack([head, 0.5 * (head + trochanter)]))
    m = 0.1 * camera.cols
    return bool(np.all((uv >= m) & (uv <= np.array([camera.cols, camera.rows]) - 1 - m)))


def _write_parameters(
    f: Any, intrinsic: np.ndarray, extrinsic: np.ndarray, camera: Camera, dtype: str
) -> None:
    params = f.create_group("proj-params")
    params.create_dataset("intrinsic", data=intrinsic.astype(dtype))
    params.create_dataset("extrinsic", data=extrinsic.astype(dtype))
    params.create_dataset("num-rows", data=np.uint64(camera.rows))
    params.create_dataset("num-cols", data=np.uint64(camera.cols))
    pitch = np.asarray(camera.pixel_spacing_mm or 0.194 * 1536 / camera.cols, dtype)
    params.create_dataset("pixel-row-spacing", data=pitch)
    params.create_dataset("pixel-col-spacing", data=pitch)


def write_synthetic_deepfluoro(
    path: str | Path,
    *,
    specimen: str = "17-1882",
    views: Sequence[SyntheticView] = DEFAULT_SYNTHETIC_VIEWS,
    image_size: int = 192,
    spacing_mm: float = 2.0,
    seed: int = 0,
    origin_shift_mm: Sequence[float] = (40.0, -25.0, -900.0),
    femur_motion_deg: float = 6.0,
    matrix_dtype: str = "float64",
    device: str = "cpu",
) -> SyntheticDeepFluoro:
    """Write a DeepFluoro-layout file of one specimen simulated from the phantom.

    Args:
        path: the HDF5 file to write (overwritten).
        specimen: the specimen group's name.
        views: the C-arm views (one projection each, numbered from 000).
        image_size: stored image side (the 1536² CIOS Fusion detector binned; 0.194 mm × 1536 /
            ``image_size`` pixels).
        spacing_mm: the phantom CT's voxel size.
        seed: phantom, femur motions and image noise.
        origin_shift_mm: where the phantom's CT sits in LPS (added to its centred frame).
        femur_motion_deg: the left femur turns about its head by up to this per projection.
        matrix_dtype: dtype of matrices, points and spacings.
        device: where the simulator runs.

    Returns:
        :class:`SyntheticDeepFluoro`, the truth in fluoronav's frames.
    """
    import h5py  # optional at import time: only the DeepFluoro files need it

    volume = _phantom(seed, spacing_mm, origin_shift_mm)
    marks = _deepfluoro_landmarks(volume.landmarks_world)
    sim = ArticulatedSimulator(
        volume, femur_side="left", config=SimulationConfig(image_size=image_size), device=device
    )
    rng = np.random.default_rng([seed, 67])
    extrinsic = np.eye(4)
    extrinsic[:3, :3] = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    extrinsic[:3, 3] = (12.0, -34.0, 560.0)
    cams, imgs, femurs, intrinsics = [], [], [], []
    out = Path(path)
    with h5py.File(out, "w") as f:
        projections = _write_specimen(f, specimen, volume, _deepfluoro_labels(volume), marks, matrix_dtype)
        for k, view in enumerate(views):
            up = carm_camera(
                lao_rao_deg=view.lao_rao_deg,
                cran_caud_deg=view.cran_caud_deg,
                isocenter_world=volume.landmarks_world[view.center] + rng.uniform(-10.0, 10.0, 3),
            )
            full = up.with_pose(_ROLL_180 @ up.camera_from_world) if view.rot_180_for_up else up
            W_fl = _femur_motion(volume.landmarks_world["femoral_head_left"], rng, femur_motion_deg)
            im = sim.simulate(full, world_from_patient=np.eye(4), world_from_femur=W_fl, seed=seed + k)
            g = projections.create_group(f"{k:03d}")
            lt = volume.landmarks_world
            troch = {"left": W_fl[:3, :3] @ lt["lesser_trochanter_left"] + W_fl[:3, 3]}
            troch["right"] = lt["lesser_trochanter_right"]
            K_df = _write_projection(g, im.image, im.camera, W_fl, marks, troch, extrinsic, matrix_dtype)
            intrinsics.append(K_df)
            g.create_dataset("rot-180-for-up", data=np.uint8(view.rot_180_for_up))
            cams.append(sim.stored_camera(up, image_size))
            imgs.append(np.ascontiguousarray(im.image[::-1, ::-1] if view.rot_180_for_up else im.image))
            femurs.append(W_fl)
        if not intrinsics or any(not np.allclose(K, intrinsics[0]) for K in intrinsics):
            raise ValueError("give at least one view; all views share one detector")
        _write_parameters(f, intrinsics[0], extrinsic, cams[0], matrix_dtype)
    return SyntheticDeepFluoro(
        path=out,
        specimen=specimen,
        volume=volume,
        landmarks_world=marks,
        cameras=tuple(cams),
        images=tuple(imgs),
        world_from_femur_left=tuple(femurs),
        rot_180_for_up=tuple(v.rot_180_for_up for v in views),
        intrinsic=intrinsics[0],
        extrinsic=extrinsic,
    )
