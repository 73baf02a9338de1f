"""The simulated world reaches the simulated navigation's case (``SimulatedNavigationConfig.world``):
each source changes what it should of the case the pipeline sees and of the truth it is measured
against, and the ideal world is today's case (the sources themselves: tests/simulation)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.simulation.instrument import InstrumentWorld
from fluoronav.simulation.navigation.loop import SimulatedNavigationConfig, run_simulated_navigation
from fluoronav.simulation.world import IDEAL, CArmWorld, FBGWorld, MotionWorld, World

SMALL = SimulatedNavigationConfig(seed=21, image_size=128, orbit_deg=(20.0,), oracle_landmarks=True)


def _case(world: World):  # type: ignore[no-untyped-def]
    return run_simulated_navigation(dataclasses.replace(SMALL, world=world), until="case")


@pytest.fixture(scope="module")
def ideal():  # type: ignore[no-untyped-def]
    return _case(IDEAL)


def test_the_ideal_world_is_the_default_case_and_images_come_from_its_ct(ideal) -> None:  # type: ignore[no-untyped-def]
    default = run_simulated_navigation(SMALL, until="case")
    a, b = ideal.artifacts["case"], default.artifacts["case"]
    assert all(np.array_equal(u.image, v.image) for u, v in zip(a.views, b.views, strict=True))
    assert ideal.truth == default.truth
    # the case's cameras are the images' cameras (the world's ideal C-arm)
    for view, im in zip(a.views, ideal.artifacts["images"], strict=True):
        np.testing.assert_array_equal(view.camera.K, im.camera.K)


def test_the_c_arm_source_gives_the_case_other_intrinsics_than_the_images(ideal) -> None:  # type: ignore[no-untyped-def]
    run = _case(World(name="carm", carm=CArmWorld(sdd_error_sd_frac=0.01, principal_point_error_sd_px=6.0)))
    for view, im, ref in zip(
        run.artifacts["case"].views, run.artifacts["images"], ideal.artifacts["images"], strict=True
    ):
        np.testing.assert_array_equal(im.image, ref.image)  # the images are the ideal world's
        ratio = view.camera.K[0, 0] / im.camera.K[0, 0]
        assert ratio != 1.0 and abs(ratio - 1.0) < 0.05
        shift_px = np.linalg.norm(view.camera.K[:2, 2] - im.camera.K[:2, 2])
        assert 0.0 < shift_px < 6.0 * 5 / (1536 / 128)  # full-detector px binned to 128²


def test_the_fbg_source_reads_the_true_shape_with_its_noise(ideal) -> None:  # type: ignore[no-untyped-def]
    run = _case(World(name="fbg", fbg=FBGWorld(noise_sd_deg=0.0, bias_deg=0.3)))
    truth = np.asarray(run.truth["control_points_deg"])
    reading = run.artifacts["case"].fbg_control_points_deg
    np.testing.assert_allclose(np.abs(reading - truth), 0.3, atol=1e-12)  # the bias alone
    assert not np.allclose(ideal.artifacts["case"].fbg_control_points_deg, reading)
    # the case states the reading's accuracy: honest by default, or what the world says it claims
    assert run.artifacts["case"].fbg_sigma_deg == pytest.approx(0.3)
    assert ideal.artifacts["case"].fbg_sigma_deg is None
    liar = _case(World(name="liar", fbg=FBGWorld(noise_sd_deg=1.5, stated_sigma_deg=0.085)))
    assert liar.artifacts["case"].fbg_sigma_deg == 0.085


def test_the_fbg_reads_the_instrument_as_built(ideal) -> None:  # type: ignore[no-untyped-def]
    """An FBG senses the strain of the instrument it is in: with the instrument as built its reading
    is of that shape (the model's nearest to it), not of the commanded control points; the ideal
    reading's error is kept about it."""
    instrument = dataclasses.replace(InstrumentWorld.realistic(), angle_scale_sd=0.3)
    run = _case(World(name="instrument", instrument=instrument))
    truth = np.asarray(run.truth["control_points_deg"])
    reading = np.asarray(run.artifacts["case"].fbg_control_points_deg)
    ideal_error = np.asarray(ideal.artifacts["case"].fbg_control_points_deg) - truth
    built_offset = reading - truth - ideal_error
    assert np.abs(built_offset).max() > 0.05  # the built shape is not the commanded one
    # a notch-angle scale of 30 % moves a control point by about that fraction of its angle
    assert np.abs(built_offset).max() < 0.3 * np.abs(truth).max() * 3 + 1.0


def test_a_flexed_c_arm_gives_the_case_the_nominal_cameras(ideal) -> None:  # type: ignore[no-untyped-def]
    """The flex moves the image; the case keeps the nominal (calibrated) geometry, not the image's."""
    run = _case(World(name="flex", carm=CArmWorld(flex_detector_shift_mm=2.0)))
    for view, im, ref in zip(
        run.artifacts["case"].views, run.artifacts["images"], ideal.artifacts["images"], strict=True
    ):
        np.testing.assert_array_equal(view.camera.K, ref.camera.K)  # the nominal camera
        assert not np.array_equal(view.camera.K, im.camera.K)  # not the flexed one


def test_the_instrument_source_moves_the_true_tip_and_the_images(ideal) -> None:  # type: ignore[no-untyped-def]
    instrument = dataclasses.replace(InstrumentWorld.realistic(), angle_scale_sd=0.3)
    run = _case(World(name="instrument", instrument=instrument))
    cp = torch.as_tensor(run.truth["control_points_deg"], dtype=torch.float64)
    ct_from_cm = np.asarray(run.truth["ct_from_cm"])
    model_tip = ct_from_cm[:3, :3] @ CMKinematics().tip_cm(cp).numpy() + ct_from_cm[:3, 3]
    assert np.linalg.norm(np.asarray(run.truth["tip_ct_mm"]) - model_tip) > 0.05
    assert ideal.truth["ct_from_cm"] == run.truth["ct_from_cm"]  # the same pose, another CM
    assert not np.array_equal(run.artifacts["images"][0].image, ideal.artifacts["images"][0].image)


def test_motion_within_a_set_moves_the_anatomy_of_each_view(ideal) -> None:  # type: ignore[no-untyped-def]
    run = _case(World(name="motion", motion=MotionWorld(within_set_mm=3.0, within_set_deg=1.0)))
    for im, ref in zip(run.artifacts["images"], ideal.artifacts["images"], strict=True):
        d = np.abs(np.asarray(im.image) - np.asarray(ref.image))
        assert d.mean() > 1e-3
    assert ideal.truth == run.truth  # the truth is the set's reference pose
