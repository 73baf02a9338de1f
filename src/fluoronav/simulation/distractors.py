"""Distractor metal in the detector's training images: K-wires, screws, a second tube, cables.

Negatives a CM detector must not fire on (after SyntheX's strong randomisation, Gao et al. 2023): steel
K-wires, steel or titanium screws (threaded shaft and head, some cannulated), a hollow nitinol or steel
tube like the CM's shaft, and thin curved wires, placed in 3D near an anchor (the femoral head, the
isocentre) and, given the CM's points, some through its neighbourhood. :func:`draw_distractors` draws
them (a JSON-ready record each); :func:`render_distractors` integrates every pixel's rays analytically
through the solids (chord length × density) into per-material areal densities (g/cm²) that the caller
adds to the scene's before the physics; :func:`distractor_densities` does both. The default
:class:`DistractorConfig` (``DISTRACTORS_OFF``) places nothing.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fluoronav.device import resolve_device
from fluoronav.geometry.camera import Camera
from fluoronav.settings import setting
from fluoronav.simulation.materials import MM_PER_CM, get_material

__all__ = [
    "DISTRACTORS_OFF",
    "DISTRACTORS_REALISTIC",
    "DISTRACTOR_PRESETS",
    "DistractorConfig",
    "distractor_densities",
    "draw_distractors",
    "render_distractors",
    "solid_chord_mm",
]

FloatRange = tuple[float, float]
IntRange = tuple[int, int]
#: screw proportions to its major (thread) diameter: core, head diameter, head height, cannula
SCREW_CORE_RATIO, SCREW_HEAD_RATIO, SCREW_HEAD_HEIGHT_RATIO, SCREW_LUMEN_RATIO = 0.7, 1.6, 0.6, 0.4
#: fraction of the thread's annulus (between core and major diameter) that is metal
SCREW_THREAD_FILL = 0.5
#: length of a cable's straight segments, mm
CABLE_SEGMENT_MM = 5.0
#: stands for "no intersection" in the ray intervals (mm along the ray)
_FAR_MM = 1e12


@dataclass(frozen=True)
class DistractorConfig:
    """Which distractors a training sample gets and their sizes; every kind is off by default.

    Sizes are drawn uniformly, counts uniformly in their inclusive range, materials uniformly from
    their tuple (names of :data:`~fluoronav.simulation.materials.MATERIALS`), axes uniformly in
    direction. The realistic sizes are the usual implants' (K-wires 1.6–2.5 mm, screws 4.5–7.3 mm);
    the counts and placements are assumed.
    """

    placement_radius_mm: float = setting(40.0, "objects' centres within this of the anchor", unit="mm", ge=0)
    p_near_cm: float = setting(
        0.5, "probability an object passes near a given CM point", unit="1", ge=0, le=1
    )
    near_cm_radius_mm: float = setting(5.0, "its axis passes within this of the point", unit="mm", ge=0)
    oversample: int = setting(3, "rays per pixel side, averaged (anti-aliasing)", unit="1", ge=1)
    k_wire: bool = setting(False, "place K-wires (steel, rounded tip)")
    k_wire_count: IntRange = setting((1, 3), "number of K-wires", unit="1", ge=0)
    k_wire_diameter_mm_range: FloatRange = setting((1.6, 2.5), "K-wire diameter", unit="mm", gt=0)
    k_wire_length_mm_range: FloatRange = setting((100.0, 250.0), "K-wire length", unit="mm", gt=0)
    k_wire_materials: tuple[str, ...] = setting(("stainless_steel",), "K-wire materials")
    screw: bool = setting(False, "place screws (threaded shaft and head)")
    screw_count: IntRange = setting((1, 3), "number of screws", unit="1", ge=0)
    screw_diameter_mm_range: FloatRange = setting((4.5, 7.3), "screw major diameter", unit="mm", gt=0)
    screw_length_mm_range: FloatRange = setting((30.0, 110.0), "screw shaft length", unit="mm", gt=0)
    screw_materials: tuple[str, ...] = setting(("stainless_steel", "titanium"), "screw materials")
    p_cannulated: float = setting(0.5, "probability a screw is cannulated (hollow)", unit="1", ge=0, le=1)
    tube: bool = setting(False, "place hollow tubes like the CM's shaft")
    tube_count: IntRange = setting((1, 1), "number of tubes", unit="1", ge=0)
    tube_outer_diameter_mm_range: FloatRange = setting((3.0, 7.0), "tube outer diameter", unit="mm", gt=0)
    tube_wall_mm_range: FloatRange = setting((0.25, 1.0), "tube wall thickness", unit="mm", gt=0)
    tube_length_mm_range: FloatRange = setting((30.0, 150.0), "tube length", unit="mm", gt=0)
    tube_materials: tuple[str, ...] = setting(("nitinol", "stainless_steel"), "tube materials")
    cable: bool = setting(False, "place thin curved wires (cables, cerclage)")
    cable_count: IntRange = setting((1, 2), "number of cables", unit="1", ge=0)
    cable_diameter_mm_range: FloatRange = setting((0.5, 1.5), "cable diameter", unit="mm", gt=0)
    cable_length_mm_range: FloatRange = setting((100.0, 300.0), "cable length", unit="mm", gt=0)
    cable_max_bend_deg: float = setting(12.0, "bend between segments of 5 mm, at most", unit="deg", ge=0)
    cable_materials: tuple[str, ...] = setting(("copper", "stainless_steel"), "cable materials")

    def __post_init__(self) -> None:
        for name in ("k_wire", "screw", "tube", "cable"):
            lo, hi = getattr(self, f"{name}_count")
            if not 0 <= lo <= hi:
                raise ValueError(f"{name}_count must be (low, high) with 0 ≤ low ≤ high")
            if not getattr(self, f"{name}_materials"):
                raise ValueError(f"{name}_materials must name at least one material")
            for m in getattr(self, f"{name}_materials"):
                get_material(m)  # an unknown name is an InputError now, not at the first sample
        for key in (k for k in self.__dataclass_fields__ if k.endswith("_range")):
            lo, hi = getattr(self, key)
            if not lo <= hi:
                raise ValueError(f"{key} must be (low, high) with low ≤ high")


#: nothing placed (the default)
DISTRACTORS_OFF = DistractorConfig()
#: every kind on, at the default counts and sizes
DISTRACTORS_REALISTIC = DistractorConfig(k_wire=True, screw=True, tube=True, cable=True)
#: the presets by name
DISTRACTOR_PRESETS: dict[str, DistractorConfig] = {"off": DISTRACTORS_OFF, "realistic": DISTRACTORS_REALISTIC}


# ----- drawing ---------------------------------------------------------------------------------
def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / max(float(np.linalg.norm(v)), 1e-12)


def _in_ball(rng: np.random.Generator, radius_mm: float) -> np.ndarray:
    return _unit(rng) * radius_mm * float(rng.random()) ** (1.0 / 3.0)


def _placement(
    rng: np.random.Generator,
    length_mm: float,
    anchor: np.ndarray,
    near: np.ndarray | None,
    cfg: DistractorConfig,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """(centre (3,), unit axis (3,), whether it passes near a CM point) of an object of ``length_mm``."""
    axis = _unit(rng)
    if near is not None and len(near) > 0 and cfg.p_near_cm > 0 and bool(rng.random() < cfg.p_near_cm):
        point = near[int(rng.integers(len(near)))] + _in_ball(rng, cfg.near_cm_radius_mm)
        along = float(rng.uniform(-0.5, 0.5)) * length_mm  # where on the object the point lies
        return point - along * axis, axis, True
    return anchor + _in_ball(rng, cfg.placement_radius_mm), axis, False


def _pick(rng: np.random.Generator, options: tuple[str, ...]) -> str:
    return options[int(rng.integers(len(options)))]


def _vec(x: np.ndarray) -> list[float]:
    return [float(v) for v in x]


def _draw_k_wire(
    rng: np.random.Generator, anchor: np.ndarray, near: np.ndarray | None, cfg: DistractorConfig
) -> dict[str, Any]:
    d = float(rng.uniform(*cfg.k_wire_diameter_mm_range))
    length = float(rng.uniform(*cfg.k_wire_length_mm_range))
    material = _pick(rng, cfg.k_wire_materials)
    centre, axis, is_near = _placement(rng, length, anchor, near, cfg)
    return {
        "kind": "k_wire",
        "material": material,
        "diameter_mm": d,
        "start_world_mm": _vec(centre - 0.5 * length * axis),  # the rounded tip
        "end_world_mm": _vec(centre + 0.5 * length * axis),
        "near_cm": is_near,
    }


def _draw_screw(
    rng: np.random.Generator, anchor: np.ndarray, near: np.ndarray | None, cfg: DistractorConfig
) -> dict[str, Any]:
    d = float(rng.uniform(*cfg.screw_diameter_mm_range))
    length = float(rng.uniform(*cfg.screw_length_mm_range))
    material = _pick(rng, cfg.screw_materials)
    cannulated = cfg.p_cannulated > 0 and bool(rng.random() < cfg.p_cannulated)
    centre, axis, is_near = _placement(rng, length, anchor, near, cfg)
    return {
        "kind": "screw",
        "material": material,
        "diameter_mm": d,
        "core_diameter_mm": SCREW_CORE_RATIO * d,
        "head_diameter_mm": SCREW_HEAD_RATIO * d,
        "head_height_mm": SCREW_HEAD_HEIGHT_RATIO * d,
        "lumen_diameter_mm": SCREW_LUMEN_RATIO * d if cannulated else 0.0,
        "start_world_mm": _vec(centre - 0.5 * length * axis),  # the tip
        "end_world_mm": _vec(centre + 0.5 * length * axis),  # where the head begins
        "near_cm": is_near,
    }


def _draw_tube(
    rng: np.random.Generator, anchor: np.ndarray, near: np.ndarray | None, cfg: DistractorConfig
) -> dict[str, Any]:
    d = float(rng.uniform(*cfg.tube_outer_diameter_mm_range))
    wall = float(rng.uniform(*cfg.tube_wall_mm_range))
    length = float(rng.uniform(*cfg.tube_length_mm_range))
    material = _pick(rng, cfg.tube_materials)
    centre, axis, is_near = _placement(rng, length, anchor, near, cfg)
    return {
        "kind": "tube",
        "material": material,
        "diameter_mm": d,
        "inner_diameter_mm": max(d - 2.0 * wall, 0.0),
        "start_world_mm": _vec(centre - 0.5 * length * axis),
        "end_world_mm": _vec(centre + 0.5 * length * axis),
        "near_cm": is_near,
    }


def _draw_cable(
    rng: np.random.Generator, anchor: np.ndarray, near: np.ndarray | None, cfg: DistractorConfig
) -> dict[str, Any]:
    d = float(rng.uniform(*cfg.cable_diameter_mm_range))
    length = float(rng.uniform(*cfg.cable_length_mm_range))
    material = _pick(rng, cfg.cable_materials)
    centre, axis, is_near = _placement(rng, length, anchor, near, cfg)
    n = max(2, math.ceil(length / CABLE_SEGMENT_MM))
    step = length / n
    points = [np.zeros(3)]
    direction = axis
    for _ in range(n):
        points.append(points[-1] + step * direction)
        normal = _unit(rng)
        normal -= (normal @ direction) * direction
        normal /= max(float(np.linalg.norm(normal)), 1e-12)
        bend = math.radians(float(rng.uniform(0.0, cfg.cable_max_bend_deg)))
        direction = math.cos(bend) * direction + math.sin(bend) * normal
    pts = np.array(points)
    pts += centre - pts.mean(axis=0)
    return {
        "kind": "cable",
        "material": material,
        "diameter_mm": d,
        "points_world_mm": [_vec(p) for p in pts],
        "near_cm": is_near,
    }


_DRAW = {"k_wire": _draw_k_wire, "screw": _draw_screw, "tube": _draw_tube, "cable": _draw_cable}


def draw_distractors(
    anchor_world_mm: np.ndarray,
    cfg: DistractorConfig,
    rng: np.random.Generator,
    *,
    near_world_mm: np.ndarray | None = None,
) -> list[dict[str, Any]]:
    """Distractor objects drawn by ``cfg`` near ``anchor_world_mm`` (3,) (mm, world), as JSON-ready records.

    Kinds in the order K-wires, screws, tubes, cables; each drawn count, then per object its size,
    material and placement. ``near_world_mm`` (N, 3): points of the CM (e.g. its landmarks); with
    probability ``p_near_cm`` an object's axis passes within ``near_cm_radius_mm`` of one of them,
    so that it crosses or touches the CM's neighbourhood. Nothing is drawn for a kind that is off.
    """
    anchor = np.asarray(anchor_world_mm, np.float64).reshape(3)
    near = None if near_world_mm is None else np.asarray(near_world_mm, np.float64).reshape(-1, 3)
    records: list[dict[str, Any]] = []
    for kind, draw in _DRAW.items():
        if not getattr(cfg, kind):
            continue
        lo, hi = getattr(cfg, f"{kind}_count")
        for _ in range(int(rng.integers(lo, hi + 1))):
            records.append(draw(rng, anchor, near, cfg))
    return records


# ----- rendering -------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Solid:
    """A cylinder from ``start`` to ``end`` (world mm) of radius ``r_out`` less a bore of ``r_in``, with
    optional spherical caps (a capsule end), whose chords count ``fraction`` of the material's density."""

    start: np.ndarray
    end: np.ndarray
    r_out: float
    r_in: float = 0.0
    caps: tuple[bool, bool] = (False, False)
    fraction: float = 1.0


def _solids(record: dict[str, Any]) -> list[_Solid]:
    """The solids of a distractor record."""
    r = 0.5 * float(record["diameter_mm"])
    if record["kind"] == "cable":
        pts = np.asarray(record["points_world_mm"], np.float64)
        return [_Solid(pts[i], pts[i + 1], r) for i in range(len(pts) - 1)]
    start = np.asarray(record["start_world_mm"], np.float64)
    end = np.asarray(record["end_world_mm"], np.float64)
    if record["kind"] == "k_wire":
        return [_Solid(start, end, r, caps=(True, False))]
    if record["kind"] == "tube":
        return [_Solid(start, end, r, 0.5 * float(record["inner_diameter_mm"]))]
    if record["kind"] != "screw":
        raise ValueError(f"unknown distractor kind {record['kind']!r}")
    lumen, core = 0.5 * float(record["lumen_diameter_mm"]), 0.5 * float(record["core_diameter_mm"])
    axis = (end - start) / max(float(np.linalg.norm(end - start)), 1e-12)
    head_end = end + float(record["head_height_mm"]) * axis
    return [
        _Solid(start, end, core, lumen, caps=(True, False)),
        _Solid(start, end, r, core, fraction=SCREW_THREAD_FILL),
        _Solid(end, head_end, 0.5 * float(record["head_diameter_mm"]), lumen),
    ]


def _cylinder_interval(
    q: torch.Tensor, d: torch.Tensor, w: torch.Tensor, length: float, r: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Ray parameters (t_in, t_out) (N,) inside the cylinder of radius ``r`` along unit ``w`` from 0 to
    ``length``, for rays ``q + t·d`` (q: (3,) the origin relative to the axis' start; d: (N, 3) unit);
    t_in > t_out where a ray misses."""
    far = torch.full_like(d[:, 0], _FAR_MM)
    qz, dz = q @ w, d @ w
    q_perp, d_perp = q - qz * w, d - dz[:, None] * w
    a = (d_perp * d_perp).sum(-1)
    b = 2.0 * (d_perp @ q_perp)
    c = q_perp @ q_perp - r * r
    disc = b * b - 4.0 * a * c
    radial = a > 1e-15
    sq = disc.clamp_min(0.0).sqrt()
    a_safe = torch.where(radial, a, torch.ones_like(a))
    t_lo = torch.where(radial, (-b - sq) / (2.0 * a_safe), -far)
    t_hi = torch.where(radial, (-b + sq) / (2.0 * a_safe), far)
    radial_hit = torch.where(radial, disc > 0, c < 0)  # a ray along the axis is inside or not at all
    slab = dz.abs() > 1e-15
    dz_safe = torch.where(slab, dz, torch.ones_like(dz))
    s0, s1 = -qz / dz_safe, (length - qz) / dz_safe
    inside_slab = bool(0.0 <= float(qz) <= length)
    s_lo = torch.where(slab, torch.minimum(s0, s1), -far if inside_slab else far)
    s_hi = torch.where(slab, torch.maximum(s0, s1), far if inside_slab else -far)
    lo, hi = torch.maximum(t_lo, s_lo), torch.minimum(t_hi, s_hi)
    hit = radial_hit & (lo < hi)
    return torch.where(hit, lo, far), torch.where(hit, hi, -far)


def _sphere_interval(q: torch.Tensor, d: torch.Tensor, r: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(t_in, t_out) (N,) of rays ``q + t·d`` (q: origin relative to the centre, d: (N, 3) unit) in the
    ball of radius ``r``; t_in > t_out where a ray misses."""
    far = torch.full_like(d[:, 0], _FAR_MM)
    b = d @ q
    disc = b * b - (q @ q - r * r)
    sq = disc.clamp_min(0.0).sqrt()
    hit = disc > 0
    return torch.where(hit, -b - sq, far), torch.where(hit, -b + sq, -far)


def solid_chord_mm(
    origin: torch.Tensor,
    directions: torch.Tensor,
    start: Sequence[float] | np.ndarray,
    end: Sequence[float] | np.ndarray,
    radius_mm: float,
    *,
    caps: tuple[bool, bool] = (False, False),
) -> torch.Tensor:
    """Length (N,) in mm of each ray inside a solid cylinder from ``start`` to ``end`` (3,) of radius
    ``radius_mm``, with a ball of the same radius at the start and/or end where ``caps`` says (a
    capsule). Rays ``origin (3,) + t·directions (N, 3)`` (unit), t ≥ 0; any dtype and device.

    The parts' union is convex, so a ray's chord is the span of the parts' intervals (analytic).
    """
    dt, dev = directions.dtype, directions.device
    a = torch.as_tensor(np.asarray(start, np.float64), dtype=dt, device=dev)
    b = torch.as_tensor(np.asarray(end, np.float64), dtype=dt, device=dev)
    length = float(torch.linalg.norm(b - a))
    w = (b - a) / max(length, 1e-12)
    lo, hi = _cylinder_interval(origin - a, directions, w, length, radius_mm)
    for capped, centre in zip(caps, (a, b), strict=True):
        if capped:
            s_lo, s_hi = _sphere_interval(origin - centre, directions, radius_mm)
            lo, hi = torch.minimum(lo, s_lo), torch.maximum(hi, s_hi)
    return (hi - lo.clamp_min(0.0)).clamp_min(0.0)


def _footprint(camera: Camera, solid: _Solid) -> tuple[int, int, np.ndarray] | None:
    """Pixels that may see the solid: (row0, col0, (rows, cols) bool) of its projected box, true within
    a bound of its projected radius of the projected axis (the whole image if it reaches the source)."""
    r = solid.r_out
    offsets = np.array([[x, y, z] for x in (-r, r) for y in (-r, r) for z in (-r, r)])
    corners = (np.stack([solid.start, solid.end])[:, None, :] + offsets).reshape(-1, 3)
    z_min = float(camera.to_camera(corners)[:, 2].min())
    if z_min <= 1.0:
        return 0, 0, np.ones((camera.rows, camera.cols), bool)
    uv = camera.project(corners)
    c0, r0 = np.floor(uv.min(axis=0)).astype(int) - 1
    c1, r1 = np.ceil(uv.max(axis=0)).astype(int) + 2
    c0, r0, c1, r1 = max(int(c0), 0), max(int(r0), 0), min(int(c1), camera.cols), min(int(r1), camera.rows)
    if c1 <= c0 or r1 <= r0:
        return None
    # a point within r of the axis at depth ≥ z_min projects within f·r·(1 + tan)·√2 / z_min of the
    # axis' projection (tan: the ray's slope); a pixel's sub-rays reach ≤ 0.71 px from its centre
    tan = float(np.abs((uv - camera.K[:2, 2]) / np.diag(camera.K)[:2]).max())
    reach = max(camera.K[0, 0], camera.K[1, 1]) * r * (1.0 + tan) * math.sqrt(2.0) / z_min + 1.5
    a, b = camera.project(np.stack([solid.start, solid.end]))
    v, u = np.mgrid[r0:r1, c0:c1]
    p = np.stack([u, v], axis=-1).astype(np.float64) - a
    ab = b - a
    t = np.clip((p @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
    dist = np.linalg.norm(p - t[..., None] * ab, axis=-1)
    return r0, c0, dist <= reach


def _solid_integral(
    camera: Camera, solid: _Solid, footprint: tuple[int, int, np.ndarray], f: int, device: torch.device
) -> torch.Tensor:
    """Mean chord (mm) × fraction of the ``f × f`` rays of each footprint pixel through ``solid``,
    (rows, cols) of the footprint's box (0 outside the footprint)."""
    r0, c0, keep = footprint
    vs, us = np.nonzero(keep)
    sub = (torch.arange(f, dtype=torch.float64, device=device) + 0.5) / f - 0.5
    sv, su = torch.meshgrid(sub, sub, indexing="ij")
    u = torch.as_tensor(us + c0, dtype=torch.float64, device=device)[:, None] + su.reshape(1, -1)
    v = torch.as_tensor(vs + r0, dtype=torch.float64, device=device)[:, None] + sv.reshape(1, -1)
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1).reshape(-1, 3)
    pixel_to_world = np.ascontiguousarray((camera.world_from_camera[:3, :3] @ np.linalg.inv(camera.K)).T)
    dirs = pix @ torch.as_tensor(pixel_to_world, device=device)
    dirs = dirs / torch.linalg.norm(dirs, dim=-1, keepdim=True)
    origin = torch.as_tensor(camera.source_world, device=device)
    chord = solid_chord_mm(origin, dirs, solid.start, solid.end, solid.r_out, caps=solid.caps)
    if solid.r_in > 0:  # the bore lies within the solid's cylinder: subtract its chord
        chord = chord - solid_chord_mm(origin, dirs, solid.start, solid.end, solid.r_in)
    out = torch.zeros(keep.shape, dtype=torch.float64, device=device)
    out[torch.as_tensor(vs, device=device), torch.as_tensor(us, device=device)] = chord.reshape(
        -1, f * f
    ).mean(1)
    return solid.fraction * out


def render_distractors(
    camera: Camera,
    records: Sequence[dict[str, Any]],
    *,
    oversample: int = 3,
    device: str | torch.device = "cpu",
) -> dict[str, torch.Tensor]:
    """Areal densities of distractor records at ``camera``: material → (rows, cols) float32 g/cm².

    Each pixel averages ``oversample²`` rays (pixel centres at ``oversample`` 1); a ray's density is
    its analytic chord through each solid (mm) times the material's nominal density. Pixel (u, v)
    is the ray through ``K⁻¹ (u, v, 1)`` from the source (OpenCV convention, origin at the centre of
    the top-left pixel). No records: an empty dict.
    """
    dev = resolve_device(device)
    out: dict[str, torch.Tensor] = {}
    for record in records:
        material = str(record["material"])
        rho_per_mm = get_material(material).density_g_cm3 / MM_PER_CM  # chord mm → g/cm²
        for solid in _solids(record):
            footprint = _footprint(camera, solid)
            if footprint is None:
                continue
            r0, c0, keep = footprint
            if material not in out:
                out[material] = torch.zeros(camera.rows, camera.cols, dtype=torch.float64, device=dev)
            chords = _solid_integral(camera, solid, footprint, oversample, dev)
            out[material][r0 : r0 + keep.shape[0], c0 : c0 + keep.shape[1]] += rho_per_mm * chords
    return {m: v.to(torch.float32) for m, v in out.items()}


def distractor_densities(
    camera: Camera,
    anchor_world_mm: np.ndarray,
    cfg: DistractorConfig,
    rng: np.random.Generator,
    device: str | torch.device = "cpu",
    *,
    near_world_mm: np.ndarray | None = None,
) -> tuple[dict[str, torch.Tensor], list[dict[str, Any]]]:
    """Distractors drawn near ``anchor_world_mm`` (:func:`draw_distractors`) and their areal densities at
    ``camera`` (:func:`render_distractors`): (material → (rows, cols) float32 g/cm², records).

    Add the densities to the scene's (``XraySimulator.areal_densities``) before the physics; render
    the same records at another view's camera for a multi-view scene. ``cfg`` off: ``({}, [])``.
    """
    records = draw_distractors(anchor_world_mm, cfg, rng, near_world_mm=near_world_mm)
    return render_distractors(camera, records, oversample=cfg.oversample, device=device), records
