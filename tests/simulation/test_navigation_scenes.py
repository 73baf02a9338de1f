"""Navigation-like scenes: the plan's axis and depths, the navigation's views, the CM in the image."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.geometry import se3
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.simulation.navigation.scenario import SimulatedNavigationConfig
from fluoronav.simulation.navigation_scenes import (
    STAGES,
    NavigationScene,
    NavigationSceneSettings,
    sample_navigation_scene,
)
from fluoronav.simulation.robot_scene import cm_centre, working_view_centre


@pytest.fixture(scope="module")
def patient() -> Volume:
    return hip_phantom(seed=11, spacing_mm=2.0)


def _points_px(scene: NavigationScene) -> np.ndarray:
    """(3, 2) A, B and the tip projected by the scene's camera (full-detector pixels)."""
    cp = torch.as_tensor(scene.control_points_deg, dtype=torch.float64)
    kin = CMKinematics(scene.cm_config)
    pts = np.concatenate([kin.landmarks_cm(cp).numpy(), kin.tip_cm(cp).numpy()[None]])
    return scene.camera.project(se3.apply(scene.world_from_cm, pts))


def _centre_px(scene: NavigationScene) -> np.ndarray:
    return np.array([(scene.camera.cols - 1) / 2.0, (scene.camera.rows - 1) / 2.0])


def test_defaults_are_the_navigations() -> None:
    nav = SimulatedNavigationConfig()
    s = NavigationSceneSettings()
    assert s.orbit_deg == nav.orbit_deg and s.aim_error_mm == nav.aim_error_mm


@pytest.mark.parametrize("stage", ["approach", "inserted"])
def test_cm_on_the_plans_axis_at_its_depth(patient: Volume, stage: str) -> None:
    w = [float(s == stage) for s in STAGES]
    settings = NavigationSceneSettings(
        stage_weights=(w[0], w[1], w[2]), move_error_mm=0.0, move_error_deg=0.0, aim_error_mm=0.0
    )
    rng = np.random.default_rng(3)
    for _ in range(6):
        scene = sample_navigation_scene(patient, rng, settings=settings)
        assert scene.stage == stage
        tr = scene.trial
        entry = se3.apply(tr.world_from_femur, tr.entry_ct)
        head = se3.apply(tr.world_from_femur, tr.femoral_head_ct)
        axis = (head - entry) / np.linalg.norm(head - entry)
        kin = CMKinematics(scene.cm_config)
        tip = se3.apply(scene.world_from_cm, kin.tip_cm(torch.as_tensor(scene.control_points_deg)).numpy())
        depth = scene.insertion_depth_mm
        np.testing.assert_allclose(tip, entry + depth * axis, atol=1e-9)
        np.testing.assert_allclose(scene.world_from_cm[:3, 2], axis, atol=1e-12)
        lo, hi = settings.approach_mm if stage == "approach" else settings.inserted_mm
        assert lo <= abs(depth) <= hi and (depth < 0) == (stage == "approach")
        if scene.view == "AP":  # the verification AP centres the planned CM and the femoral head
            target = scene.world_from_cm.copy()
            target[:3, 3] += -depth * axis  # the planned pose (tip on the entry point)
            centre = 0.5 * (cm_centre(target) + head)
            np.testing.assert_allclose(scene.camera.project(centre[None])[0], _centre_px(scene), atol=1e-6)


def test_working_stage_is_the_first_images_view(patient: Volume) -> None:
    settings = NavigationSceneSettings(stage_weights=(1.0, 0.0, 0.0))
    rng = np.random.default_rng(5)
    views = set()
    for _ in range(8):
        scene = sample_navigation_scene(patient, rng, settings=settings)
        np.testing.assert_array_equal(scene.world_from_cm, scene.trial.world_from_cm[0])
        assert np.isnan(scene.insertion_depth_mm)
        views.add(scene.view)
        if scene.view == "AP":
            uv = scene.camera.project(working_view_centre(scene.trial)[None])[0]
            np.testing.assert_allclose(uv, _centre_px(scene), atol=1e-6)
    assert views <= {"AP", "orbit +20", "orbit -15"} and len(views) >= 2


def test_cm_in_the_image_unless_asked(patient: Volume) -> None:
    rng = np.random.default_rng(8)
    margin = NavigationSceneSettings().margin_px
    assert margin is not None
    for _ in range(12):
        uv = _points_px(sample_navigation_scene(patient, rng))
        assert np.all(uv >= margin) and np.all(uv <= 1535 - margin)
    far = NavigationSceneSettings(stage_weights=(0.0, 1.0, 0.0), approach_mm=(60.0, 90.0), margin_px=None)
    outside = [
        bool(np.any((uv < 0) | (uv > 1535)))
        for uv in (_points_px(sample_navigation_scene(patient, rng, settings=far)) for _ in range(12))
    ]
    assert any(outside)  # asked for: the CM may leave the image
    with pytest.raises(ValueError, match="margin_px"):
        sample_navigation_scene(
            patient,
            rng,
            settings=NavigationSceneSettings(stage_weights=(0.0, 1.0, 0.0), approach_mm=(300.0, 300.0)),
        )


def test_same_generator_state_same_scene(patient: Volume) -> None:
    a = sample_navigation_scene(patient, np.random.default_rng(21))
    b = sample_navigation_scene(patient, np.random.default_rng(21))
    assert (a.stage, a.view) == (b.stage, b.view)
    np.testing.assert_array_equal(a.world_from_cm, b.world_from_cm)
    np.testing.assert_array_equal(a.camera.camera_from_world, b.camera.camera_from_world)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"stage_weights": (0.0, 0.0, 0.0)},
        {"stage_weights": (1.0, -1.0, 1.0)},
        {"approach_mm": (10.0, 5.0)},
        {"inserted_mm": (-5.0, 5.0)},
        {"move_error_mm": -1.0},
        {"max_draws": 0},
    ],
)
def test_settings_are_checked(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        NavigationSceneSettings(**kwargs)
