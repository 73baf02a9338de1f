"""A procedural hip phantom: pelvis, sacrum, L5 and both proximal femurs in soft tissue, in HU.

The bones are smooth implicit shapes (spheres, ellipsoids, tapered capsules, thick triangles)
combined as signed-distance-style fields (smooth unions, a socket carved out of each acetabulum),
each evaluated only inside its bounding box and turned into a cortical shell over cancellous bone
with anti-aliased (partial-volume) boundaries.

Frame: world = LPS (mm), patient supine, direction identity, volume centre at the world origin
(within half a voxel). The default field of view is 344 × 240 × 240 mm (x, y, z), at 1.0 mm spacing
a (240, 240, 344) array (nz, ny, nx). Seed 0 is the canonical anatomy; other seeds vary the bones'
sizes and angles, the femur's pose about its head, body size, fat, HU levels and texture.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from fluoronav.anatomy.sdf import (
    FAR,
    Bone,
    Coords,
    axis_angle,
    cone,
    cup,
    dot,
    ellipsoid,
    exit_point,
    rotate_bone,
    slab,
    smooth_union,
    sphere,
    sub,
    tube,
)
from fluoronav.anatomy.volume import Volume

__all__ = ["DEFAULT_FOV_MM", "LABEL_NAMES", "hip_phantom"]

logger = logging.getLogger(__name__)

#: Field of view (x, y, z) in mm used when ``shape`` is not given.
DEFAULT_FOV_MM = (344.0, 240.0, 240.0)
#: Label values of the phantom's bones.
LABEL_NAMES = {1: "pelvis", 2: "femur_left", 3: "femur_right"}

AIR_HU = -1000.0


# ---------------------------------------------------------------------------------------------
# Anatomy parameters
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Params:
    scale: float = 1.0
    pelvis_width: float = 1.0
    head_radius_mm: float = 23.5
    neck_shaft_deg: float = 130.0
    anteversion_deg: float = 12.0
    neck_length_mm: float = 47.0
    abduction_deg: tuple[float, float] = (0.0, 0.0)  # (left, right)
    flexion_deg: tuple[float, float] = (0.0, 0.0)
    rotation_deg: tuple[float, float] = (0.0, 0.0)
    body_semi_axes_mm: tuple[float, float] = (168.0, 113.0)
    fat_mm: float = 18.0
    cortical_hu: float = 1500.0
    cancellous_hu: float = 280.0
    cortical_mm: float = 2.5


def _draw_params(seed: int) -> _Params:
    if seed == 0:
        return _Params()
    rng = np.random.default_rng(seed)

    def u(lo: float, hi: float) -> float:
        return float(rng.uniform(lo, hi))

    return _Params(
        scale=u(0.94, 1.05),
        pelvis_width=u(0.94, 1.05),
        head_radius_mm=u(22.0, 25.0),
        neck_shaft_deg=u(124.0, 136.0),
        anteversion_deg=u(7.0, 17.0),
        neck_length_mm=u(43.0, 50.0),
        abduction_deg=(u(-6.0, 8.0), u(-6.0, 8.0)),
        flexion_deg=(u(-8.0, 8.0), u(-8.0, 8.0)),
        rotation_deg=(u(-10.0, 10.0), u(-10.0, 10.0)),
        body_semi_axes_mm=(u(160.0, 170.0), u(104.0, 116.0)),
        fat_mm=u(10.0, 26.0),
        cortical_hu=u(1300.0, 1700.0),
        cancellous_hu=u(220.0, 360.0),
        cortical_mm=u(2.2, 3.0),
    )


# Hip joint centre height and antero-posterior position (mm) of the canonical anatomy.
_HIP_Z = -30.0
_HIP_Y = -10.0
_HIP_X = 84.0


def _pelvis(p: _Params) -> tuple[Bone, Bone, dict[str, np.ndarray]]:
    """Pelvis (ilium, ischium, pubis, sacrum) and L5; returns (pelvis, spine, landmarks)."""
    g = p.scale

    def P(x: float, y: float, z: float, s: float = 1.0) -> np.ndarray:
        # side-relative point (x ≥ 0 for the left side) → world, scaled about the hip-level centre
        return np.array([s * x * g * p.pelvis_width, _HIP_Y + y * g, _HIP_Z + z * g])

    pelvis, spine = Bone(), Bone()
    marks: dict[str, np.ndarray] = {}
    R_socket = p.head_radius_mm + 2.0
    for s, side in ((1.0, "left"), (-1.0, "right")):
        A = P(_HIP_X, 0, 0, s)
        # acetabular cup: a thick sphere opening laterally, inferiorly and anteriorly
        axis = np.array([s * 0.72, -0.30, -0.62])
        axis /= np.linalg.norm(axis)
        cup_r = R_socket + 9.0 * g
        cup_c = A - axis * 3.0
        pelvis.add(cup(cup_c, cup_r, axis, 1.0))
        # ilium body rising from the acetabulum to the wing
        pelvis.add(cone(P(_HIP_X - 6, 4, 8, s), P(76, 14, 46, s), 17 * g, 12 * g, blend_mm=6))
        # iliac wing: a fan of thick triangles from the ilium body to the crest
        apex = P(76, 14, 44, s)
        rim = [
            P(100, -30, 24, s),  # AIIS
            P(118, -46, 55, s),  # ASIS
            P(132, -20, 86, s),
            P(128, 14, 106, s),
            P(106, 44, 113, s),
            P(76, 64, 102, s),
            P(48, 72, 76, s),  # PSIS
            P(44, 58, 42, s),  # posterior inferior, at the sacro-iliac joint
        ]
        for a, b in itertools.pairwise(rim):
            pelvis.add(slab(apex, a, b, 4.0 * g, blend_mm=3))
        pelvis.add(tube(rim[1:7], 6.0 * g, blend_mm=3))  # iliac crest
        pelvis.add(sphere(rim[1], 8.0 * g, blend_mm=4))  # ASIS
        pelvis.add(sphere(rim[0], 7.0 * g, blend_mm=4))  # AIIS
        # arcuate line / pelvic brim from the sacro-iliac joint to the iliopubic eminence
        pelvis.add(tube([P(42, 50, 50, s), P(58, 30, 30, s), P(68, 6, 12, s), P(62, -20, -2, s)], 7 * g, 4))
        # superior pubic ramus to the symphysis; pubic body; inferior pubic and ischial rami
        pelvis.add(
            tube(
                [P(_HIP_X - 8, -14, -4, s), P(60, -24, -6, s), P(34, -44, -16, s), P(11, -52, -24, s)],
                [13 * g, 10 * g, 8.5 * g, 9 * g],
                4,
            )
        )
        pelvis.add(cone(P(11, -52, -24, s), P(15, -46, -54, s), 10 * g, 8 * g, 4))
        pelvis.add(
            tube([P(15, -46, -54, s), P(30, -30, -64, s), P(48, -6, -70, s)], [8 * g, 7 * g, 8 * g], 4)
        )
        # ischial tuberosity and ischium body back up to the acetabulum
        pelvis.add(cone(P(48, -6, -70, s), P(62, 14, -56, s), 10 * g, 13 * g, 5))
        pelvis.add(cone(P(62, 14, -56, s), P(_HIP_X - 4, 8, -10, s), 13 * g, 16 * g, 6))
        pelvis.add(cone(P(66, 30, -22, s), P(58, 40, -34, s), 6 * g, 3 * g, 3))  # ischial spine
        pelvis.carve.append(sphere(A, R_socket))
        marks[f"asis_{side}"] = rim[1] + np.array([0.0, -8.0 * g, 0.0])
        marks[f"ischial_tuberosity_{side}"] = P(55, 4, -63, s) + np.array([0.0, 0.0, -13.0 * g])
        marks[f"acetabulum_{side}"] = A
    # sacrum: central column, alae towards the sacro-iliac joints, a tapered wedge between them
    pelvis.add(
        tube([P(0, 44, 56), P(0, 64, 24), P(0, 82, -8), P(0, 80, -36)], [18 * g, 15 * g, 9 * g, 5 * g], 5)
    )
    for s in (1.0, -1.0):
        pelvis.add(cone(P(0, 46, 54), P(44, 54, 52, s), 16 * g, 15 * g, 5))
    pelvis.add(slab(P(44, 52, 54), P(-44, 52, 54), P(0, 80, -4), 10 * g, 5))
    # anterior sacral foramina: four pairs of antero-posterior channels
    for x, z, r in ((22, 40, 3.5), (20, 24, 3.2), (17, 9, 2.8), (14, -4, 2.5)):
        y0 = 44 + (56 - z) * 0.6
        for s in (1.0, -1.0):
            pelvis.carve.append(cone(P(x, y0 - 22, z, s), P(x, y0 + 22, z - 6, s), r * g, r * g))
    marks["sacral_promontory"] = P(0, 44, 56) + np.array([0.0, -18.0 * g, 0.0])
    marks["pubic_symphysis"] = np.array([0.0, _HIP_Y - 52 * g - 9 * g, _HIP_Z - 30 * g])
    # L5 vertebra: body, transverse processes, spinous process (bone without a label)
    spine.add(cone(P(0, 34, 102), P(0, 34, 134), 22 * g, 22 * g))
    spine.add(tube([P(-52, 48, 104), P(52, 48, 104)], 7 * g, 4))
    spine.add(cone(P(0, 50, 110), P(0, 84, 104), 8 * g, 6 * g, 4))
    return pelvis, spine, marks


def _femur(p: _Params, side: str) -> tuple[Bone, dict[str, np.ndarray]]:
    """Proximal femur for one side; returns the bone and its landmarks (head centre, entry...)."""
    s = 1.0 if side == "left" else -1.0
    i = 0 if side == "left" else 1
    g = p.scale
    c = np.array([s * _HIP_X * g * p.pelvis_width, _HIP_Y, _HIP_Z])
    R = p.head_radius_mm
    # anatomical shaft axis (proximal direction): tilted ~7° so the knees are medial of the hips
    tilt = np.deg2rad(7.0)
    u = np.array([s * np.sin(tilt), 0.0, np.cos(tilt)])
    lat = np.array([s * np.cos(tilt), 0.0, -np.sin(tilt)])
    post = np.array([0.0, 1.0, 0.0])
    av = np.deg2rad(p.anteversion_deg)
    h = np.cos(av) * (-lat) + np.sin(av) * (-post)  # medial, turned anteriorly by the anteversion
    h -= (h @ u) * u
    h /= np.linalg.norm(h)
    a = np.deg2rad(180.0 - p.neck_shaft_deg)
    n = np.cos(a) * u + np.sin(a) * h  # neck axis, pointing from the shaft to the head
    L = p.neck_length_mm * g
    b = c - L * n  # neck axis meets the shaft axis here
    lat_t = np.cross(post, u) * s  # lateral unit normal to the shaft, in the coronal plane
    lat_t /= np.linalg.norm(lat_t)

    bone = Bone()
    bone.add(sphere(c, R))
    bone.add(cone(c - 0.35 * R * n, b + 6 * g * u, 0.66 * R, 19 * g, blend_mm=8))  # neck
    bone.add(tube([b + 22 * g * u, b - 40 * g * u, b - 320 * g * u], [18 * g, 15 * g, 13.5 * g], 10))  # shaft
    G = b + 16 * g * u + 20 * g * lat_t + 5 * g * post
    bone.add(ellipsoid(G, np.stack([lat_t, post, u], axis=1), [13 * g, 17 * g, 22 * g], blend_mm=8))
    LT = b - 30 * g * u - 11 * g * lat_t + 10 * g * post
    bone.add(ellipsoid(LT, np.stack([lat_t, post, u], axis=1), [8 * g, 8 * g, 12 * g], blend_mm=5))
    # intertrochanteric crest (posterior ridge from greater to lesser trochanter)
    bone.add(cone(G - 4 * g * lat_t + 6 * g * post, LT + 2 * g * post, 8 * g, 6 * g, 6))

    # pose: abduction (about y), flexion (about x), rotation (about the shaft axis) around the head
    Rp = (
        axis_angle(np.array([0.0, 1.0, 0.0]), -s * p.abduction_deg[i])  # + moves the knee laterally
        @ axis_angle(np.array([1.0, 0.0, 0.0]), -p.flexion_deg[i])  # + moves the knee anteriorly
        @ axis_angle(u, s * p.rotation_deg[i])
    )
    if not np.allclose(Rp, np.eye(3)):
        bone = rotate_bone(bone, Rp, c)
        G, LT = Rp @ (G - c) + c, Rp @ (LT - c) + c

    b_w, u_w = Rp @ (b - c) + c, Rp @ u
    t0 = p.cortical_mm

    def thickness(P: Coords) -> np.ndarray:
        # the diaphyseal cortex thickens to ~5 mm below the lesser trochanter
        below = -dot(sub(P, b_w), u_w)
        return np.float32(t0) + np.float32(2.5) * np.clip(
            (below - np.float32(35.0 * g)) / np.float32(40.0), 0, 1
        )

    bone.thickness = thickness
    marks = {
        f"femoral_head_{side}": c,
        f"greater_trochanter_{side}": G,
        f"lesser_trochanter_{side}": LT,
    }
    # entry point: where the drilling line from the head centre through the greater trochanter's
    # centre leaves the femur, i.e. on its lateral surface
    marks[f"entry_{side}"] = exit_point(bone, c, G - c)
    return bone, marks


# Rasterisation
# ---------------------------------------------------------------------------------------------


def _axis_coords(origin: np.ndarray, spacing: float, shape_xyz: tuple[int, int, int]) -> list[np.ndarray]:
    return [(origin[k] + spacing * np.arange(shape_xyz[k])).astype(np.float32) for k in range(3)]


def _box(lo: np.ndarray, hi: np.ndarray, axes: list[np.ndarray]) -> tuple[slice, slice, slice] | None:
    """Index slices (z, y, x) of the grid points inside [lo, hi], or None if empty."""
    sl = []
    for k in range(3):
        i0 = int(np.searchsorted(axes[k], lo[k], side="left"))
        i1 = int(np.searchsorted(axes[k], hi[k], side="right"))
        if i1 <= i0:
            return None
        sl.append(slice(i0, i1))
    return sl[2], sl[1], sl[0]


def _coords(box: tuple[slice, slice, slice], axes: list[np.ndarray]) -> Coords:
    zs, ys, xs = box
    return axes[0][xs][None, None, :], axes[1][ys][None, :, None], axes[2][zs][:, None, None]


def _rasterise(
    bone: Bone, axes: list[np.ndarray], margin: float
) -> tuple[tuple[slice, slice, slice], np.ndarray] | None:
    """The bone's field on the grid inside its bounding box: (box, sdf array)."""
    lo, hi = bone.bounds(margin)
    box = _box(lo, hi, axes)
    if box is None:
        return None
    shape = tuple(s.stop - s.start for s in box)
    d = np.full(shape, FAR, dtype=np.float32)
    for prim, carve in [(q, False) for q in bone.primitives] + [(q, True) for q in bone.carve]:
        pb = _box(prim.lo - margin - prim.blend_mm, prim.hi + margin + prim.blend_mm, axes)
        if pb is None:
            continue
        # the primitive's box intersected with the bone box, relative to the bone box
        rel = tuple(
            slice(max(pb[k].start, box[k].start) - box[k].start, min(pb[k].stop, box[k].stop) - box[k].start)
            for k in range(3)
        )
        if any(r.stop <= r.start for r in rel):
            continue
        absolute = tuple(slice(r.start + box[k].start, r.stop + box[k].start) for k, r in enumerate(rel))
        f = prim.sdf(_coords(absolute, axes)).astype(np.float32, copy=False)  # type: ignore[arg-type]
        d[rel] = np.maximum(d[rel], -f) if carve else smooth_union(d[rel], f, prim.blend_mm)
    return box, d


def _ellipse_sdf(x: np.ndarray, y: np.ndarray, a: float, b: float) -> np.ndarray:
    """Approximate signed distance (mm) to an axis-aligned ellipse with semi-axes a, b."""
    k0 = np.sqrt((x / np.float32(a)) ** 2 + (y / np.float32(b)) ** 2)
    k1 = np.sqrt((x / np.float32(a * a)) ** 2 + (y / np.float32(b * b)) ** 2)
    return k0 * (k0 - 1.0) / np.maximum(k1, np.float32(1e-6))


def _texture(rng: np.random.Generator, shape: tuple[int, ...], cell_vox: float) -> np.ndarray:
    """Smooth unit-variance-ish noise (trilinear upsampling of a coarse Gaussian grid), float32."""
    coarse = rng.standard_normal(tuple(int(np.ceil(n / cell_vox)) + 2 for n in shape), dtype=np.float32)
    zoomed = ndimage.zoom(coarse, [n / c for n, c in zip(shape, coarse.shape, strict=True)], order=1)
    out = np.zeros(shape, dtype=np.float32)
    sl = tuple(slice(0, min(a, b)) for a, b in zip(shape, zoomed.shape, strict=True))
    out[sl] = zoomed[sl]
    return out


def _soft_tissue_hu(
    p: _Params, marks: dict[str, np.ndarray], axes: list[np.ndarray], h: np.float32
) -> np.ndarray:
    """One axial slice of the soft tissue (ny, nx) HU: an elliptic cylinder (muscle) with a
    subcutaneous fat layer, in air, anti-aliased over ``h`` mm."""
    # widened where needed so the greater trochanters stay covered, but kept inside the default
    # field of view
    a_body, b_body = p.body_semi_axes_mm
    bony_half_width = max(abs(marks["entry_left"][0]), abs(marks["entry_right"][0]))
    a_body = min(max(a_body, bony_half_width + p.fat_mm + 8.0), 0.5 * DEFAULT_FOV_MM[0] - 1.5)
    fat_mm = min(p.fat_mm, a_body - bony_half_width - 6.0)
    d2 = _ellipse_sdf(axes[0][None, :], (axes[1] - np.float32(2.0))[:, None], a_body, b_body)
    f_body = np.clip(0.5 - d2 / h, 0.0, 1.0)
    f_muscle = np.clip(0.5 - (d2 + np.float32(fat_mm)) / h, 0.0, 1.0)
    slice_hu: np.ndarray = AIR_HU * (1.0 - f_body) + (-100.0) * (f_body - f_muscle) + 40.0 * f_muscle
    return slice_hu


def _paint_bones(
    data: np.ndarray,
    labels: np.ndarray,
    bones: list[tuple[Bone, int]],
    axes: list[np.ndarray],
    p: _Params,
    h: np.float32,
    spacing_mm: float,
    rng: np.random.Generator | None,
) -> None:
    """Paint each bone into ``data`` (HU) in place, a cortical shell over cancellous bone (textured
    from ``rng`` where given), and its label value (0: none) into ``labels``."""
    margin = p.cortical_mm + 2.0 * spacing_mm
    for bone, value in bones:
        raster = _rasterise(bone, axes, margin)
        if raster is None:
            continue
        box, d = raster
        t = bone.thickness(_coords(box, axes)) if bone.thickness is not None else np.float32(p.cortical_mm)
        f_out = np.clip(0.5 - d / h, 0.0, 1.0)
        f_in = np.clip(0.5 - (d + t) / h, 0.0, 1.0)
        canc: np.ndarray | np.float32 = np.float32(p.cancellous_hu)
        if rng is not None:
            canc = canc + np.float32(35.0) * _texture(rng, d.shape, 6.0 / spacing_mm)
        region = data[box]
        region *= 1.0 - f_out
        region += np.float32(p.cortical_hu) * (f_out - f_in) + canc * f_in
        if value:
            labels[box][d < 0] = value


def hip_phantom(
    *,
    seed: int = 0,
    spacing_mm: float = 1.0,
    shape: tuple[int, int, int] | None = None,
    texture: bool = True,
) -> Volume:
    """Build the procedural hip phantom (HU, float32) with labels and landmarks.

    Args:
        seed: anatomy and texture seed; 0 is the canonical anatomy, other seeds vary the shape
            (sizes ±~7 %, head radius 22–25 mm, neck-shaft angle 124–136°, anteversion 7–17°, femur
            pose within a few degrees) and the HU levels. The same seed gives the same volume.
        spacing_mm: isotropic voxel size in mm.
        shape: array shape (nz, ny, nx); default covers :data:`DEFAULT_FOV_MM` (344 × 240 × 240 mm,
            x × y × z) at ``spacing_mm``. The anatomy keeps its size in mm; a small shape crops it.
        texture: add a gentle noise texture (±~40 HU) to cancellous bone.

    Returns:
        a :class:`Volume` named ``phantom-<seed>``: LPS world frame, identity direction, centre at
        the origin; labels ``{1: pelvis, 2: femur_left, 3: femur_right}``; landmarks (world mm)
        ``femoral_head_left/right`` (head centres), ``entry_left/right`` (drilling entry on the
        lateral surface of the greater trochanter), ``pelvis_center`` (midpoint of the acetabular
        centres), ``asis_left/right``, ``pubic_symphysis``, ``sacral_promontory``,
        ``ischial_tuberosity_left/right``, ``acetabulum_left/right``,
        ``greater_trochanter_left/right``, ``lesser_trochanter_left/right``.

    HU levels: air −1000, fat ≈ −100, muscle ≈ 40, cancellous bone ≈ 220–360, cortical bone
    ≈ 1300–1700 (2.2–3 mm shell; up to ~5 mm along the femoral shaft).
    """
    if spacing_mm <= 0:
        raise ValueError(f"spacing_mm must be positive, got {spacing_mm}")
    if shape is None:
        shape_xyz = tuple(round(f / spacing_mm) for f in DEFAULT_FOV_MM)
    else:
        if len(shape) != 3 or min(shape) < 2:
            raise ValueError(f"shape must be (nz, ny, nx) with each ≥ 2, got {shape}")
        shape_xyz = (int(shape[2]), int(shape[1]), int(shape[0]))
    nx, ny, nz = shape_xyz
    origin = -0.5 * spacing_mm * (np.asarray(shape_xyz, dtype=np.float64) - 1.0)
    axes = _axis_coords(origin, spacing_mm, shape_xyz)  # type: ignore[arg-type]
    p = _draw_params(seed)
    rng = np.random.default_rng([seed, 0x41A7])  # texture stream, separate from the shape draw
    h = np.float32(max(spacing_mm, 1e-3))

    pelvis, spine, marks = _pelvis(p)
    femurs = {}
    for side in ("left", "right"):
        bone, fm = _femur(p, side)
        femurs[side] = bone
        marks.update(fm)
    marks["pelvis_center"] = 0.5 * (marks["acetabulum_left"] + marks["acetabulum_right"])

    slice_hu = _soft_tissue_hu(p, marks, axes, h)
    data = np.empty((nz, ny, nx), dtype=np.float32)
    data[:] = slice_hu.astype(np.float32)[None]
    labels = np.zeros((nz, ny, nx), dtype=np.uint8)

    bones = [(spine, 0), (pelvis, 1), (femurs["left"], 2), (femurs["right"], 3)]
    _paint_bones(data, labels, bones, axes, p, h, spacing_mm, rng if texture else None)

    volume = Volume(
        data=data,
        spacing_mm=(spacing_mm, spacing_mm, spacing_mm),
        origin_mm=(float(origin[0]), float(origin[1]), float(origin[2])),
        direction=np.eye(3),
        labels=labels,
        label_names=dict(LABEL_NAMES),
        landmarks_world={k: np.asarray(v, dtype=np.float64) for k, v in marks.items()},
        name=f"phantom-{seed}",
    )
    logger.debug("hip phantom seed=%d shape=%s spacing=%.3g mm", seed, data.shape, spacing_mm)
    return volume
