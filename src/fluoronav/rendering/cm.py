"""Analytic DRR of the notched CM: exact line integrals ``μ · chord length`` through the solid.

Per link, in the link's straight frame, a ray ``o + t·d`` meets the annulus ``{r_in ≤ r ≤ r_out}``
in the outer cylinder's interval minus the inner one's, clipped to the link's axial slab; each
half-notch removes the same annulus clipped to the notch slab and the half-space ``side · y > cut``.
All pieces are convex, so the chord is a sum of closed-form interval overlaps. Only pixels inside a
link's projected bounding box are evaluated, so the cost scales with the CM's image area, not the
image size. Backends: ``"numba"`` (CPU, one parallel kernel over candidates × views, links and ROI
pixels) and ``"torch"`` (vectorised over candidates × views × links × tile pixels, for CUDA);
``"auto"`` picks numba on CPU and torch elsewhere. The link poses and boxes are computed in torch
float64 either way.
"""

from __future__ import annotations

import logging
from typing import Literal

import numpy as np
import torch

from fluoronav.device import resolve_device
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.geometry import Region, link_table, region_z_range_mm
from fluoronav.manipulator.kinematics import CMKinematics

__all__ = ["CMRenderer", "compile_kernels"]

logger = logging.getLogger(__name__)

Backend = Literal["auto", "numba", "torch"]
_BIG = 1e30


def _overlap(a0: torch.Tensor, a1: torch.Tensor, b0: torch.Tensor, b1: torch.Tensor) -> torch.Tensor:
    return (torch.minimum(a1, b1) - torch.maximum(a0, b0)).clamp_min(0.0)


def _slab(
    o: torch.Tensor, d: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Parameter interval of ``lo ≤ o + t·d ≤ hi`` (empty as (1, 0)), broadcast."""
    par = d.abs() < 1e-12
    ds = torch.where(par, torch.ones_like(d), d)
    t0, t1 = (lo - o) / ds, (hi - o) / ds
    tmin, tmax = torch.minimum(t0, t1), torch.maximum(t0, t1)
    inside = (lo <= o) & (o <= hi)
    tmin = torch.where(par, torch.where(inside, -_BIG, 1.0), tmin)
    tmax = torch.where(par, torch.where(inside, _BIG, 0.0), tmax)
    return tmin, tmax


def _cylinder(
    dist2: torch.Tensor, tc: torch.Tensor, a2s: torch.Tensor, par: torch.Tensor, radius: float
) -> tuple[torch.Tensor, torch.Tensor]:
    hit = dist2 < radius * radius
    h = torch.sqrt(((radius * radius - dist2) / a2s).clamp_min(0.0))
    t0 = torch.where(par, -_BIG, tc - h)
    t1 = torch.where(par, _BIG, tc + h)
    return torch.where(hit, t0, 1.0), torch.where(hit, t1, 0.0)


def chord_lengths_torch(
    o: torch.Tensor,
    d: torch.Tensor,
    z_range: torch.Tensor,
    notches: torch.Tensor,
    r_in: float,
    r_out: float,
    cut: float,
) -> torch.Tensor:
    """Parameter length of rays inside straight links (``t ≥ 0``, in units of ``|d|``).

    Args:
        o: (G, 1, 3) ray origins in each link's frame.
        d: (G, P, 3) ray directions in each link's frame.
        z_range: (G, 1, 2) link slab; notches: (G, 2, 3) half-notches ``(z_lo, z_hi, side)``.

    Returns:
        (G, P) chord parameter lengths.
    """
    ox, oy, oz = o[..., 0], o[..., 1], o[..., 2]
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    a2 = dx * dx + dy * dy
    par = a2 < 1e-24
    a2s = torch.where(par, torch.ones_like(a2), a2)
    tc = -(ox * dx + oy * dy) / a2s  # closest approach to the axis: stable near grazing rays
    px, py = ox + tc * dx, oy + tc * dy
    dist2 = torch.where(par, (ox * ox + oy * oy).expand_as(a2), px * px + py * py)
    o0, o1 = _cylinder(dist2, tc, a2s, par, r_out)
    i0, i1 = _cylinder(dist2, tc, a2s, par, r_in)
    z0, z1 = z_range[..., 0], z_range[..., 1]
    s0, s1 = _slab(oz, dz, z0, z1)
    s0 = s0.clamp_min(0.0)  # the ray starts at the source
    total = _overlap(o0, o1, s0, s1) - _overlap(i0, i1, s0, s1)
    for m in range(notches.shape[1]):
        na = torch.maximum(notches[:, m, 0:1], z0)
        nb = torch.minimum(notches[:, m, 1:2], z1)
        n0, n1 = _slab(oz, dz, na, nb)
        n0 = torch.maximum(n0, s0)
        n1 = torch.where(nb > na, n1, torch.full_like(n1, -_BIG))
        side = notches[:, m, 2:3]
        sd, so = side * dy, side * oy
        sds = torch.where(sd.abs() < 1e-12, torch.ones_like(sd), sd)
        th = (cut - so) / sds
        n0 = torch.where(sd >= 1e-12, torch.maximum(n0, th), n0)
        n1 = torch.where(sd <= -1e-12, torch.minimum(n1, th), n1)
        n1 = torch.where((sd.abs() < 1e-12) & (so <= cut), torch.full_like(n1, -_BIG), n1)
        total = total - (_overlap(o0, o1, n0, n1) - _overlap(i0, i1, n0, n1))
    return total.clamp_min(0.0)


def compile_kernels() -> None:
    """Compile the CPU link renderer for the argument types this module passes into numba's on-disk
    cache, so that a new process's first render loads the machine code instead of compiling it."""
    from fluoronav.rendering._cm_numba import RENDER_LINKS_ARGS, render_links

    for args in RENDER_LINKS_ARGS:
        render_links.compile(args)


class CMRenderer:
    """Analytic DRRs of the CM for batches of candidates and views.

    Args:
        config: CM geometry (paper defaults if None).
        mu_per_mm: linear attenuation coefficient of the CM material, 1/mm.
        device: torch device of the outputs (and of the torch backend).
        backend: ``"auto"`` (numba on CPU, torch otherwise), ``"numba"`` or ``"torch"``.
        torch_dtype: compute dtype of the torch backend (float64 by default; float32 is faster on
            GPUs and agrees to ~2e-3 mm near grazing rays).
        max_tile_elements: memory bound of the torch backend (groups × tile pixels per chunk).
        row_spans: numba backend: in each row of a link's box, only the columns across the box's
            projected footprint (the hull of its 8 projected corners; the same images, faster for
            an oblique CM); False: every pixel of the box (the benchmark's reference).
    """

    def __init__(
        self,
        config: CMConfig | None = None,
        *,
        mu_per_mm: float,
        device: str | torch.device = "cpu",
        backend: Backend = "auto",
        torch_dtype: torch.dtype = torch.float64,
        max_tile_elements: int = 1 << 22,
        row_spans: bool = True,
    ) -> None:
        self.config = config or CMConfig()
        self.mu_per_mm = float(mu_per_mm)
        self.device = resolve_device(device)
        if backend not in ("auto", "numba", "torch"):
            raise ValueError(f"unknown backend {backend!r}")
        self.backend = ("numba" if self.device.type == "cpu" else "torch") if backend == "auto" else backend
        self.torch_dtype = torch_dtype
        self.max_tile_elements = int(max_tile_elements)
        self.row_spans = bool(row_spans)
        self.kinematics = CMKinematics(self.config)
        self._table = link_table(self.config)

    # ----- geometry ---------------------------------------------------------------------
    def _prepare(
        self, camera_from_cm: torch.Tensor, control_points_deg: torch.Tensor, K: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        f64 = torch.float64
        T_cam = torch.as_tensor(camera_from_cm, dtype=f64, device=self.device)
        cp = torch.as_tensor(control_points_deg, dtype=f64, device=self.device)
        Kt = torch.as_tensor(K, dtype=f64, device=self.device)
        n = self.config.n_control_points
        if T_cam.ndim != 4 or T_cam.shape[-2:] != (4, 4):
            raise ValueError(f"camera_from_cm must be (B, V, 4, 4), got {tuple(T_cam.shape)}")
        B, V = T_cam.shape[:2]
        if cp.shape != (B, n):
            raise ValueError(f"control_points_deg must be ({B}, {n}), got {tuple(cp.shape)}")
        if Kt.shape != (V, 3, 3):
            raise ValueError(f"K must be ({V}, 3, 3), got {tuple(Kt.shape)}")
        return T_cam, cp, Kt

    def _camera_from_link(self, T_cam: torch.Tensor, cp: torch.Tensor) -> torch.Tensor:
        cm_from_link = self.kinematics.link_transforms(cp)  # (B, L, 4, 4)
        return T_cam[:, :, None] @ cm_from_link[:, None]  # (B, V, L, 4, 4)

    def _z_range(self, region: Region) -> np.ndarray:
        zlo, zhi = region_z_range_mm(self.config, region)
        zr = self._table.z_range_mm.copy()
        zr[:, 0] = np.maximum(zr[:, 0], zlo)
        zr[:, 1] = np.minimum(zr[:, 1], zhi)
        return zr

    def link_corners_px(
        self, camera_from_link: torch.Tensor, K: torch.Tensor, z_range: np.ndarray
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Projected corners of each link's straight box (``±r_out`` in x and y, its slab in z).

        Args:
            camera_from_link: (B, V, L, 4, 4); K: (V, 3, 3); z_range: (L, 2) rendered slab per link.

        Returns:
            uv (B, V, L, 8, 2) pixel positions of the corners (corner ``i``: x sign bit 0, y sign bit
            1, z end bit 2), and behind (B, V, L) bool: a corner lies at or behind the source plane
            (its projection is then not the box's footprint).
        """
        r = self._table.r_out_mm
        zr = torch.as_tensor(z_range, dtype=camera_from_link.dtype, device=camera_from_link.device)
        sx = torch.tensor([-1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0, 1.0], dtype=zr.dtype, device=zr.device) * r
        sy = torch.tensor([-1.0, -1.0, 1.0, 1.0, -1.0, -1.0, 1.0, 1.0], dtype=zr.dtype, device=zr.device) * r
        zz = torch.where(torch.arange(8, device=zr.device) < 4, zr[:, 0:1], zr[:, 1:2])  # (L, 8)
        corners = torch.stack([sx.expand_as(zz), sy.expand_as(zz), zz], dim=-1)  # (L, 8, 3)
        R, t = camera_from_link[..., :3, :3], camera_from_link[..., :3, 3]
        pc = corners @ R.transpose(-1, -2) + t[..., None, :]  # (B, V, L, 8, 3)
        uvw = pc @ K[None, :, None].transpose(-1, -2)
        depth = uvw[..., 2]
        behind = (depth <= 1e-6).any(dim=-1)  # (B, V, L)
        return uvw[..., :2] / depth.clamp_min(1e-6)[..., None], behind

    def link_bboxes(
        self,
        camera_from_link: torch.Tensor,
        K: torch.Tensor,
        z_range: np.ndarray,
        rows: int,
        cols: int,
        *,
        corners: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """Projected pixel boxes of the links.

        Args:
            camera_from_link: (B, V, L, 4, 4); K: (V, 3, 3); z_range: (L, 2) rendered slab per link.
            corners: :meth:`link_corners_px` of the same arguments, if already computed.

        Returns:
            (B, V, L, 4) int64 half-open ``(row0, row1, col0, col1)``, clipped to the image; empty
            (row1 = row0) for links with nothing to render. A box reaching behind the source covers
            the whole image.
        """
        uv, behind = corners if corners is not None else self.link_corners_px(camera_from_link, K, z_range)
        lo = uv.amin(dim=-2).floor()
        hi = uv.amax(dim=-2).ceil() + 1.0
        c0 = lo[..., 0].clamp(0, cols)
        c1 = hi[..., 0].clamp(0, cols)
        r0 = lo[..., 1].clamp(0, rows)
        r1 = hi[..., 1].clamp(0, rows)
        r0, c0 = torch.where(behind, 0.0, r0), torch.where(behind, 0.0, c0)
        r1, c1 = torch.where(behind, float(rows), r1), torch.where(behind, float(cols), c1)
        empty = torch.as_tensor(z_range[:, 1] <= z_range[:, 0], device=uv.device)
        r1 = torch.where(empty, r0, r1)
        return torch.stack([r0, r1, c0, c1], dim=-1).to(torch.int64)

    # ----- public API -------------------------------------------------------------------
    def render(
        self,
        camera_from_cm: torch.Tensor,
        control_points_deg: torch.Tensor,
        K: torch.Tensor,
        rows: int,
        cols: int,
        *,
        region: Region = "solid",
        roi: bool = True,
    ) -> torch.Tensor:
        """Line integrals of the CM.

        Args:
            camera_from_cm: (B, V, 4, 4) pose of the CM base frame in each view's camera, mm.
            control_points_deg: (B, n) control points per candidate.
            K: (V, 3, 3) intrinsics (pixels).
            rows, cols: image size.
            region: ``"solid"`` (the whole CM) or ``"notched"`` (only material between A and B).
            roi: evaluate only pixels inside each link's projected box (False evaluates every pixel
                for every link; same result, used as the benchmark baseline).

        Returns:
            (B, V, rows, cols) float32 line integrals ``μ · chord_mm`` on ``self.device``.
        """
        return self._integrate(camera_from_cm, control_points_deg, K, rows, cols, region, roi, self.mu_per_mm)

    def _integrate(
        self,
        camera_from_cm: torch.Tensor,
        control_points_deg: torch.Tensor,
        K: torch.Tensor,
        rows: int,
        cols: int,
        region: Region,
        roi: bool,
        scale: float,
    ) -> torch.Tensor:
        T_cam, cp, Kt = self._prepare(camera_from_cm, control_points_deg, K)
        B, V = T_cam.shape[:2]
        zr = self._z_range(region)
        cam_from_link = self._camera_from_link(T_cam, cp)
        corners = self.link_corners_px(cam_from_link, Kt, zr) if roi else None
        if roi:
            bbox = self.link_bboxes(cam_from_link, Kt, zr, rows, cols, corners=corners)
        else:
            full = torch.tensor([0, rows, 0, cols], dtype=torch.int64, device=self.device)
            bbox = full.expand(B, V, zr.shape[0], 4).clone()
            bbox[..., 1] = torch.where(torch.as_tensor(zr[:, 1] > zr[:, 0], device=self.device), rows, 0)
        R = cam_from_link[..., :3, :3]
        link_from_cam = torch.zeros_like(cam_from_link)
        link_from_cam[..., :3, :3] = R.transpose(-1, -2)
        link_from_cam[..., :3, 3] = -(R.transpose(-1, -2) @ cam_from_link[..., :3, 3:4])[..., 0]
        link_from_cam[..., 3, 3] = 1.0
        Kinv = torch.linalg.inv(Kt)
        if self.backend == "numba":
            # within a box, each row only across the box's projected footprint (its hull is ~2.5×
            # smaller than the axis-aligned box of a link seen obliquely)
            hull = corners if self.row_spans else None
            return self._render_numba(link_from_cam, bbox, hull, Kinv, zr, B, V, rows, cols, scale)
        return self._render_torch(link_from_cam, bbox, Kinv, zr, B, V, rows, cols, scale)

    def _render_numba(
        self,
        link_from_cam: torch.Tensor,
        bbox: torch.Tensor,
        hull: tuple[torch.Tensor, torch.Tensor] | None,
        Kinv: torch.Tensor,
        zr: np.ndarray,
        B: int,
        V: int,
        rows: int,
        cols: int,
        scale: float,
    ) -> torch.Tensor:
        from fluoronav.rendering._cm_numba import render_links

        out = np.zeros((B * V, rows, cols), dtype=np.float32)
        tab = self._table
        L = zr.shape[0]
        if hull is None:  # every pixel of the box
            uv = np.zeros((B * V, L, 8, 2))
            clip = np.zeros((B * V, L), dtype=np.bool_)
        else:
            uv = hull[0].reshape(B * V, L, 8, 2).cpu().numpy()
            clip = ~hull[1].reshape(B * V, L).cpu().numpy()
        render_links(
            out,
            np.ascontiguousarray(link_from_cam.reshape(B * V, -1, 4, 4).cpu().numpy()),
            np.ascontiguousarray(bbox.reshape(B * V, -1, 4).cpu().numpy()),
            np.ascontiguousarray(uv),
            np.ascontiguousarray(clip),
            np.ascontiguousarray(Kinv.cpu().numpy()),
            V,
            np.ascontiguousarray(zr),
            np.ascontiguousarray(tab.notches),
            tab.r_in_mm,
            tab.r_out_mm,
            tab.cut_mm,
            scale,
        )
        return torch.from_numpy(out).reshape(B, V, rows, cols).to(self.device)

    def _render_torch(
        self,
        link_from_cam: torch.Tensor,
        bbox: torch.Tensor,
        Kinv: torch.Tensor,
        zr: np.ndarray,
        B: int,
        V: int,
        rows: int,
        cols: int,
        scale: float,
    ) -> torch.Tensor:
        dt, dev = self.torch_dtype, self.device
        L = zr.shape[0]
        tab = self._table
        out = torch.zeros(B * V, rows * cols, dtype=dt, device=dev)
        box = bbox.reshape(-1, 4)  # (G, 4), G = B·V·L
        G = box.shape[0]
        h = (box[:, 1] - box[:, 0]).clamp_min(0)
        w = (box[:, 3] - box[:, 2]).clamp_min(0)
        live = torch.nonzero((h > 0) & (w > 0)).flatten()
        if live.numel() == 0:
            return out.reshape(B, V, rows, cols).float()
        H, W = int(h[live].max()), int(w[live].max())
        T = link_from_cam.reshape(G, 4, 4).to(dt)
        img_of = torch.arange(G, device=dev) // L
        view_of = img_of % V
        link_of = torch.arange(G, device=dev) % L
        zr_t = torch.as_tensor(zr, dtype=dt, device=dev)
        notch_t = torch.as_tensor(tab.notches, dtype=dt, device=dev)
        Kinv = Kinv.to(dt)
        ar_r = torch.arange(H, device=dev)
        ar_c = torch.arange(W, device=dev)
        chunk = max(1, self.max_tile_elements // (H * W))
        for s in range(0, live.numel(), chunk):
            g = live[s : s + chunk]
            rr = box[g, 0:1, None] + ar_r[None, :, None]  # (g, H, 1)
            cc = box[g, 2:3, None] + ar_c[None, None, :]  # (g, 1, W)
            valid = (rr < box[g, 1:2, None]) & (cc < box[g, 3:4, None])  # (g, H, W)
            rr_b, cc_b = rr.expand_as(valid), cc.expand_as(valid)
            pix = torch.stack([cc_b, rr_b, torch.ones_like(rr_b)], dim=-1).to(dt).reshape(len(g), H * W, 3)
            e = pix @ Kinv[view_of[g]].transpose(-1, -2)  # (g, P, 3) camera-frame directions
            Rl = T[g, :3, :3]
            d = e @ Rl.transpose(-1, -2)
            o = T[g, None, :3, 3]
            lengths = chord_lengths_torch(
                o, d, zr_t[link_of[g], None], notch_t[link_of[g]], tab.r_in_mm, tab.r_out_mm, tab.cut_mm
            )
            vals = lengths * e.norm(dim=-1) * scale
            vals = torch.where(valid.reshape(len(g), -1), vals, torch.zeros_like(vals))
            flat = (rr_b.clamp(max=rows - 1) * cols + cc_b.clamp(max=cols - 1)).reshape(len(g), -1)
            target = img_of[g, None].expand_as(flat) * (rows * cols) + flat
            out.view(-1).scatter_add_(0, target.reshape(-1), vals.reshape(-1))
        return out.reshape(B, V, rows, cols).float()

    def mask(
        self,
        camera_from_cm: torch.Tensor,
        control_points_deg: torch.Tensor,
        K: torch.Tensor,
        rows: int,
        cols: int,
        *,
        min_chord_mm: float = 0.0,
    ) -> torch.Tensor:
        """(B, V, rows, cols) bool: pixels whose ray crosses more than ``min_chord_mm`` of the notched part.

        The notched part is the material between landmarks A and B (straight-frame ``0 ≤ z ≤
        distal_notch_plane``); same arguments as :meth:`render`.
        """
        chord = self._integrate(camera_from_cm, control_points_deg, K, rows, cols, "notched", True, 1.0)
        return chord > min_chord_mm

    def landmarks_px(
        self, camera_from_cm: torch.Tensor, control_points_deg: torch.Tensor, K: torch.Tensor
    ) -> torch.Tensor:
        """(B, V, 2, 2) pixel positions (u, v) of landmarks A and B (float64, on ``self.device``)."""
        T_cam, cp, Kt = self._prepare(camera_from_cm, control_points_deg, K)
        ab = self.kinematics.landmarks_cm(cp)  # (B, 2, 3)
        pc = ab[:, None] @ T_cam[..., :3, :3].transpose(-1, -2) + T_cam[..., None, :3, 3]  # (B, V, 2, 3)
        uvw = pc @ Kt[None].transpose(-1, -2)
        return uvw[..., :2] / uvw[..., 2:3]
