"""Parametric description of a notched continuum manipulator (CM).

Defaults are the paper's CM (Gao et al. 2022): a nitinol tube, 6 mm outer and 4 mm inner diameter,
35 mm long, 27 notches cut alternately on two opposite sides, bending in one plane, with joint
angles interpolated by a cubic spline through 5 control points. The dimensions the paper does not
give (notch pitch, width and depth, base length) and why they were chosen: docs/conventions.md.

Frame (docs/conventions.md): origin A between the base and the first notch, on the axis; +z along
the axis towards the tip; bending in the y-z plane, joints rotate about x. Notch ``j`` (0-based) is
centred at ``z_j = first_notch_offset_mm + j · notch_pitch_mm`` and opens towards +y for even ``j``,
−y for odd. A positive joint angle rotates the distal part about +x (bending the tip towards −y).
"""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from fluoronav.errors import InputError

__all__ = ["CMConfig", "load_cm_config"]


class CMConfig(BaseModel):
    """Geometry, kinematics and material of a notched CM (frozen, validated). Lengths in mm."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    n_notches: int = Field(27, ge=1)
    outer_diameter_mm: float = Field(6.0, gt=0)
    inner_diameter_mm: float = Field(4.0, ge=0)
    total_length_mm: float = Field(35.0, gt=0)
    base_length_mm: float = Field(4.0, ge=0)
    notch_pitch_mm: float = Field(1.0, gt=0)
    notch_width_mm: float = Field(0.7, gt=0)
    notch_depth_mm: float = Field(4.5, gt=0)
    first_notch_offset_mm: float | None = Field(
        None, description="A → centre of the first notch; default half a pitch"
    )
    n_control_points: int = Field(5, ge=2)
    control_point_range_deg: tuple[float, float] = (-7.9, 7.9)
    material: str = "nitinol"
    density_g_cm3: float = Field(6.45, gt=0)
    hu_value: float = 2000.0

    @model_validator(mode="after")
    def _check(self) -> CMConfig:
        if self.inner_diameter_mm >= self.outer_diameter_mm:
            raise ValueError("inner_diameter_mm must be smaller than outer_diameter_mm")
        if self.notch_width_mm >= self.notch_pitch_mm:
            raise ValueError("notch_width_mm must be smaller than notch_pitch_mm")
        if self.notch_depth_mm >= self.outer_diameter_mm:
            raise ValueError("notch_depth_mm must leave a spine (smaller than outer_diameter_mm)")
        if self.distal_notch_plane_mm > self.total_length_mm - self.base_length_mm:
            raise ValueError("the notches do not fit in total_length_mm")
        return self

    # ----- derived geometry (straight configuration, CM base frame) -----------------------
    @property
    def first_notch_z_mm(self) -> float:
        return self.notch_pitch_mm / 2.0 if self.first_notch_offset_mm is None else self.first_notch_offset_mm

    def notch_z_mm(self, j: int) -> float:
        """Axial position of notch ``j``'s centre (its joint rotation centre)."""
        return self.first_notch_z_mm + j * self.notch_pitch_mm

    @property
    def distal_notch_plane_mm(self) -> float:
        """Axial position of the distal plane of the last notch (landmark B when straight)."""
        return self.notch_z_mm(self.n_notches - 1) + self.notch_width_mm / 2.0

    @property
    def tip_z_mm(self) -> float:
        """Axial position of the distal end of the tube (the CM tip when straight)."""
        return self.total_length_mm - self.base_length_mm

    @property
    def outer_radius_mm(self) -> float:
        return self.outer_diameter_mm / 2.0

    @property
    def inner_radius_mm(self) -> float:
        return self.inner_diameter_mm / 2.0

    @property
    def notch_cut_level_mm(self) -> float:
        """A notch removes material where ``side · y > notch_cut_level_mm`` (side = ±1)."""
        return self.outer_radius_mm - self.notch_depth_mm

    def notch_side(self, j: int) -> int:
        """+1 if notch ``j`` opens towards +y, −1 towards −y."""
        return 1 if j % 2 == 0 else -1

    def knot_positions(self) -> list[float]:
        """Spline knots in notch-index units: ``(N−1)·(i+1)/(n+1)`` (the authors' 26·(i+1)/6)."""
        n, N = self.n_control_points, self.n_notches
        return [(N - 1) * (i + 1) / (n + 1) for i in range(n)]

    @property
    def max_bend_deg(self) -> float:
        """Joint angle at which a notch closes (its faces touch at the outer wall)."""
        lever = self.outer_radius_mm - self.notch_cut_level_mm
        return math.degrees(math.atan2(self.notch_width_mm, max(lever, 1e-9)))


def with_shaft(config: CMConfig, shaft_length_mm: float) -> CMConfig:
    """The CM with its mounting shaft as a longer base: the base tube extended by ``shaft_length_mm``
    behind the base (−z), landmarks, notches and tip unchanged. For rendering the CM as it appears
    in an X-ray (the rigid shaft it is mounted on, same tube); 0 returns ``config``."""
    if shaft_length_mm < 0:
        raise ValueError(f"shaft_length_mm must be ≥ 0, got {shaft_length_mm}")
    if shaft_length_mm == 0:
        return config
    return config.model_copy(
        update={
            "base_length_mm": config.base_length_mm + shaft_length_mm,
            "total_length_mm": config.total_length_mm + shaft_length_mm,
        }
    )


def load_cm_config(path: str | Path) -> CMConfig:
    """Read a CM configuration from TOML or JSON; missing keys keep the paper's defaults."""
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise InputError(p, f"cannot read CM config ({exc.__class__.__name__})") from None
    try:
        data: Any = tomllib.loads(raw.decode()) if p.suffix.lower() == ".toml" else json.loads(raw)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(p, f"CM config does not parse ({exc})") from None
    if isinstance(data, dict) and "cm" in data and isinstance(data["cm"], dict):
        data = data["cm"]
    if not isinstance(data, dict):
        raise InputError(p, "CM config must be a table/object of parameters")
    try:
        return CMConfig(**data)
    except ValidationError as exc:
        first = exc.errors()[0]
        loc = ".".join(str(x) for x in first["loc"]) or "config"
        raise InputError(p, f"invalid CM config: {loc}: {first['msg']}") from None
