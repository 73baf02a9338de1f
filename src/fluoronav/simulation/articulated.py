"""Physics X-ray simulation of an articulated hip: the patient and one femur move independently.

The CT is split once, by its labels, into two rigid bodies: ``rest``, the CT with the chosen femur's voxels
(its label dilated by one voxel, minus other bones') replaced by soft tissue (:data:`FILLER_HU`), so that the
femur can turn inside tissue; and ``femur``, the femur's per-material partial densities *minus* the filler's
on the same voxels, cropped to their bounding box (with identity motions ``rest + femur`` is exactly the CT's
material decomposition). Each body is rendered at its own pose (``world_from_patient`` moves both;
``world_from_femur`` is the femur's total motion) and the per-material areal densities are summed and clamped
at 0. The drilled path, the voxelised CM, the labels and the detector physics are those of
:class:`~fluoronav.simulation.xray.XraySimulator`, reused through a subclass that drills once per body, each
in its own frame.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from fluoronav.anatomy.io import resolve_ct
from fluoronav.anatomy.volume import Volume
from fluoronav.device import resolve_device
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.rendering.ct import QUANTISED_LEVELS, CTRenderer, quantise_uint16
from fluoronav.simulation.instrument import BuiltCM
from fluoronav.simulation.materials import DECOMPOSE_CHUNK_VOXELS, MM_PER_CM, decompose_hu, hu_to_density
from fluoronav.simulation.scene import Scene
from fluoronav.simulation.xray import (
    RENDERED_CT_MATERIALS,
    SimulatedImage,
    SimulationConfig,
    VaryImage,
    XraySimulator,
    imaged,
)

__all__ = ["FILLER_HU", "ArticulatedSimulator", "femur_in_box", "split_femur"]

log = logging.getLogger(__name__)

#: HU of the soft tissue that fills the femur's place in the ``rest`` body
FILLER_HU = 40.0


def split_femur(volume: Volume, side: str, *, dilate_voxels: int = 1) -> tuple[np.ndarray, tuple[slice, ...]]:
    """The femur's voxel mask (nz, ny, nx) bool and its bounding box (slices, one voxel margin).

    Raises:
        ValueError: the volume has no labels or no ``femur_<side>`` label.
    """
    crop, box = femur_in_box(volume, side, dilate_voxels=dilate_voxels)
    mask = np.zeros(np.shape(volume.data), dtype=np.bool_)
    mask[box] = crop
    return mask, box


def femur_in_box(
    volume: Volume, side: str, *, dilate_voxels: int = 1
) -> tuple[np.ndarray, tuple[slice, ...]]:
    """:func:`split_femur`'s ``mask[box]`` and ``box``, without a mask of the whole volume.

    The mask (the label dilated by ``dilate_voxels``, minus other labels) is computed on the label's
    bounding box grown by ``dilate_voxels + 1``: each voxel within ``dilate_voxels`` steps of the
    femur is reached along a path inside the box spanned by the two, so the result is exact.

    Raises:
        ValueError: the volume has no labels or no ``femur_<side>`` label.
    """
    if volume.labels is None:
        raise ValueError("the articulated simulator needs a labelled CT")
    value = volume.label_value(f"femur_{side}")
    if value is None:
        raise ValueError(f"the CT has no label 'femur_{side}' (labels: {volume.label_names})")
    labels = volume.labels
    shape = np.asarray(labels.shape)
    # the label's extent per axis (no coordinates of every femur voxel)
    is_femur = labels == value
    if not is_femur.any():
        raise ValueError(f"label 'femur_{side}' is empty")
    extent = []
    for axis in range(3):
        hit = np.flatnonzero(np.any(is_femur, axis=tuple(a for a in range(3) if a != axis)))
        extent.append((int(hit[0]), int(hit[-1])))
    del is_femur
    grow = max(dilate_voxels, 0) + 1
    r_lo = np.maximum(np.array([a for a, _ in extent]) - grow, 0)
    r_hi = np.minimum(np.array([b for _, b in extent]) + 1 + grow, shape)
    region = labels[tuple(slice(int(a), int(b)) for a, b in zip(r_lo, r_hi, strict=True))]
    femur = region == value
    mask = femur
    if dilate_voxels > 0:
        other = (region > 0) & ~femur
        mask = ndimage.binary_dilation(femur, iterations=dilate_voxels) & ~other
    idx = np.argwhere(mask) + r_lo
    lo = np.maximum(idx.min(0) - 1, 0)
    hi = np.minimum(idx.max(0) + 2, shape)
    local = tuple(slice(int(a - r), int(b - r)) for a, b, r in zip(lo, hi, r_lo, strict=True))
    return np.ascontiguousarray(mask[local]), tuple(
        slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True)
    )


@dataclass(frozen=True, eq=False)
class _BoxMask:
    """A whole-volume bool mask that is False outside ``box``, held as ``mask`` (its values in
    ``box``); indexing it by a box of slices gives the whole mask's values there."""

    mask: np.ndarray
    box: tuple[slice, ...]

    def __getitem__(self, region: tuple[slice, ...]) -> np.ndarray:
        """The mask in ``region`` (slices with start and stop inside the volume)."""
        starts = [int(r.start) for r in region]
        out = np.zeros([int(r.stop) - a for r, a in zip(region, starts, strict=True)], dtype=bool)
        lo = [max(a, int(b.start)) for a, b in zip(starts, self.box, strict=True)]
        hi = [min(int(r.stop), int(b.stop)) for r, b in zip(region, self.box, strict=True)]
        if all(b > a for a, b in zip(lo, hi, strict=True)):
            dst = tuple(slice(a - s, b - s) for a, b, s in zip(lo, hi, starts, strict=True))
            src = tuple(
                slice(a - int(m.start), b - int(m.start)) for a, b, m in zip(lo, hi, self.box, strict=True)
            )
            out[dst] = self.mask[src]
        return out


class _XrayHelpers(XraySimulator):
    """XraySimulator's CM, drilling, label and physics helpers without its whole-CT renderers.

    The drilled path is sampled from ``hu`` (in the frame of ``volume``'s grid) with the voxels of
    ``filled`` read as :data:`FILLER_HU` (all of them where ``filled`` is True): the bodies' CTs
    without a copy of the patient's.
    """

    def __init__(
        self,
        volume: Volume,
        hu: np.ndarray,
        config: SimulationConfig,
        device: torch.device,
        *,
        filled: np.ndarray | _BoxMask | bool = False,
    ) -> None:
        # deliberately not calling super().__init__: it decomposes and uploads the whole CT
        self.volume = volume
        self.config = config
        self.device = device
        self._hu = hu
        self._filled = filled
        self._renderers = {}

    def _hu_box(self, box: tuple[slice, ...]) -> np.ndarray:
        """The body's HU in ``box``: the CT's, :data:`FILLER_HU` on the filled voxels."""
        hu = np.asarray(self._hu[box])
        if isinstance(self._filled, bool):
            return np.full_like(hu, FILLER_HU) if self._filled else hu
        return np.where(self._filled[box], np.float32(FILLER_HU), hu)


def _body_renderers(
    parts: dict[str, np.ndarray], world_from_index: np.ndarray, device: torch.device
) -> dict[str, CTRenderer]:
    """One renderer per non-zero material of a body; each skips its own empty space (the femur's
    volumes are zero outside its mask, the rest's outside the body)."""
    return {
        m: CTRenderer.from_tensor(
            torch.from_numpy(np.ascontiguousarray(parts[m], dtype=np.float32)).to(device),
            world_from_index,
            mipmap=False,
            skip_empty=True,
        )
        for m in RENDERED_CT_MATERIALS
        if parts[m].any()
    }


def _rest_densities(hu: np.ndarray, crop_mask: np.ndarray, box: tuple[slice, ...]) -> dict[str, np.ndarray]:
    """The ``rest`` body's material densities: the CT's with the femur's voxels (``crop_mask`` in
    ``box``) filled with :data:`FILLER_HU`'s, set in place (no filled copy of a fine patient's CT)."""
    rest = decompose_hu(hu, RENDERED_CT_MATERIALS)
    filler = decompose_hu(np.array([FILLER_HU], dtype=np.float32), RENDERED_CT_MATERIALS)
    for m, density in rest.items():
        density[box][crop_mask] = filler[m][0]
    return rest


def _quantised_rest_renderers(
    hu: np.ndarray, crop_mask: np.ndarray, box: tuple[slice, ...], world_from_index: np.ndarray
) -> dict[str, CTRenderer]:
    """:func:`_rest_densities`' renderers on the CPU with uint16 volumes (half the float32 ones'
    memory), built slab by slab so that no float32 volume of the CT's size exists.

    One step serves the three materials: every partial density lies in [0, ρ(HU)] and ρ
    (:func:`~fluoronav.simulation.materials.hu_to_density`) is non-decreasing, so ρ of the highest HU
    (or of the filler) bounds them all without clipping, known before any voxel is decomposed
    (a per-material maximum would cost a second pass); the error is at most half a step per sample.
    """
    top_hu = max(float(np.max(hu)), FILLER_HU)
    scale = float(hu_to_density(np.array([top_hu]))[0]) / QUANTISED_LEVELS
    filler = decompose_hu(np.array([FILLER_HU], dtype=np.float32), RENDERED_CT_MATERIALS)
    q = {m: np.empty(hu.shape, dtype=np.uint16) for m in RENDERED_CT_MATERIALS}
    nz = hu.shape[0]
    step = max(DECOMPOSE_CHUNK_VOXELS // max(hu[0].size, 1), 1)
    for z0 in range(0, nz, step):
        z1 = min(z0 + step, nz)
        parts = decompose_hu(hu[z0:z1], RENDERED_CT_MATERIALS)
        b0, b1 = max(z0, box[0].start), min(z1, box[0].stop)  # the femur's slices in this slab
        for m, density in parts.items():
            if b1 > b0:
                femur = crop_mask[b0 - box[0].start : b1 - box[0].start]
                density[b0 - z0 : b1 - z0, box[1], box[2]][femur] = filler[m][0]
            quantise_uint16(density, scale, out=q[m][z0:z1])
    return {
        m: CTRenderer.from_tensor(
            torch.from_numpy(q[m]), world_from_index, mipmap=False, skip_empty=True, scale=scale
        )
        for m in RENDERED_CT_MATERIALS
        if q[m].any()
    }


class ArticulatedSimulator:
    """Realistic X-ray images of a CT whose patient and femur move independently (CPU or CUDA).

    Args:
        volume: labelled CT in HU (labels ``femur_left`` / ``femur_right``).
        femur_side: which femur moves on its own.
        config: simulation settings (``image_size`` is overridden per call by ``simulate``).
        device: torch device for rendering and physics.
        quantise: on the CPU, store the ``rest`` body's densities as uint16
            (:func:`~fluoronav.rendering.ct.quantise_uint16`; half the float32 volumes' memory, for
            a fine patient); its images change by the quantisation, at most half a step (the
            density of the CT's highest HU over 65535) per sample. Ignored on CUDA (float32 there).
    """

    def __init__(
        self,
        volume: Volume,
        *,
        femur_side: str = "left",
        config: SimulationConfig | None = None,
        device: str | torch.device = "cpu",
        quantise: bool = False,
    ) -> None:
        self.volume = volume
        self.femur_side = femur_side
        self.config = config or SimulationConfig()
        self.device = resolve_device(device)
        crop_mask, box = femur_in_box(volume, femur_side)
        hu = np.asarray(volume.data, dtype=np.float32)
        self.rest_world_from_index = np.asarray(volume.world_from_index, dtype=np.float64)
        if quantise and self.device.type == "cpu":
            self._rest = _quantised_rest_renderers(hu, crop_mask, box, self.rest_world_from_index)
        else:
            rest = _rest_densities(hu, crop_mask, box)
            self._rest = _body_renderers(rest, self.rest_world_from_index, self.device)
        # femur body: own densities minus the filler's, on the mask, cropped to the box
        crop_hu = hu[box]
        own = decompose_hu(crop_hu, RENDERED_CT_MATERIALS)
        filler = decompose_hu(np.array([FILLER_HU], dtype=np.float32), RENDERED_CT_MATERIALS)
        delta = {m: np.where(crop_mask, own[m] - filler[m][0], 0.0).astype(np.float32) for m in own}
        offset = np.eye(4)
        offset[:3, 3] = [box[2].start, box[1].start, box[0].start]
        self.femur_world_from_index = self.rest_world_from_index @ offset
        self._femur = _body_renderers(delta, self.femur_world_from_index, self.device)
        # drilling samplers (see the module docstring): rest CT in the patient frame; the femur's
        # CT (filler outside its mask) and the filler alone in the femur frame, subtracted
        # (both cropped to the box: outside it they sample the same air and cancel)
        box_volume = volume.replace(
            data=crop_hu, labels=None, origin_mm=tuple(self.femur_world_from_index[:3, 3])
        )
        filled = _BoxMask(crop_mask, box)  # the femur's voxels, held in its box only
        self._drill_rest = _XrayHelpers(volume, hu, self.config, self.device, filled=filled)
        self._drill_femur = _XrayHelpers(box_volume, crop_hu, self.config, self.device, filled=~crop_mask)
        self._drill_filler = _XrayHelpers(box_volume, crop_hu, self.config, self.device, filled=True)
        log.debug("articulated split: femur box %s, %d femur voxels", box, int(crop_mask.sum()))

    # ----- geometry ------------------------------------------------------------------------
    def stored_camera(self, camera: Camera, image_size: int | None = None) -> Camera:
        """The stored-image camera: ``camera`` (full detector) resampled to ``image_size`` squared."""
        n = int(image_size or self.config.image_size)
        return camera.scaled_to(n, n)

    @staticmethod
    def _scene(
        camera: Camera,
        cm: tuple[np.ndarray, np.ndarray] | None,
        cm_config: CMConfig,
        built_cm: BuiltCM | None = None,
    ) -> Scene:
        if cm is None:
            if built_cm is not None:
                raise ValueError("built_cm needs a CM pose and shape (cm)")
            return Scene(
                camera=camera,
                world_from_cm=np.eye(4),
                control_points_deg=np.zeros(5),
                has_cm=False,
                cm_config=cm_config,
            )
        world_from_cm, cp = cm
        return Scene(
            camera=camera,
            world_from_cm=np.asarray(world_from_cm, np.float64),
            control_points_deg=np.asarray(cp, np.float64),
            cm_config=cm_config,
            built_cm=built_cm,
        )

    # ----- images --------------------------------------------------------------------------
    def areal_densities(
        self,
        camera: Camera,
        *,
        world_from_patient: np.ndarray,
        world_from_femur: np.ndarray,
        cm: tuple[np.ndarray, np.ndarray] | None = None,
        stored: Camera | None = None,
        cm_config: CMConfig | None = None,
        built_cm: BuiltCM | None = None,
    ) -> dict[str, torch.Tensor]:
        """Per-material areal densities (g/cm², (H, W) tensors) at ``stored`` (default: ``camera``).

        Args:
            camera: full-detector camera (world frame).
            world_from_patient: (4, 4) motion of the whole patient.
            world_from_femur: (4, 4) total motion of the femur.
            cm: ``(world_from_cm (4, 4), control_points_deg (5,))`` or None for no CM.
            stored: camera of the stored image (same view, possibly binned).
            cm_config: CM geometry (default :class:`CMConfig`).
            built_cm: the instrument as built (:func:`~fluoronav.simulation.instrument.build_instrument`),
                drawn at ``cm``'s pose with its own notches and joint angles for ``cm``'s control
                points; None: the model ``cm_config`` itself.
        """
        stored = stored or camera
        cm_config = cm_config or CMConfig()
        wp = np.asarray(world_from_patient, np.float64)
        wf = np.asarray(world_from_femur, np.float64)
        K = stored.K[None]
        dens: dict[str, torch.Tensor] = {}
        for body, w_body in ((self._rest, wp), (self._femur, wf)):
            T = (stored.camera_from_world @ w_body)[None]
            for m, renderer in body.items():
                img = renderer.render_poses(K, T, stored.rows, stored.cols)[0]
                dens[m] = dens[m] + img if m in dens else img
        dens = {m: v.clamp_min(0.0) for m, v in dens.items()}
        scene = self._scene(camera, cm, cm_config, built_cm)
        if scene.has_cm:
            helper = self._drill_rest
            if self.config.drill:
                removed: dict[str, torch.Tensor] = {}
                for sampler, w_body, sign in (
                    (self._drill_rest, wp, 1.0),
                    (self._drill_femur, wf, 1.0),
                    (self._drill_filler, wf, -1.0),
                ):
                    body_scene = self._scene(
                        camera,
                        (np.linalg.inv(w_body) @ scene.world_from_cm, scene.control_points_deg),
                        cm_config,
                        built_cm,
                    )
                    body_cam = stored.with_pose(stored.camera_from_world @ w_body)
                    for m, r in sampler._drilled_densities(body_scene, body_cam).items():
                        removed[m] = removed[m] + sign * r if m in removed else sign * r
                for m, r in removed.items():
                    if m in dens:
                        dens[m] = (dens[m] - r.clamp_min(0.0)).clamp_min(0.0)
            occ_mm = helper._cm_integral(scene, stored)
            for m, rho in helper._cm_material_densities(cm_config).items():
                dens[m] = dens.get(m, torch.zeros_like(occ_mm)) + rho * occ_mm
        return {m: v / MM_PER_CM for m, v in dens.items()}

    def simulate(
        self,
        camera: Camera,
        *,
        world_from_patient: np.ndarray,
        world_from_femur: np.ndarray,
        cm: tuple[np.ndarray, np.ndarray] | None = None,
        seed: int,
        image_size: int | None = None,
        cm_config: CMConfig | None = None,
        built_cm: BuiltCM | None = None,
        vary: VaryImage | None = None,
    ) -> SimulatedImage:
        """A realistic image (reproducible for a seed) with its CM labels.

        Args:
            camera: full-detector camera (e.g. 1536² CIOS Fusion) in the world frame.
            world_from_patient, world_from_femur: (4, 4) body motions (see the module docstring).
            cm: ``(world_from_cm (4, 4), control_points_deg (5,))`` or None.
            seed: noise seed.
            image_size: stored rows = cols (default ``config.image_size``).
            cm_config: CM geometry (default :class:`CMConfig`).
            built_cm: the instrument as built, drawn and labelled (mask, landmarks) instead of the
                model (see :meth:`areal_densities`); None: the model.
            vary: decides the sample's :class:`~fluoronav.simulation.xray.ImageVariation` from its
                stored camera and landmarks; None: none.

        Returns:
            :class:`SimulatedImage` whose ``scene`` holds the full camera, the CM pose and
            ``built_cm``.
        """
        cm_config = cm_config or CMConfig()
        stored = self.stored_camera(camera, image_size)
        dens = self.areal_densities(
            camera,
            world_from_patient=world_from_patient,
            world_from_femur=world_from_femur,
            cm=cm,
            stored=stored,
            cm_config=cm_config,
            built_cm=built_cm,
        )
        scene = self._scene(camera, cm, cm_config, built_cm)
        mask, lm = self._drill_rest.labels(scene, stored)
        variation = vary(stored, lm) if vary is not None else None
        image = imaged(dens, self.config.physics, variation, pixel_scale=camera.cols / stored.cols, seed=seed)
        return SimulatedImage(image=image, mask=mask, landmarks_px=lm, camera=stored, scene=scene)


@functools.lru_cache(maxsize=2)
def anatomy_and_simulator(
    ct: str, phantom_seed: int, image_size: int, device: str
) -> tuple[Volume, ArticulatedSimulator]:
    """The CT (``"phantom"`` or a path, :func:`~fluoronav.anatomy.io.resolve_ct`) and a physics
    simulator that moves its left femur, at ``image_size``² (cached per process)."""
    volume = resolve_ct(ct, seed=phantom_seed)
    sim = ArticulatedSimulator(
        volume, femur_side="left", config=SimulationConfig(image_size=image_size), device=device
    )
    return volume, sim
