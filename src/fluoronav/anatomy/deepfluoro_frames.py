"""DeepFluoro's camera frame → fluoronav's, once (docs/conventions.md, "DeepFluoro frames").

DeepFluoro (and xReg, which made it) projects a CT point ``p`` (LPS, mm) of the pelvis into stored
pixel (u, v) = (column, row) as ``[u, v, 1]ᵀ ∝ intrinsic · extrinsic · inv(cam-to-pelvis-vol) · p``,
in a projective frame whose z points **towards the source** (negative focal lengths). That frame
sees the detector from behind, so no rigid ``camera_from_world`` reproduces a stored image; the
image is flipped instead (:class:`ImageFlip`: turned by 180° where ``rot-180-for-up`` is set, then
its columns mirrored where its pixel axes and the viewing direction form a left-handed frame), the
2D landmarks with it. The camera follows from ``flip · intrinsic · extrinsic ·
inv(cam-to-pelvis-vol)`` factored into positive intrinsics and a rigid pose with the CT in front
(:func:`fluoronav_camera`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fluoronav.errors import InputError
from fluoronav.geometry import se3
from fluoronav.geometry.camera import Camera

__all__ = ["ImageFlip", "df_camera_from_ct", "fluoronav_camera"]


@dataclass(frozen=True)
class ImageFlip:
    """Axis flips that take a stored DeepFluoro image to fluoronav's orientation.

    Attributes:
        rows, cols: the image size (pixels; unchanged by the flips).
        flip_rows: row ``v`` goes to ``rows − 1 − v``.
        flip_cols: column ``u`` goes to ``cols − 1 − u``.
    """

    rows: int
    cols: int
    flip_rows: bool = False
    flip_cols: bool = False

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) homogeneous pixel map, stored (u, v, 1) → flipped (u, v, 1)."""
        A = np.eye(3)
        if self.flip_cols:
            A[0, 0], A[0, 2] = -1.0, self.cols - 1.0
        if self.flip_rows:
            A[1, 1], A[1, 2] = -1.0, self.rows - 1.0
        return A

    def then_mirror_columns(self) -> ImageFlip:
        """This flip followed by a left-right mirror."""
        return ImageFlip(self.rows, self.cols, self.flip_rows, not self.flip_cols)

    def image(self, stored: np.ndarray) -> np.ndarray:
        """The stored (rows, cols) image in fluoronav's orientation (a contiguous copy)."""
        a = np.asarray(stored)
        if a.shape[-2:] != (self.rows, self.cols):
            raise ValueError(f"image shape {a.shape} does not match {self.rows}x{self.cols}")
        if self.flip_rows:
            a = a[..., ::-1, :]
        if self.flip_cols:
            a = a[..., :, ::-1]
        return np.ascontiguousarray(a)

    def pixels(self, uv: np.ndarray) -> np.ndarray:
        """Stored pixels (..., 2) as (u, v) → fluoronav's (..., 2)."""
        p = np.asarray(uv, np.float64)
        return p @ self.matrix[:2, :2].T + self.matrix[:2, 2]


def df_camera_from_ct(extrinsic: np.ndarray, cam_to_vol: np.ndarray) -> np.ndarray:
    """(4, 4) DeepFluoro projective frame from the CT: ``extrinsic · inv(cam-to-<bone>-vol)``."""
    E = np.asarray(extrinsic, np.float64).reshape(4, 4)
    G = np.asarray(cam_to_vol, np.float64).reshape(4, 4)
    return E @ np.linalg.inv(G)


def fluoronav_camera(
    intrinsic: np.ndarray,
    df_from_ct: np.ndarray,
    *,
    rows: int,
    cols: int,
    rot_180_for_up: bool,
    point_in_front_ct: np.ndarray,
    pixel_spacing_mm: float | None,
    source: str = "DeepFluoro file",
) -> tuple[Camera, ImageFlip]:
    """The fluoronav camera of a DeepFluoro projection and the flips of its image.

    Args:
        intrinsic: (3, 3) DeepFluoro intrinsics (pixels; any signs of the focal lengths).
        df_from_ct: (4, 4) DeepFluoro projective frame from the CT (:func:`df_camera_from_ct`).
        rows, cols: stored image size.
        rot_180_for_up: the projection's ``rot-180-for-up`` flag.
        point_in_front_ct: (3,) a CT point (LPS, mm) between source and detector (e.g. the landmark
            centroid): it decides which side of the source is "in front".
        pixel_spacing_mm: detector pixel pitch for the camera, or None.
        source: names the file in errors.

    Returns:
        ``(camera, flip)``: ``camera.project(p)`` = ``flip.pixels`` of DeepFluoro's projection of
        ``p``; the camera's ``camera_from_world`` is ``camera_from_ct`` (world = the CT, LPS).

    Notes:
        With ``Q = flip · intrinsic`` and ``d = sign(diag Q)``: ``Q = K · diag(d)`` with ``K`` of
        positive diagonal, and ``Q · df_from_ct ∝ K · (λ diag(d) · df_from_ct)`` for either sign of
        ``λ``; ``λ`` is the sign of the front point's depth (so it lies at z > 0) and the pose is
        rigid when ``λ d₀ d₁ d₂ = +1``, else the columns are mirrored and ``d₀`` changes sign.
    """
    K_df = np.asarray(intrinsic, np.float64).reshape(3, 3)
    P = np.asarray(df_from_ct, np.float64).reshape(4, 4)
    if abs(K_df[2, 2]) < 1e-12 or not np.allclose(K_df[2, :2], 0.0):
        raise InputError(source, "proj-params/intrinsic must have a last row [0, 0, c] with c ≠ 0")
    K_df = K_df / K_df[2, 2]
    front = P[:3, :3] @ np.asarray(point_in_front_ct, np.float64) + P[:3, 3]
    if abs(front[2]) < 1e-9:
        raise InputError(source, "the CT lies in the source's plane: the poses cannot be right")
    lam = float(np.sign(front[2]))
    flip = ImageFlip(rows, cols, flip_rows=rot_180_for_up, flip_cols=rot_180_for_up)
    for _ in range(2):
        Q = flip.matrix @ K_df
        d = np.sign(np.diag(Q))
        if np.any(d == 0):
            raise InputError(source, "proj-params/intrinsic has a zero focal length")
        if lam * float(np.prod(d)) > 0:
            break
        flip = flip.then_mirror_columns()
    D = np.diag(np.append(d, 1.0))
    camera_from_ct = lam * D @ P
    camera_from_ct[3] = (0.0, 0.0, 0.0, 1.0)
    if np.linalg.det(camera_from_ct[:3, :3]) < 0.99:
        raise InputError(source, "extrinsic · inv(cam-to-pelvis-vol) is not a rotation and translation")
    # float32 matrices (as xReg stores them) leave the rotation ~1e-7 off orthonormal
    camera_from_ct[:3, :3] = se3.project_to_so3(camera_from_ct[:3, :3])
    camera = Camera(
        rows=rows,
        cols=cols,
        K=Q @ np.diag(d),
        camera_from_world=camera_from_ct,
        pixel_spacing_mm=pixel_spacing_mm,
    )
    return camera, flip
