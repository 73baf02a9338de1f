"""What each level of a bone registration works on: volumes, binned views, DRRs and the similarity.

The DRR volume of a bone is its *attenuation in excess of soft tissue*,
``max(0, μ(HU) − μ(TISSUE_HU))`` on the bone's label (dilated by one voxel for its partial-volume
rim), cropped to the label's bounding box and box-downsampled per level: bone against the tissue
around it is what the X-ray shows, and the excess goes smoothly to 0 at the bone surface, so the
label mask adds no artificial edge. The views are binned per level (:class:`BoneLevelData`). The
patch radius follows xReg's rule (41 px at the 0.194 mm detector pixel, scaled) unless the level
sets one (docs/validation.md, "Bones").
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch
from scipy import ndimage
from torch.nn import functional as tnf

from fluoronav.anatomy.volume import MU_WATER_PER_MM, Volume, hu_to_mu
from fluoronav.geometry.camera import CIOS_FUSION, Camera
from fluoronav.registration.bone.presets import BoneLevel
from fluoronav.registration.bone.views import BoneView
from fluoronav.registration.engine import SimilarityFactory, default_similarity
from fluoronav.registration.levels import LevelConfig, patch_radius_for
from fluoronav.rendering.ct import CTRenderer

__all__ = [
    "TISSUE_HU",
    "BoneLevelData",
    "bone_excess_mu",
    "box_downsample",
    "level_similarity",
    "render_level",
    "shared_level_renderers",
]

#: soft tissue HU subtracted from the bone attenuation (see the module docstring)
TISSUE_HU = 40.0


#: per CT (weakly held: dropped with the volume): each bone's excess-μ volume and level renderers,
#: so that the registrations of a navigation (pelvis per view, femur, the verification's again)
#: build them once; a volume is treated as unchanging once registered against
_VOLUME_CACHE: weakref.WeakKeyDictionary[Volume, dict[Any, Any]] = weakref.WeakKeyDictionary()


def _cache_of(volume: Volume) -> dict[Any, Any]:
    try:
        return _VOLUME_CACHE.setdefault(volume, {})
    except TypeError:  # not weakly referenceable: no cache
        return {}


def shared_level_renderers(
    volume: Volume, label_names: Sequence[str], device: torch.device | str
) -> dict[Any, Any]:
    """The dict of level renderers of :func:`bone_excess_mu` ``(volume, label_names)`` on ``device``
    that every registration of those labels shares (:class:`BoneLevelData` ``renderers``)."""
    return _cache_of(volume).setdefault(("renderers", tuple(label_names), str(device)), {})


def bone_excess_mu(volume: Volume, label_names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Bone attenuation in excess of soft tissue on the labels, cropped: (μ (nz, ny, nx) float32 1/mm,
    world_from_index (4, 4) of the crop). Computed once per volume and labels (the arrays returned
    are shared: do not modify them).

    Raises:
        ValueError: no labels or a missing / empty label.
    """
    cache = _cache_of(volume)
    key = ("excess_mu", tuple(label_names))
    if key not in cache:
        cache[key] = _bone_excess_mu(volume, label_names)
    mu, world_from_index = cache[key]
    return mu, world_from_index.copy()


def _bone_excess_mu(volume: Volume, label_names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    if volume.labels is None:
        raise ValueError("bone registration needs a labelled CT")
    values = []
    for name in label_names:
        v = volume.label_value(name)
        if v is None:
            raise ValueError(f"the CT has no label {name!r} (labels: {volume.label_names})")
        values.append(v)
    bone = np.isin(volume.labels, values)
    if not bone.any():
        raise ValueError(f"labels {list(label_names)} are empty")
    other = (volume.labels > 0) & ~bone
    mask = ndimage.binary_dilation(bone, iterations=1) & ~other
    idx = np.argwhere(mask)
    lo, hi = idx.min(0), idx.max(0) + 1
    box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
    tissue = float(hu_to_mu(np.array([TISSUE_HU]), MU_WATER_PER_MM)[0])
    mu = np.where(mask[box], np.maximum(hu_to_mu(volume.data[box], MU_WATER_PER_MM) - tissue, 0.0), 0.0)
    offset = np.eye(4)
    offset[:3, 3] = [lo[2], lo[1], lo[0]]
    return np.ascontiguousarray(mu, dtype=np.float32), np.asarray(
        volume.world_from_index, np.float64
    ) @ offset


def box_downsample(mu: torch.Tensor, world_from_index: np.ndarray, f: int) -> tuple[torch.Tensor, np.ndarray]:
    """Box-average by ``f`` along every axis (zero padding: the zero outside the grid)."""
    if f == 1:
        return mu, world_from_index
    nz, ny, nx = mu.shape
    x = tnf.pad(mu[None, None], (0, (-nx) % f, 0, (-ny) % f, 0, (-nz) % f))
    small = tnf.avg_pool3d(x, kernel_size=f, stride=f)[0, 0].contiguous()
    S = np.diag([float(f), float(f), float(f), 1.0])
    S[:3, 3] = (f - 1) / 2.0
    return small, world_from_index @ S


class BoneLevelData:
    """Per level: working cameras, fixed images (filled, binned), view masks and the renderer of the
    volume pyramid level, keyed by the level's name (``<prefix>-<index>``); ``levels`` are the
    optimiser levels with those names and their patch radii. ``renderers``: a dict of the volume's
    renderers by (voxel factor, ``skip_empty``) from earlier registrations of the same ``mu``
    (:func:`shared_level_renderers`), reused and filled."""

    def __init__(
        self,
        views: Sequence[BoneView],
        mu: torch.Tensor,
        world_from_index: np.ndarray,
        levels: Sequence[BoneLevel],
        prefix: str,
        device: torch.device,
        *,
        skip_empty: bool = True,
        renderers: dict[Any, CTRenderer] | None = None,
    ) -> None:
        sizes = {(v.camera.rows, v.camera.cols) for v in views}
        if len(sizes) != 1:
            raise ValueError(f"all views must have the same image size, got {sorted(sizes)}")
        spacing = float(np.linalg.norm(world_from_index[:3, :3], axis=0).min())
        self.levels: list[LevelConfig] = []
        self.cams: dict[str, list[Camera]] = {}
        self.fixed: dict[str, torch.Tensor] = {}
        # shared with the caller when given: registrations of the same bone on other views reuse
        # each level's volume and its empty-space map
        shared: dict[Any, CTRenderer] = {} if renderers is None else renderers
        self.renderers: dict[str, CTRenderer] = {}
        self.masks: dict[str, torch.Tensor | None] = {}
        for i, lv in enumerate(levels):
            cols = views[0].camera.cols
            f = max(1, round(cols / lv.image_px))
            cams = [v.camera.downsample(f) for v in views]
            name = f"{prefix}-{i}"
            ps = cams[0].pixel_spacing_mm
            scale = (ps / CIOS_FUSION.pixel_spacing_mm) if ps else CIOS_FUSION.cols / cams[0].cols
            radius = (
                lv.patch_radius_px
                if lv.patch_radius_px is not None
                else patch_radius_for(max(1, round(scale)))
            )
            opt = lv.optimizer.with_(patch_radius=radius, name=name)
            self.levels.append(opt)
            self.cams[name] = cams
            # each view binned and its unused pixels filled at this level's resolution
            binned = [v.binned(f) for v in views]
            self.fixed[name] = torch.stack([torch.as_tensor(b[0], dtype=torch.float32) for b in binned]).to(
                device
            )
            self.masks[name] = (
                None
                if all(b[1] is None for b in binned)
                else torch.stack(
                    [torch.as_tensor(np.ones(b[0].shape, bool) if b[1] is None else b[1]) for b in binned]
                ).to(device)
            )
            vf = max(1, math.floor(lv.voxel_mm / spacing + 1e-6))
            if (vf, skip_empty) not in shared:
                small, w_small = box_downsample(mu, world_from_index, vf)
                shared[vf, skip_empty] = CTRenderer.from_tensor(
                    small, w_small, mipmap=False, skip_empty=skip_empty
                )
            self.renderers[name] = shared[vf, skip_empty]


def render_level(
    level_data: BoneLevelData, camera_from_view0: np.ndarray, object_poses: torch.Tensor, level: LevelConfig
) -> torch.Tensor:
    """DRRs (P, V, h, w) of the level volume for object poses ``view0_from_object`` (P, 4, 4);
    ``camera_from_view0``: (V, 4, 4) ``camera_k_from_camera_0``."""
    cams = level_data.cams[level.name]
    P, V = object_poses.shape[0], len(cams)
    T = (
        torch.as_tensor(camera_from_view0, dtype=torch.float64)[None] @ object_poses.cpu()[:, None]
    )  # (P, V, 4, 4)
    K = np.broadcast_to(np.stack([c.K for c in cams])[None], (P, V, 3, 3)).reshape(P * V, 3, 3)
    out = level_data.renderers[level.name].render_poses(
        K, T.reshape(P * V, 4, 4).numpy(), cams[0].rows, cams[0].cols
    )
    return out.reshape(P, V, cams[0].rows, cams[0].cols)


def level_similarity(level_data: BoneLevelData) -> SimilarityFactory:
    """The engine's default similarity with the level's binned view masks."""

    def make(
        fixed: torch.Tensor, level: LevelConfig, mask: torch.Tensor | None
    ) -> Callable[..., torch.Tensor]:
        return default_similarity(fixed, level, level_data.masks[level.name])

    return make
