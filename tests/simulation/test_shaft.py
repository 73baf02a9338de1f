"""The CM's mounting shaft in the simulator: analytic tube chords and where the shaft shows."""

from __future__ import annotations

import numpy as np
import torch

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.simulation.scene import sample_scene
from fluoronav.simulation.xray import SimulationConfig, XraySimulator, tube_chord_mm


def test_tube_chord_matches_sampled_integration() -> None:
    rng = np.random.default_rng(0)
    origin = torch.tensor([7.0, -3.0, 40.0], dtype=torch.float64)
    # rays aimed at random points around the cylinder (some miss, some graze, some cross the ends)
    targets = np.column_stack([rng.uniform(-4, 4, 200), rng.uniform(-4, 4, 200), rng.uniform(-60, 5, 200)])
    d = targets - origin.numpy()
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = tube_chord_mm(origin, torch.as_tensor(d), 3.0, -54.0, -4.0).numpy()
    t = np.linspace(0.0, 200.0, 400_001)
    for k in range(0, 200, 7):
        p = origin.numpy()[None] + t[:, None] * d[k]
        inside = (p[:, 0] ** 2 + p[:, 1] ** 2 <= 9.0) & (p[:, 2] >= -54.0) & (p[:, 2] <= -4.0)
        assert abs(inside.sum() * (t[1] - t[0]) - got[k]) < 2e-3
    assert (got == 0).any() and (got > 0).any()


def test_shaft_image_is_the_binned_fine_chord_image() -> None:
    """The simulator's binned shaft image (one pass over sub-pixel rays) against the fine image of
    :func:`tube_chord_mm` over every sub-pixel of the detector, average-pooled."""
    vol = hip_phantom(seed=0, spacing_mm=3.0)
    cfg = SimulationConfig(image_size=96, cm_oversample=3, shaft_length_mm=50.0)
    sim = XraySimulator(vol, config=cfg)
    rng = np.random.default_rng(11)
    for _ in range(3):
        scene = sample_scene(vol, rng)
        camera = sim.stored_camera(scene)
        got = sim._shaft_integral(scene, camera).double()
        cm = scene.cm_config
        z1 = -float(cm.base_length_mm)
        z0 = z1 - cfg.shaft_length_mm
        f = cfg.cm_oversample
        fine = scene.camera.scaled_to(camera.rows * f, camera.cols * f)
        cm_from_camera = np.linalg.inv(fine.camera_from_world @ scene.world_from_cm)
        d = torch.as_tensor(fine.ray_directions_world().reshape(-1, 3) @ scene.world_from_cm[:3, :3])
        o = torch.as_tensor(cm_from_camera[:3, 3])
        chord = tube_chord_mm(o, d, cm.outer_diameter_mm / 2, z0, z1) - tube_chord_mm(
            o, d, cm.inner_diameter_mm / 2, z0, z1
        )
        expected = torch.nn.functional.avg_pool2d(chord.reshape(1, 1, fine.rows, fine.cols), f)[0, 0]
        assert float(expected.max()) > 1.0  # the shaft is in the view
        torch.testing.assert_close(got, expected, rtol=0.0, atol=1e-5)
