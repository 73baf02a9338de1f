"""Signed-distance primitives (mm) and rigid moves of them, from which the hip phantom is built."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "FAR",
    "Bone",
    "Coords",
    "Primitive",
    "SdfFn",
    "Vec",
    "axis_angle",
    "cone",
    "cup",
    "dot",
    "ellipsoid",
    "exit_point",
    "norm",
    "rotate_bone",
    "rotate_primitive",
    "slab",
    "smooth_union",
    "sphere",
    "sub",
    "tube",
]

FAR = 1.0e3  # "far outside" value of a signed distance field, mm

Coords = tuple[np.ndarray, np.ndarray, np.ndarray]  # broadcastable X, Y, Z (mm)
SdfFn = Callable[[Coords], np.ndarray]
Vec = Sequence[float] | np.ndarray  # a 3-vector, mm


# ---------------------------------------------------------------------------------------------
# Primitive signed-distance functions (mm). Each takes broadcastable coordinate arrays.
# ---------------------------------------------------------------------------------------------


def sub(P: Coords, c: np.ndarray) -> Coords:
    return P[0] - np.float32(c[0]), P[1] - np.float32(c[1]), P[2] - np.float32(c[2])


def dot(P: Coords, v: np.ndarray) -> np.ndarray:
    return P[0] * np.float32(v[0]) + P[1] * np.float32(v[1]) + P[2] * np.float32(v[2])


def norm(P: Coords) -> np.ndarray:
    return np.sqrt(P[0] * P[0] + P[1] * P[1] + P[2] * P[2])


@dataclass(frozen=True)
class Primitive:
    """One implicit shape: ``sdf(coords)`` and its axis-aligned bounding box (lo, hi) in mm."""

    sdf: SdfFn
    lo: np.ndarray
    hi: np.ndarray
    blend_mm: float = 0.0  # smooth-union radius with what came before


def sphere(c: Vec, r: float, blend_mm: float = 0.0) -> Primitive:
    c_ = np.asarray(c, dtype=np.float64)
    return Primitive(lambda P: norm(sub(P, c_)) - np.float32(r), c_ - r, c_ + r, blend_mm)


def ellipsoid(c: Vec, axes: np.ndarray, radii: Sequence[float], blend_mm: float = 0.0) -> Primitive:
    """Ellipsoid with orthonormal axes (columns of ``axes``); approximate (bound-preserving) distance."""
    c_ = np.asarray(c, dtype=np.float64)
    R = np.asarray(axes, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)

    def sdf(P: Coords) -> np.ndarray:
        d = sub(P, c_)
        q = [dot(d, R[:, i]) for i in range(3)]
        k0 = np.sqrt(sum((q[i] / np.float32(r[i])) ** 2 for i in range(3)))
        k1 = np.sqrt(sum((q[i] / np.float32(r[i] ** 2)) ** 2 for i in range(3)))
        return k0 * (k0 - 1.0) / np.maximum(k1, np.float32(1e-6))

    ext = np.sqrt(((R * r[None, :]) ** 2).sum(axis=1))
    return Primitive(sdf, c_ - ext, c_ + ext, blend_mm)


def cone(a: Vec, b: Vec, ra: float, rb: float, blend_mm: float = 0.0) -> Primitive:
    """Tapered capsule from ``a`` (radius ``ra``) to ``b`` (radius ``rb``)."""
    a_, b_ = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    ba = b_ - a_
    inv = 1.0 / float(ba @ ba)

    def sdf(P: Coords) -> np.ndarray:
        pa = sub(P, a_)
        h = np.clip(dot(pa, ba) * np.float32(inv), 0.0, 1.0)
        q = (pa[0] - h * np.float32(ba[0]), pa[1] - h * np.float32(ba[1]), pa[2] - h * np.float32(ba[2]))
        return norm(q) - (np.float32(ra) + h * np.float32(rb - ra))

    r = max(ra, rb)
    return Primitive(sdf, np.minimum(a_, b_) - r, np.maximum(a_, b_) + r, blend_mm)


def slab(a: Vec, b: Vec, c: Vec, half_mm: float, blend_mm: float = 0.0) -> Primitive:
    """A triangle thickened by ``half_mm`` (distance to the triangle minus half the thickness)."""
    A, B, C = (np.asarray(v, dtype=np.float64) for v in (a, b, c))
    ba, cb, ac = B - A, C - B, A - C
    nor = np.cross(ba, ac)
    edges = [(A, ba, np.cross(ba, nor)), (B, cb, np.cross(cb, nor)), (C, ac, np.cross(ac, nor))]

    def sdf(P: Coords) -> np.ndarray:
        outside = None
        edge_d2 = None
        for origin, e, en in edges:
            p = sub(P, origin)
            s = np.sign(dot(p, en))
            outside = s if outside is None else outside + s
            h = np.clip(dot(p, e) * np.float32(1.0 / (e @ e)), 0.0, 1.0)
            d2 = (float(e[0]) * h - p[0]) ** 2 + (float(e[1]) * h - p[1]) ** 2 + (float(e[2]) * h - p[2]) ** 2
            edge_d2 = d2 if edge_d2 is None else np.minimum(edge_d2, d2)
        plane = dot(sub(P, A), nor) ** 2 * np.float32(1.0 / (nor @ nor))
        assert outside is not None and edge_d2 is not None
        return np.sqrt(np.where(outside < 2.0, edge_d2, plane)) - np.float32(half_mm)

    pts = np.stack([A, B, C])
    return Primitive(sdf, pts.min(0) - half_mm, pts.max(0) + half_mm, blend_mm)


def cup(c: Vec, r: float, axis: np.ndarray, offset_mm: float, blend_mm: float = 0.0) -> Primitive:
    """A ball cut by the plane ``axis · (p − c) = offset`` (kept on the side opposite to ``axis``)."""
    c_ = np.asarray(c, dtype=np.float64)
    n = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)

    def sdf(P: Coords) -> np.ndarray:
        d = sub(P, c_)
        return np.maximum(norm(d) - np.float32(r), dot(d, n) - np.float32(offset_mm))

    return Primitive(sdf, c_ - r, c_ + r, blend_mm)


def tube(points: Sequence[Vec], radii: Sequence[float] | float, blend_mm: float = 0.0) -> list[Primitive]:
    """A polyline of tapered capsules."""
    pts = [np.asarray(p, dtype=np.float64) for p in points]
    rs = [float(radii)] * len(pts) if isinstance(radii, int | float) else [float(r) for r in radii]
    return [cone(pts[i], pts[i + 1], rs[i], rs[i + 1], blend_mm) for i in range(len(pts) - 1)]


def smooth_union(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    if k <= 0:
        return np.minimum(a, b)
    h = np.clip(0.5 + 0.5 * (b - a) / np.float32(k), 0.0, 1.0)
    return b + (a - b) * h - np.float32(k) * h * (1.0 - h)


@dataclass
class Bone:
    """A bone: an ordered list of primitives, smooth-unioned, then minus the ``carve`` primitives."""

    primitives: list[Primitive] = field(default_factory=list)
    carve: list[Primitive] = field(default_factory=list)  # shapes removed after the union
    thickness: SdfFn | None = None  # cortical thickness field (mm); None = the default thickness

    def add(self, *items: Primitive | list[Primitive]) -> None:
        for item in items:
            self.primitives.extend(item if isinstance(item, list) else [item])

    def bounds(self, margin: float) -> tuple[np.ndarray, np.ndarray]:
        lo = np.min([p.lo for p in self.primitives], axis=0) - margin
        hi = np.max([p.hi for p in self.primitives], axis=0) + margin
        return lo, hi

    def sdf_points(self, points: np.ndarray) -> np.ndarray:
        """The bone's field at (N, 3) world points (the same combination as on the grid), mm."""
        P = (
            points[:, 0].astype(np.float32),
            points[:, 1].astype(np.float32),
            points[:, 2].astype(np.float32),
        )
        d = np.full(points.shape[0], FAR, dtype=np.float32)
        for prim in self.primitives:
            d = smooth_union(d, prim.sdf(P).astype(np.float32), prim.blend_mm)
        return self._finish(P, d)

    def _finish(self, P: Coords, d: np.ndarray) -> np.ndarray:
        for prim in self.carve:
            d = np.maximum(d, -prim.sdf(P))
        return d


# ---------------------------------------------------------------------------------------------
# Rigid moves of primitives and bones; ray exit points.
# ---------------------------------------------------------------------------------------------


def axis_angle(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    k = axis / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    t = np.deg2rad(angle_deg)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def rotate_primitive(prim: Primitive, R: np.ndarray, centre: np.ndarray) -> Primitive:
    """The primitive rotated by ``R`` about ``centre`` (evaluated in back-rotated coordinates)."""
    Rt = R.T.astype(np.float32)
    c = centre.astype(np.float32)
    corners = np.array(
        [
            [x, y, z]
            for x in (prim.lo[0], prim.hi[0])
            for y in (prim.lo[1], prim.hi[1])
            for z in (prim.lo[2], prim.hi[2])
        ]
    )
    rc = (corners - centre) @ R.T + centre

    def sdf(P: Coords, f: SdfFn = prim.sdf) -> np.ndarray:
        d = (P[0] - c[0], P[1] - c[1], P[2] - c[2])
        q = tuple(Rt[k, 0] * d[0] + Rt[k, 1] * d[1] + Rt[k, 2] * d[2] + c[k] for k in range(3))
        return f(q)

    return Primitive(sdf, rc.min(0), rc.max(0), prim.blend_mm)


def rotate_bone(bone: Bone, R: np.ndarray, centre: np.ndarray) -> Bone:
    """The same bone rotated by ``R`` about ``centre``."""
    return Bone(
        primitives=[rotate_primitive(p, R, centre) for p in bone.primitives],
        carve=[rotate_primitive(p, R, centre) for p in bone.carve],
        thickness=bone.thickness,
    )


def exit_point(bone: Bone, start: np.ndarray, direction: np.ndarray, step_mm: float = 0.25) -> np.ndarray:
    """Last inside→outside crossing of the bone surface along a ray from ``start``, refined by bisection."""
    d = direction / np.linalg.norm(direction)
    t = np.arange(0.0, 150.0, step_mm)
    f = bone.sdf_points(start[None, :] + t[:, None] * d[None, :])
    inside = np.nonzero(f < 0)[0]
    if inside.size == 0 or inside[-1] + 1 >= t.size:
        raise RuntimeError("phantom construction error: the ray does not leave the bone")
    lo, hi = float(t[inside[-1]]), float(t[inside[-1] + 1])
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        if bone.sdf_points((start + mid * d)[None, :])[0] < 0:
            lo = mid
        else:
            hi = mid
    return start + 0.5 * (lo + hi) * d
