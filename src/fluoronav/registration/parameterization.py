"""Parameterisations: flat optimiser vectors (P, D) → scene quantities (torch, float64 inside).

A rigid block has 6 parameters ``(rx, ry, rz, tx, ty, tz)``: a rotation vector in **degrees** and a
translation in **mm**, a perturbation ``δ = [R(r) | t]`` of a reference pose (zero parameters give it
exactly). :class:`CMPoseShape`, :class:`MultiCMReference` and :class:`HandEye` perturb in the *object* frame
(CM base frame, reference frame), right-multiplied: ``camera_from_cm = camera_from_cm0 @ δ``, rotating about
the CM base origin A (the paper's perturbations are "about a random axis in the CM base frame").
:class:`RigidAboutPoint` and :class:`RotationAboutPoint` rotate about a given centre (pelvis centre, femoral
head) with the camera's axes (``axes="camera"``, the default: the authors' pelvis σ is larger along the
camera's z) or the object's (``axes="object"``). Control points are absolute values in degrees; ``initial()``
gives the start vector. All outputs are float64 tensors on the parameterisation's device.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from fluoronav.geometry.rotations import rotvec_to_matrix
from fluoronav.geometry.transforms import as_tensor, invert_transform, make_transform, rotation_about_point

__all__ = [
    "CMPoseShape",
    "CMState",
    "HandEye",
    "HandEyeState",
    "MultiCMReference",
    "Parameterization",
    "RigidAboutPoint",
    "RigidState",
    "RotationAboutPoint",
    "delta_transform",
    "reference_frame",
]

_RIGID_NAMES = ("rx_deg", "ry_deg", "rz_deg", "tx_mm", "ty_mm", "tz_mm")
_CP_NAMES = tuple(f"cp{i + 1}_deg" for i in range(5))
_F64 = torch.float64


def _t64(x: torch.Tensor | np.ndarray, device: torch.device | str | None) -> torch.Tensor:
    return as_tensor(x, dtype=_F64, device=device)


def delta_transform(params6: torch.Tensor) -> torch.Tensor:
    """(..., 6) rotation vector in degrees + translation in mm → (..., 4, 4) ``[R | t]``."""
    return make_transform(rotvec_to_matrix(params6[..., :3] * (math.pi / 180.0)), params6[..., 3:6])


def reference_frame(base_from_cm: torch.Tensor | np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The multiple-CM reference frame: identity rotation, origin at the mean CM base origin.

    Args:
        base_from_cm: (M, 4, 4) CM poses in some frame ``base`` (robot base in the paper).

    Returns:
        (base_from_ref (4, 4), ref_from_cm (M, 4, 4)), float64.
    """
    T = _t64(base_from_cm, None)
    base_from_ref = make_transform(torch.eye(3, dtype=_F64), T[:, :3, 3].mean(dim=0))
    return base_from_ref, invert_transform(base_from_ref) @ T


@dataclass(frozen=True)
class CMState:
    """CM quantities for a batch.

    Attributes:
        camera_from_cm: (P, 4, 4), or (P, M, 4, 4) for M CM poses.
        control_points_deg: (P, 5).
    """

    camera_from_cm: torch.Tensor
    control_points_deg: torch.Tensor


@dataclass(frozen=True)
class HandEyeState(CMState):
    """:class:`CMState` (P, M, 4, 4) plus ``camera_from_ref`` (P, 4, 4) and ``ee_from_cm`` (P, 4, 4)."""

    camera_from_ref: torch.Tensor
    ee_from_cm: torch.Tensor


@dataclass(frozen=True)
class RigidState:
    """A rigid object's pose for a batch: ``camera_from_object`` (P, 4, 4)."""

    camera_from_object: torch.Tensor


class Parameterization(ABC):
    """Maps optimiser vectors (P, D) to scene quantities; ``names`` label the D parameters."""

    names: tuple[str, ...]

    @property
    def dim(self) -> int:
        return len(self.names)

    @abstractmethod
    def initial(self) -> np.ndarray:
        """(D,) start vector (zero perturbation, initial control points)."""

    @abstractmethod
    def __call__(self, params: torch.Tensor | np.ndarray) -> CMState | RigidState: ...

    def _check(self, params: torch.Tensor | np.ndarray, device: torch.device) -> torch.Tensor:
        p = _t64(params, device)
        if p.dim() == 1:
            p = p.unsqueeze(0)
        if p.dim() != 2 or p.shape[1] != self.dim:
            raise ValueError(f"{type(self).__name__} expects params (P, {self.dim}), got {tuple(p.shape)}")
        return p


class CMPoseShape(Parameterization):
    """Single CM: 6 rigid (CM base frame perturbation) + 5 control points (deg, absolute).

    Args:
        camera_from_cm0: (4, 4) reference pose.
        control_points0_deg: (5,) initial control points (used by ``initial()``).

    ``__call__(params (P, 11)) -> CMState(camera_from_cm (P, 4, 4), control_points_deg (P, 5))``.
    """

    names = _RIGID_NAMES + _CP_NAMES

    def __init__(
        self,
        camera_from_cm0: torch.Tensor | np.ndarray,
        control_points0_deg: torch.Tensor | np.ndarray | None = None,
        *,
        device: torch.device | str = "cpu",
    ) -> None:
        self.device = torch.device(device)
        self.camera_from_cm0 = _t64(camera_from_cm0, self.device)
        cp0 = torch.zeros(5, dtype=_F64) if control_points0_deg is None else _t64(control_points0_deg, None)
        self.control_points0_deg = cp0.to(self.device)

    def initial(self) -> np.ndarray:
        return np.concatenate([np.zeros(6), self.control_points0_deg.cpu().numpy()])

    def __call__(self, params: torch.Tensor | np.ndarray) -> CMState:
        p = self._check(params, self.device)
        return CMState(self.camera_from_cm0 @ delta_transform(p[:, :6]), p[:, 6:11])


class _AboutPoint(Parameterization):
    def __init__(
        self,
        camera_from_object0: torch.Tensor | np.ndarray,
        center_object_mm: torch.Tensor | np.ndarray,
        *,
        axes: Literal["camera", "object"],
        device: torch.device | str,
    ) -> None:
        if axes not in ("camera", "object"):
            raise ValueError(f"axes must be 'camera' or 'object', got {axes!r}")
        self.device = torch.device(device)
        self.axes = axes
        self.camera_from_object0 = _t64(camera_from_object0, self.device)
        self.center_object_mm = _t64(center_object_mm, self.device)
        c = self.camera_from_object0[:3, :3] @ self.center_object_mm + self.camera_from_object0[:3, 3]
        self.center_camera_mm = c

    def initial(self) -> np.ndarray:
        return np.zeros(self.dim)

    def _pose(self, rotvec_deg: torch.Tensor, t_mm: torch.Tensor) -> RigidState:
        R = rotvec_to_matrix(rotvec_deg * (math.pi / 180.0))
        if self.axes == "camera":
            D = rotation_about_point(R, self.center_camera_mm.expand_as(t_mm))
            D[:, :3, 3] += t_mm
            return RigidState(D @ self.camera_from_object0)
        D = rotation_about_point(R, self.center_object_mm.expand_as(t_mm))
        D[:, :3, 3] += t_mm
        return RigidState(self.camera_from_object0 @ D)


class RigidAboutPoint(_AboutPoint):
    """Rigid object (bone): rotation (deg) about a centre + translation (mm), 6 parameters.

    Args:
        camera_from_object0: (4, 4) reference pose (e.g. ``camera_from_world`` for the CT).
        center_object_mm: (3,) rotation centre in the object frame (e.g. pelvis volume centre).
        axes: "camera" (default) or "object": the frame whose axes the rotation vector and
            translation are expressed in.

    ``__call__(params (P, 6)) -> RigidState(camera_from_object (P, 4, 4))``.
    """

    names = _RIGID_NAMES

    def __init__(
        self,
        camera_from_object0: torch.Tensor | np.ndarray,
        center_object_mm: torch.Tensor | np.ndarray,
        *,
        axes: Literal["camera", "object"] = "camera",
        device: torch.device | str = "cpu",
    ) -> None:
        super().__init__(camera_from_object0, center_object_mm, axes=axes, device=device)

    def __call__(self, params: torch.Tensor | np.ndarray) -> RigidState:
        p = self._check(params, self.device)
        return self._pose(p[:, :3], p[:, 3:6])


class RotationAboutPoint(_AboutPoint):
    """Rotation only (deg) about a centre, 3 parameters — the femur about its femoral head.

    ``__call__(params (P, 3)) -> RigidState(camera_from_object (P, 4, 4))``.
    """

    names = _RIGID_NAMES[:3]

    def __init__(
        self,
        camera_from_object0: torch.Tensor | np.ndarray,
        center_object_mm: torch.Tensor | np.ndarray,
        *,
        axes: Literal["camera", "object"] = "camera",
        device: torch.device | str = "cpu",
    ) -> None:
        super().__init__(camera_from_object0, center_object_mm, axes=axes, device=device)

    def __call__(self, params: torch.Tensor | np.ndarray) -> RigidState:
        p = self._check(params, self.device)
        return self._pose(p, torch.zeros_like(p))


class MultiCMReference(Parameterization):
    """Multiple CM poses, one shape (eq. 3): ``camera_from_cm_m = camera_from_ref(δ) @ ref_from_cm_m``.

    Args:
        camera_from_ref0: (4, 4) initial reference-frame pose (perturbed in the reference frame).
        ref_from_cm: (M, 4, 4) fixed relative poses (from robot kinematics and the hand-eye matrix).
        control_points0_deg: (5,) initial shape, shared by all poses.

    ``__call__(params (P, 11)) -> CMState(camera_from_cm (P, M, 4, 4), control_points_deg (P, 5))``.
    """

    names = _RIGID_NAMES + _CP_NAMES

    def __init__(
        self,
        camera_from_ref0: torch.Tensor | np.ndarray,
        ref_from_cm: torch.Tensor | np.ndarray,
        control_points0_deg: torch.Tensor | np.ndarray | None = None,
        *,
        device: torch.device | str = "cpu",
    ) -> None:
        self.device = torch.device(device)
        self.camera_from_ref0 = _t64(camera_from_ref0, self.device)
        self.ref_from_cm = _t64(ref_from_cm, self.device)
        if self.ref_from_cm.dim() != 3:
            raise ValueError(f"ref_from_cm must be (M, 4, 4), got {tuple(self.ref_from_cm.shape)}")
        cp0 = torch.zeros(5, dtype=_F64) if control_points0_deg is None else _t64(control_points0_deg, None)
        self.control_points0_deg = cp0.to(self.device)

    @classmethod
    def from_base_poses(
        cls,
        camera_from_base0: torch.Tensor | np.ndarray,
        base_from_cm: torch.Tensor | np.ndarray,
        control_points0_deg: torch.Tensor | np.ndarray | None = None,
        *,
        device: torch.device | str = "cpu",
    ) -> MultiCMReference:
        """Build the reference frame (:func:`reference_frame`) from CM poses in the robot base frame."""
        base_from_ref, ref_from_cm = reference_frame(base_from_cm)
        return cls(
            _t64(camera_from_base0, None) @ base_from_ref, ref_from_cm, control_points0_deg, device=device
        )

    @property
    def n_poses(self) -> int:
        return int(self.ref_from_cm.shape[0])

    def initial(self) -> np.ndarray:
        return np.concatenate([np.zeros(6), self.control_points0_deg.cpu().numpy()])

    def __call__(self, params: torch.Tensor | np.ndarray) -> CMState:
        p = self._check(params, self.device)
        camera_from_ref = self.camera_from_ref0 @ delta_transform(p[:, :6])
        return CMState(camera_from_ref[:, None] @ self.ref_from_cm[None], p[:, 6:11])


class HandEye(Parameterization):
    """Hand-eye calibration during multiple-CM registration (eq. 5), 6 + 6 + 5 = 17 parameters.

    ``camera_from_cm_m = camera_from_ref(δ_ref) @ ref_from_base @ base_from_ee_m @ ee_from_cm(δ_he)``
    with ``ee_from_cm(δ_he) = ee_from_cm0 @ δ_he`` (perturbation in the CM base frame). The
    reference frame (identity rotation in the robot base frame, origin at the mean CM base origin)
    is computed once from the *initial* hand-eye matrix and then held fixed, so that δ_ref keeps
    one meaning while the hand-eye matrix changes.

    Args:
        camera_from_base0: (4, 4) initial robot base pose in the camera (C-arm) frame.
        base_from_ee: (M, 4, 4) robot forward kinematics ``T_ee^Rbase`` per pose.
        ee_from_cm0: (4, 4) initial hand-eye matrix ``T_CM^ee``.
        control_points0_deg: (5,) initial shape.

    ``__call__(params (P, 17)) -> HandEyeState`` with camera_from_cm (P, M, 4, 4).
    """

    names = _RIGID_NAMES + tuple(f"he_{n}" for n in _RIGID_NAMES) + _CP_NAMES

    def __init__(
        self,
        camera_from_base0: torch.Tensor | np.ndarray,
        base_from_ee: torch.Tensor | np.ndarray,
        ee_from_cm0: torch.Tensor | np.ndarray,
        control_points0_deg: torch.Tensor | np.ndarray | None = None,
        *,
        device: torch.device | str = "cpu",
    ) -> None:
        self.device = torch.device(device)
        self.base_from_ee = _t64(base_from_ee, self.device)
        if self.base_from_ee.dim() != 3:
            raise ValueError(f"base_from_ee must be (M, 4, 4), got {tuple(self.base_from_ee.shape)}")
        self.ee_from_cm0 = _t64(ee_from_cm0, self.device)
        base_from_ref, _ = reference_frame(self.base_from_ee @ self.ee_from_cm0)
        self.base_from_ref = base_from_ref.to(self.device)
        self.camera_from_ref0 = _t64(camera_from_base0, self.device) @ self.base_from_ref
        self.ref_from_ee = invert_transform(self.base_from_ref) @ self.base_from_ee  # (M, 4, 4)
        cp0 = torch.zeros(5, dtype=_F64) if control_points0_deg is None else _t64(control_points0_deg, None)
        self.control_points0_deg = cp0.to(self.device)

    @property
    def n_poses(self) -> int:
        return int(self.base_from_ee.shape[0])

    def initial(self) -> np.ndarray:
        return np.concatenate([np.zeros(12), self.control_points0_deg.cpu().numpy()])

    def __call__(self, params: torch.Tensor | np.ndarray) -> HandEyeState:
        p = self._check(params, self.device)
        camera_from_ref = self.camera_from_ref0 @ delta_transform(p[:, :6])
        ee_from_cm = self.ee_from_cm0 @ delta_transform(p[:, 6:12])
        camera_from_cm = camera_from_ref[:, None] @ self.ref_from_ee[None] @ ee_from_cm[:, None]
        return HandEyeState(camera_from_cm, p[:, 12:17], camera_from_ref, ee_from_cm)
