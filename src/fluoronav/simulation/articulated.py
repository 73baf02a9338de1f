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

import numpy as np
import torch
from scipy import ndimage

from fluoronav.anatomy.io import resolve_ct
from fluoronav.anatomy.volume import Volume
from fluoronav.device import resolve_device
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.rendering.ct import CTRenderer
from fluoronav.simulation.instrument import BuiltCM
from fluoronav.simulation.materials import MM_PER_CM, decompose_hu
from fluoronav.simulation.scene import Scene
from fluoronav.simulation.xray import (
    RENDERED_CT_MATERIALS,
    SimulatedImage,
    SimulationConfig,
    VaryImage,
    XraySimulator,
    imaged,
)

__all__ = ["FILLER_HU", "ArticulatedSimulator", "split_femur"]

log = logging.getLogger(__name__)

#: HU of the soft tissue that fills the femur's place in the ``rest`` body
FILLER_HU = 40.0


def split_femur(volume: Volume, side: str, *, dilate_voxels: int = 1) -> tuple[np.ndarray, tuple[slice, ...]]:
    """The femur's voxel mask (nz, ny, nx) bool and its bounding box (slices, one voxel margin).

    Raises:
        ValueError: the volume has no labels or no ``femur_<side>`` label.
    """
    if volume.labels is None:
        raise ValueError("the articulated simulator needs a labelled CT")
    value = volume.label_value(f"femur_{side}")
    if value is None:
        raise ValueError(f"the CT has no label 'femur_{side}' (labels: {volume.label_names})")
    femur = volume.labels == value
    if not femur.any():
        raise ValueError(f"label 'femur_{side}' is empty")
    mask = femur
    if dilate_voxels > 0:
        other = (volume.labels > 0) & ~femur
        mask = ndimage.binary_dilation(femur, iterations=dilate_voxels) & ~other
    idx = np.argwhere(mask)
    lo = np.maximum(idx.min(0) - 1, 0)
    hi = np.minimum(idx.max(0) + 2, mask.shape)
    return mask, tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))


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
        filled: np.ndarray | bool = False,
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


def _rest_densities(hu: np.ndarray, mask: np.ndarray) -> dict[str, np.ndarray]:
    """The ``rest`` body's material densities: the CT's with the femur's voxels (``mask``) filled
    with :data:`FILLER_HU`'s, set in place (no filled copy of a fine patient's CT)."""
    rest = decompose_hu(hu, RENDERED_CT_MATERIALS)
    filler = decompose_hu(np.array([FILLER_HU], dtype=np.float32), RENDERED_CT_MATERIALS)
    for m, density in rest.items():
        np.putmask(density, mask, filler[m][0])
    return rest


class ArticulatedSimulator:
    """Realistic X-ray images of a CT whose patient and femur move independently (CPU or CUDA).

    Args:
        volume: labelled CT in HU (labels ``femur_left`` / ``femur_right``).
        femur_side: which femur moves on its own.
        config: simulation settings (``image_size`` is overridden per call by ``simulate``).
        device: torch device for rendering and physics.
    """

    def __init__(
        self,
        volume: Volume,
        *,
        femur_side: str = "left",
        config: SimulationConfig | None = None,
        device: str | torch.device = "cpu",
    ) -> None:
        self.volume = volume
        self.femur_side = femur_side
        self.config = config or SimulationConfig()
        self.device = resolve_device(device)
        mask, box = split_femur(volume, femur_side)
        hu = np.asarray(volume.data, dtype=np.float32)
        self.rest_world_from_index = np.asarray(volume.world_from_index, dtype=np.float64)
        self._rest = _body_renderers(_rest_densities(hu, mask), self.rest_world_from_index, self.device)
        # femur body: own densities minus the filler's, on the mask, cropped to the box
        crop_hu = hu[box]
        crop_mask = mask[box]
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
        self._drill_rest = _XrayHelpers(volume, hu, self.config, self.device, filled=mask)
        self._drill_femur = _XrayHelpers(box_volume, crop_hu, self.config, self.device, filled=~crop_mask)
        self._drill_filler = _XrayHelpers(box_volume, crop_hu, self.config, self.device, filled=True)
        log.debug("articulated split: femur box %s, %d femur voxels", box, int(mask.sum()))

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
