"""The kernels compiled at install are the ones the pipeline calls: after ``compile_all`` a simulated
image and a similarity cost compile nothing more."""

from __future__ import annotations

import numpy as np
import torch

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.cli.compile_kernels import compile_all
from fluoronav.manipulator import geometry
from fluoronav.registration import _similarity_numba
from fluoronav.registration.similarity import PatchGradNCC
from fluoronav.rendering import _cm_numba, _ct_numba
from fluoronav.rendering.ct import CTRenderer
from fluoronav.simulation import _tube_numba
from fluoronav.simulation.scene import sample_scene
from fluoronav.simulation.xray import SimulationConfig, XraySimulator

KERNELS = {
    "march_rays": _ct_numba.march_rays,
    "render_links": _cm_numba.render_links,
    "voxelize_link": geometry._voxelize_link,
    "binned_tube_chords": _tube_numba.binned_tube_chords,
    "patch_grad_ncc_cost": _similarity_numba.patch_grad_ncc_cost,
}


def _signatures() -> dict[str, set]:
    return {name: set(k.signatures) for name, k in KERNELS.items()}


def test_compiled_kernels_cover_the_pipelines_calls() -> None:
    compile_all()
    before = _signatures()
    assert len(before["march_rays"]) >= 2 and all(before.values())
    # one simulated image: the CT with empty-space maps, the drilled path and the CM without them,
    # the voxeliser, the shaft's chords and the label mask (the CM renderer)
    vol = hip_phantom(seed=0, spacing_mm=4.0)
    sim = XraySimulator(vol, config=SimulationConfig(image_size=48))
    scene = sample_scene(vol, np.random.default_rng(3))
    image = sim.simulate(scene, seed=1)
    assert image.mask.any() and np.isfinite(image.image).all()
    # a bone renderer (empty-space skipping, mipmaps) and the similarity of its float32 images
    mu = CTRenderer.from_hu(vol)
    drr = mu.render([sim.stored_camera(scene)])
    moving = torch.stack([drr[0], drr[0].roll(2, dims=1)])
    cost = PatchGradNCC(drr[0], patch_radius=4, stride=3)(moving)
    assert cost.shape == (2,) and float(cost[0]) < float(cost[1])
    assert _signatures() == before
