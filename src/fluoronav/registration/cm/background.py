"""Static anatomy backgrounds for CM registration: the CT rendered once per view ROI.

In the study the pelvis/femur are registered first; the anatomy DRR at that pose is constant while
the CM is optimised, so it is rendered once per view and level (``CMView.background``) and the moving
image is ``background + CM DRR``. The units are the DRR's line integrals with ``μ = μ_water (1 +
HU/1000)``, μ_water = 0.02/mm, consistent with ``CMRegistrationConfig.cm_mu_per_mm``.
"""

from __future__ import annotations

import numpy as np
import torch

from fluoronav.anatomy.volume import MU_WATER_PER_MM, Volume
from fluoronav.geometry.camera import Camera
from fluoronav.rendering.ct import CTRenderer

__all__ = ["CTBackground"]


class CTBackground:
    """Callable ``roi_camera -> (h, w) float32`` DRR of a CT at a fixed pose.

    Args:
        volume_hu: CT in HU.
        world_from_volume: (4, 4) pose of the CT's physical frame in the workflow's world frame (the
            bone registration result; identity when the world is the CT frame).
        mu_water_per_mm: μ of water for the HU → μ conversion.
        device: rendering device.
    """

    def __init__(
        self,
        volume_hu: Volume,
        *,
        world_from_volume: np.ndarray | None = None,
        mu_water_per_mm: float = MU_WATER_PER_MM,
        device: str | torch.device = "cpu",
    ) -> None:
        self.renderer = CTRenderer.from_hu(volume_hu, mu_water_per_mm=mu_water_per_mm, device=device)
        self.world_from_volume = (
            np.eye(4) if world_from_volume is None else np.asarray(world_from_volume, np.float64)
        )

    def __call__(self, camera: Camera) -> np.ndarray:
        cam = camera.with_pose(camera.camera_from_world @ self.world_from_volume)
        return self.renderer.render_one(cam).float().cpu().numpy()
