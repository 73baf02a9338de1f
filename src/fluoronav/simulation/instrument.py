"""The instrument as built: a CM that deviates from the model the registration fits, for the images.

The registration models the CM as a perfect tube whose notch angles lie on a cubic spline through the control
points. A real one does not: each notch is cut where the machine put it, as wide and deep as it cut it; each
bends by its own amount for the same actuation (the spline's angle times ``1 + ε_j`` plus an offset ``δ_j``);
the tube's diameters are the drawn tube's, within tolerance (magnitudes: docs/simulation.md, "Simulated
worlds"). :func:`build_instrument` draws one (:class:`BuiltCM`) from an :class:`InstrumentWorld`; the
simulator draws it in the images (``ArticulatedSimulator.simulate(..., built_cm=)``) and the functions here
give the truth to measure errors against (joint angles, link poses, tip, landmarks for commanded control
points). :func:`spline_fit_control_points_deg` is the best the model can do: the control points whose spline
is nearest (least squares) to the built angles.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.geometry import NotchGeometry
from fluoronav.manipulator.kinematics import CMKinematics

__all__ = [
    "BuiltCM",
    "InstrumentWorld",
    "build_instrument",
    "built_joint_angles_deg",
    "built_landmarks_cm",
    "built_link_transforms",
    "built_tip_cm",
    "spline_fit_control_points_deg",
]


@dataclass(frozen=True)
class InstrumentWorld:
    """How far the instrument as built is from the model: standard deviations of independent
    normal deviations, per instrument (diameters) or per notch (the rest). A zero turns one off;
    the defaults are all off (the instrument is the model), :meth:`realistic` holds the magnitudes
    below, for the paper's CM (6 mm nitinol tube, 27 notches, 35 mm).

    Attributes:
        outer_diameter_sd_mm: the tube's true outer diameter about the nominal, mm. 0.017: nitinol
            tube suppliers' standard tolerance for 5 < OD ≤ 10 mm is ±0.050 mm on OD (lumenous.com,
            "Nitinol tube", tolerance table), read as ±3σ (a capable drawing process, assumed).
        inner_diameter_sd_mm: the lumen's true diameter, mm. 0.017: the same table's ±0.050 mm on ID,
            read as ±3σ (assumed).
        notch_depth_sd_mm: each notch's depth from the outer surface, mm. 0.02: wire EDM holds
            ±0.02 mm in one roughing pass, ±0.01 mm with 2–3 passes (mecvil.com, "Wire EDM:
            tolerances"); a notched tube is cut in one pass, the ±0.02 mm read as 1σ (assumed,
            deliberately wide: the cut's recast layer and burr are outside that figure).
        notch_width_sd_mm: each notch's axial width, mm. 0.02: as the depth.
        notch_position_sd_mm: each notch's axial centre about its nominal pitch position, mm
            (independent per notch: a CNC cut positions each notch absolutely, so pitch errors do
            not accumulate; assumed). 0.02: as the depth.
        angle_scale_sd: relative deviation of each notch's joint angle from the spline's (its
            compliance relative to the model's), dimensionless: ``φ_j = φ_spline,j · (1 + ε_j) + δ_j``.
            0.07: assumed, no measured per-notch figure found. A notch's bending stiffness goes about
            as its spine thickness cubed over its width: the geometric tolerances above alone give
            3 · 0.02 / 1.5 = 4 % (spine 1.5 mm) and 0.02 / 0.7 = 3 %; the alloy's heat treatment and
            tendon friction along the CM add to it.
        angle_offset_sd_deg: each notch's angle offset ``δ_j`` (a residual set at zero bend), degrees.
            0.1: assumed (a tenth of a degree per notch, 27 notches: a straight CM's tip off the axis
            by ~0.1 mm).
    """

    outer_diameter_sd_mm: float = 0.0
    inner_diameter_sd_mm: float = 0.0
    notch_depth_sd_mm: float = 0.0
    notch_width_sd_mm: float = 0.0
    notch_position_sd_mm: float = 0.0
    angle_scale_sd: float = 0.0
    angle_offset_sd_deg: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not value >= 0.0:
                raise ValueError(f"{f.name} must be ≥ 0, got {value}")

    @classmethod
    def ideal(cls) -> InstrumentWorld:
        """Every deviation off: the instrument is exactly the model (the defaults)."""
        return cls()

    @classmethod
    def realistic(cls) -> InstrumentWorld:
        """The magnitudes documented on each field."""
        return cls(
            outer_diameter_sd_mm=0.017,
            inner_diameter_sd_mm=0.017,
            notch_depth_sd_mm=0.02,
            notch_width_sd_mm=0.02,
            notch_position_sd_mm=0.02,
            angle_scale_sd=0.07,
            angle_offset_sd_deg=0.1,
        )

    @property
    def enabled(self) -> bool:
        """Whether the instrument as built differs from the model at all."""
        return any(getattr(self, f.name) > 0 for f in fields(self))


@dataclass(frozen=True, eq=False)
class BuiltCM:
    """One instrument as built.

    Attributes:
        config: its geometry where uniform: the model's with the true outer and inner diameters.
        notches: its notches where they were cut: centres, widths and depths (mm).
        angle_scale: (N,) each notch's angle relative to the spline's, ``1 + ε_j``.
        angle_offset_deg: (N,) each notch's angle offset ``δ_j``, degrees.
        model: the model it was built to (the registration's config; its spline).
    """

    config: CMConfig
    notches: NotchGeometry
    angle_scale: np.ndarray
    angle_offset_deg: np.ndarray
    model: CMConfig


def build_instrument(cfg: InstrumentWorld, cm_config: CMConfig, rng: np.random.Generator) -> BuiltCM:
    """Draw one instrument built to ``cm_config`` with the deviations of ``cfg``.

    Every draw is made whatever its magnitude (a zero only scales it away), so the same ``rng``
    state gives the same instrument for the deviations that are on, whichever others are off.

    Args:
        cfg: magnitudes of the deviations.
        cm_config: the model the instrument is built to.
        rng: random generator.

    Returns:
        :class:`BuiltCM`; with :meth:`InstrumentWorld.ideal` exactly the model.

    Raises:
        ValueError: the drawn geometry is not a valid CM (notches out of order, no spine left).
    """
    n = cm_config.n_notches
    d_od, d_id = rng.normal(size=2)
    d_z, d_w, d_d, eps, delta = rng.normal(size=(5, n))
    config = CMConfig.model_validate(
        {
            **cm_config.model_dump(),
            "outer_diameter_mm": cm_config.outer_diameter_mm + cfg.outer_diameter_sd_mm * d_od,
            "inner_diameter_mm": cm_config.inner_diameter_mm + cfg.inner_diameter_sd_mm * d_id,
        }
    )
    z = np.array([cm_config.notch_z_mm(j) for j in range(n)]) + cfg.notch_position_sd_mm * d_z
    width = cm_config.notch_width_mm + cfg.notch_width_sd_mm * d_w
    depth = cm_config.notch_depth_mm + cfg.notch_depth_sd_mm * d_d
    if np.any(depth >= config.outer_diameter_mm):
        raise ValueError("a drawn notch is deeper than the tube: no spine left")
    notches = NotchGeometry(
        z_mm=tuple(float(v) for v in z),
        width_mm=tuple(float(v) for v in width),
        depth_mm=tuple(float(v) for v in depth),
    )
    return BuiltCM(
        config=config,
        notches=notches,
        angle_scale=1.0 + cfg.angle_scale_sd * eps,
        angle_offset_deg=cfg.angle_offset_sd_deg * delta,
        model=cm_config,
    )


def _control_points(built: BuiltCM, control_points_deg: np.ndarray | torch.Tensor) -> torch.Tensor:
    cp = torch.as_tensor(np.asarray(control_points_deg, dtype=np.float64))
    if cp.shape[-1:] != (built.model.n_control_points,):
        raise ValueError(
            f"control_points_deg must end in ({built.model.n_control_points},), got {tuple(cp.shape)}"
        )
    return cp


def built_joint_angles_deg(built: BuiltCM, control_points_deg: np.ndarray | torch.Tensor) -> torch.Tensor:
    """(..., n) commanded control points → (..., N) the built instrument's notch angles, degrees."""
    cp = _control_points(built, control_points_deg)
    spline = CMKinematics(built.model).joint_angles_deg(cp)
    scale = torch.as_tensor(built.angle_scale, dtype=spline.dtype)
    offset = torch.as_tensor(built.angle_offset_deg, dtype=spline.dtype)
    return spline * scale + offset


def built_link_transforms(built: BuiltCM, control_points_deg: np.ndarray | torch.Tensor) -> torch.Tensor:
    """(..., n) control points → (..., N+1, 4, 4) the built instrument's ``cm_from_link``."""
    kin = CMKinematics(built.config)
    return kin.link_transforms_from_angles(
        built_joint_angles_deg(built, control_points_deg), notch_z_mm=np.asarray(built.notches.z_mm)
    )


def _point_on_top_link(
    built: BuiltCM, control_points_deg: np.ndarray | torch.Tensor, z_mm: float
) -> torch.Tensor:
    T = built_link_transforms(built, control_points_deg)[..., -1, :, :]
    return T[..., :3, 2] * z_mm + T[..., :3, 3]


def built_tip_cm(built: BuiltCM, control_points_deg: np.ndarray | torch.Tensor) -> torch.Tensor:
    """(..., n) → (..., 3): the built instrument's distal end point in its base frame, mm."""
    return _point_on_top_link(built, control_points_deg, built.config.tip_z_mm)


def built_landmarks_cm(built: BuiltCM, control_points_deg: np.ndarray | torch.Tensor) -> torch.Tensor:
    """(..., n) → (..., 2, 3): the built instrument's landmarks A (base origin) and B (distal plane
    of its last notch as cut), mm."""
    B = _point_on_top_link(built, control_points_deg, built.notches.distal_plane_mm)
    return torch.stack([torch.zeros_like(B), B], dim=-2)


def spline_fit_control_points_deg(
    built: BuiltCM, control_points_deg: np.ndarray | torch.Tensor
) -> torch.Tensor:
    """(..., n) → (..., n): the control points whose model spline is nearest (least squares over the
    N notch angles) to the built instrument's angles: the best the model can represent it."""
    angles = built_joint_angles_deg(built, control_points_deg)
    W = CMKinematics(built.model).spline_weights(angles)  # (N, n)
    return angles @ torch.linalg.pinv(W).T
