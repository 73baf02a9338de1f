"""The instrument as built: the model when ideal, deviations of the configured size, its kinematics,
and its images and labels."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy import ndimage

from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.geometry import NotchGeometry, voxelize_cm, voxelize_cm_links
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.simulation.instrument import (
    BuiltCM,
    InstrumentWorld,
    build_instrument,
    built_joint_angles_deg,
    built_landmarks_cm,
    built_link_transforms,
    built_tip_cm,
    spline_fit_control_points_deg,
)

CONFIG = CMConfig()
CP = np.array([3.0, 2.0, 1.0, 0.0, -1.0])
SHAPES = torch.tensor(
    [[3.0, 2.0, 1.0, 0.0, -1.0], [7.9, -7.9, 5.0, 7.0, -3.0], [0.0] * 5], dtype=torch.float64
)


def _ideal(seed: int = 0) -> BuiltCM:
    return build_instrument(InstrumentWorld.ideal(), CONFIG, np.random.default_rng(seed))


def test_an_ideal_instrument_is_the_model() -> None:
    built = _ideal()
    kin = CMKinematics(CONFIG)
    assert built.config == CONFIG
    assert built.notches == NotchGeometry.nominal(CONFIG)
    assert torch.equal(built_joint_angles_deg(built, SHAPES), kin.joint_angles_deg(SHAPES))
    assert torch.equal(built_link_transforms(built, SHAPES), kin.link_transforms(SHAPES))
    torch.testing.assert_close(built_tip_cm(built, SHAPES), kin.tip_cm(SHAPES), rtol=0, atol=1e-12)
    torch.testing.assert_close(
        built_landmarks_cm(built, SHAPES), kin.landmarks_cm(SHAPES), rtol=0, atol=1e-12
    )
    torch.testing.assert_close(spline_fit_control_points_deg(built, SHAPES), SHAPES, rtol=0, atol=1e-9)


def test_deviations_have_the_configured_size() -> None:
    """400 instruments of 27 notches: per-notch standard deviations within 5 % (standard error
    ~0.5 %), per-instrument diameters within 15 % (standard error ~3.5 %), means near zero."""
    world = InstrumentWorld.realistic()
    rng = np.random.default_rng(1)
    built = [build_instrument(world, CONFIG, rng) for _ in range(400)]
    nominal = NotchGeometry.nominal(CONFIG)
    per_notch = {
        "angle_scale_sd": np.concatenate([b.angle_scale - 1.0 for b in built]),
        "angle_offset_sd_deg": np.concatenate([b.angle_offset_deg for b in built]),
        "notch_position_sd_mm": np.concatenate([np.subtract(b.notches.z_mm, nominal.z_mm) for b in built]),
        "notch_width_sd_mm": np.concatenate(
            [np.subtract(b.notches.width_mm, nominal.width_mm) for b in built]
        ),
        "notch_depth_sd_mm": np.concatenate(
            [np.subtract(b.notches.depth_mm, nominal.depth_mm) for b in built]
        ),
    }
    for name, dev in per_notch.items():
        sd = getattr(world, name)
        assert dev.std() == pytest.approx(sd, rel=0.05), name
        assert abs(dev.mean()) < 4 * sd / math.sqrt(dev.size), name
    od = np.array([b.config.outer_diameter_mm for b in built]) - CONFIG.outer_diameter_mm
    inner = np.array([b.config.inner_diameter_mm for b in built]) - CONFIG.inner_diameter_mm
    assert od.std() == pytest.approx(world.outer_diameter_sd_mm, rel=0.15)
    assert inner.std() == pytest.approx(world.inner_diameter_sd_mm, rel=0.15)
    # the angles are the spline's, scaled and offset per notch
    b = built[0]
    spline = CMKinematics(CONFIG).joint_angles_deg(torch.as_tensor(CP)).numpy()
    np.testing.assert_allclose(
        built_joint_angles_deg(b, CP).numpy(), spline * b.angle_scale + b.angle_offset_deg, rtol=0, atol=1e-12
    )
    assert np.abs(built_joint_angles_deg(b, CP).numpy() - spline).max() > 0.05


def test_one_notch_bent_by_delta_swings_the_tip_about_that_notch() -> None:
    """Straight CM, notch j bent by δ: the tip turns by δ about notch j's centre (on the axis), so it
    moves to (0, −ℓ sin δ, z_j + ℓ cos δ) with the lever arm ℓ = tip_z − z_j (≈ δ·ℓ sideways)."""
    j, delta_deg = 5, 1.0
    offset = np.zeros(CONFIG.n_notches)
    offset[j] = delta_deg
    built = replace(_ideal(), angle_offset_deg=offset)
    z_j = CONFIG.notch_z_mm(j)
    lever = CONFIG.tip_z_mm - z_j
    d = math.radians(delta_deg)
    tip = built_tip_cm(built, np.zeros(5)).numpy()
    np.testing.assert_allclose(tip, [0.0, -lever * math.sin(d), z_j + lever * math.cos(d)], atol=1e-12)
    assert np.linalg.norm(tip - [0.0, 0.0, CONFIG.tip_z_mm]) == pytest.approx(d * lever, rel=1e-4)
    b_lever = CONFIG.distal_notch_plane_mm - z_j
    B = built_landmarks_cm(built, np.zeros(5)).numpy()[1]
    np.testing.assert_allclose(B, [0.0, -b_lever * math.sin(d), z_j + b_lever * math.cos(d)], atol=1e-12)


def test_a_notch_cut_off_its_pitch_moves_its_joint_centre() -> None:
    """Notch j cut Δz further along: bending only at notch j (by δ) now turns about z_j + Δz."""
    j, dz, delta_deg = 10, 0.05, 2.0
    ideal = _ideal()
    z = list(ideal.notches.z_mm)
    z[j] += dz
    offset = np.zeros(CONFIG.n_notches)
    offset[j] = delta_deg
    built = replace(ideal, notches=replace(ideal.notches, z_mm=tuple(z)), angle_offset_deg=offset)
    lever = CONFIG.tip_z_mm - z[j]
    d = math.radians(delta_deg)
    tip = built_tip_cm(built, np.zeros(5)).numpy()
    np.testing.assert_allclose(tip, [0.0, -lever * math.sin(d), z[j] + lever * math.cos(d)], atol=1e-12)


def test_the_spline_fit_absorbs_a_uniform_stiffness_error() -> None:
    """Every notch 10 % more compliant: the spline through control points 10 % larger is exact."""
    built = replace(_ideal(), angle_scale=np.full(CONFIG.n_notches, 1.1))
    fit = spline_fit_control_points_deg(built, SHAPES)
    torch.testing.assert_close(fit, 1.1 * SHAPES, rtol=0, atol=1e-9)
    # a per-notch error is not a spline: the fit leaves a residual
    rough = build_instrument(InstrumentWorld.realistic(), CONFIG, np.random.default_rng(3))
    fit_angles = CMKinematics(CONFIG).joint_angles_deg(spline_fit_control_points_deg(rough, SHAPES))
    assert (fit_angles - built_joint_angles_deg(rough, SHAPES)).abs().amax() > 0.05


def test_voxelised_as_built_equals_the_model_for_nominal_notches() -> None:
    """The explicit-link voxeliser with the config's notches and the spline's links is the model's."""
    T = CMKinematics(CONFIG).link_transforms(torch.as_tensor(CP)).numpy()
    for region in ("solid", "notched"):
        ref = voxelize_cm(CONFIG, CP, spacing_mm=0.2, region=region)
        got = voxelize_cm_links(
            CONFIG, T, notches=NotchGeometry.nominal(CONFIG), spacing_mm=0.2, region=region
        )
        assert np.array_equal(got.occupancy, ref.occupancy)
        assert np.array_equal(got.world_from_index, ref.world_from_index)


def test_deeper_notches_remove_material() -> None:
    """Each notch 0.2 mm deeper than nominal: less nitinol, by about the extra slab volume."""
    nominal = NotchGeometry.nominal(CONFIG)
    deeper = replace(nominal, depth_mm=tuple(d + 0.2 for d in nominal.depth_mm))
    T = CMKinematics(CONFIG).link_transforms(torch.zeros(5, dtype=torch.float64)).numpy()
    ref = voxelize_cm_links(CONFIG, T, notches=nominal, spacing_mm=0.1)
    got = voxelize_cm_links(CONFIG, T, notches=deeper, spacing_mm=0.1)
    removed_mm3 = (ref.occupancy.sum() - got.occupancy.sum()) * 0.1**3
    # per notch: the tube wall's chord band between y = −1.5 and −1.3 (the cut level, side-relative)
    # over the notch width: 2 · ∫ (√(r_o² − y²) − √(r_i² − y²)) dy · width
    y = np.linspace(1.3, 1.5, 2001)
    band = np.trapezoid(2 * (np.sqrt(9.0 - y**2) - np.sqrt(4.0 - y**2)), y)
    expected = band * CONFIG.notch_width_mm * CONFIG.n_notches
    assert removed_mm3 == pytest.approx(expected, rel=0.1)


# ----- images ----------------------------------------------------------------------------------------
SIZE = 128


@pytest.fixture(scope="module")
def images():
    from fluoronav.anatomy.phantom import hip_phantom
    from fluoronav.geometry.carm import carm_camera
    from fluoronav.simulation.articulated import ArticulatedSimulator
    from fluoronav.simulation.physics import XrayPhysics
    from fluoronav.simulation.scene import cm_pose_along
    from fluoronav.simulation.xray import SimulationConfig

    vol = hip_phantom(seed=0, spacing_mm=4.0)
    cfg = SimulationConfig(physics=XrayPhysics(energy_bin_keV=3.0, photons_per_pixel=None), image_size=SIZE)
    head, entry = vol.landmarks_world["femoral_head_left"], vol.landmarks_world["entry_left"]
    axis = (head - entry) / np.linalg.norm(head - entry)
    world_from_cm = cm_pose_along(entry + 5.0 * axis, axis, 1.2)
    camera = carm_camera(isocenter_world=entry + 20.0 * axis, source_to_isocenter_mm=450.0)  # CM centred
    sim = ArticulatedSimulator(vol, config=cfg)
    bent = replace(_ideal(), angle_offset_deg=np.full(CONFIG.n_notches, 2.0))  # +54° over the CM

    def shot(built: BuiltCM | None):
        eye = np.eye(4)
        return sim.simulate(
            camera,
            world_from_patient=eye,
            world_from_femur=eye,
            cm=(world_from_cm, CP),
            seed=0,
            built_cm=built,
        )

    def densities(built: BuiltCM | None, with_cm: bool = True):
        eye = np.eye(4)
        return sim.areal_densities(
            camera,
            world_from_patient=eye,
            world_from_femur=eye,
            cm=(world_from_cm, CP) if with_cm else None,
            stored=sim.stored_camera(camera, SIZE),
            built_cm=built,
        )

    return {
        "model": shot(None),
        "ideal": shot(_ideal()),
        "bent": shot(bent),
        "built": bent,
        "densities": densities,
    }


def test_an_ideal_built_cm_draws_the_models_image(images) -> None:
    model, ideal = images["model"], images["ideal"]
    assert np.array_equal(ideal.image, model.image)
    assert model.mask.sum() > 20
    assert np.count_nonzero(ideal.mask != model.mask) <= 2  # analytic chords vs the renderer's, at edges
    np.testing.assert_allclose(ideal.landmarks_px, model.landmarks_px, atol=1e-9)


def test_a_built_cm_changes_the_image_only_around_the_cm_and_its_labels_follow_it(images) -> None:
    model, bent, built = images["model"], images["bent"], images["built"]
    diff = np.abs(bent.image - model.image)
    # the masks cover A–B only: 8 px (~9 mm at the CM) more hold the tip beyond B and the blur
    near = ndimage.binary_dilation((bent.mask > 0) | (model.mask > 0), iterations=8)
    assert diff[near].max() > 0.3  # the CM moved
    assert diff[~near].max() < 0.02 * diff[near].max()  # elsewhere only scatter changes
    # the labels are the built instrument's: B where its kinematics put it, far from the model's B
    camera, w = bent.camera, bent.scene.world_from_cm
    B = built_landmarks_cm(built, CP).numpy()[1]
    np.testing.assert_allclose(bent.landmarks_px[1], camera.project(B @ w[:3, :3].T + w[:3, 3]), atol=1e-9)
    assert np.linalg.norm(bent.landmarks_px[1] - model.landmarks_px[1]) > 5.0
    np.testing.assert_allclose(bent.landmarks_px[0], model.landmarks_px[0], atol=1e-9)
    assert np.count_nonzero(bent.mask != model.mask) > 20
    assert bent.scene.built_cm is built


def test_the_drilled_path_follows_the_built_instrument(images) -> None:
    """Where the model CM lies and the built one does not, the built scene's bone is intact."""
    model, bent = images["model"], images["bent"]
    none = images["densities"](None, with_cm=False)
    drilled_model = images["densities"](None)
    drilled_built = images["densities"](images["built"])
    only_model = (model.mask > 0) & ~ndimage.binary_dilation(bent.mask > 0, iterations=5)
    assert only_model.sum() > 5
    bone = "bone_cortical"
    hole = (none[bone] - drilled_model[bone]).numpy()[only_model]
    kept = (none[bone] - drilled_built[bone]).numpy()[only_model]
    assert hole.max() > 0.05  # g/cm²: the model's hole is there
    assert np.abs(kept).max() < 1e-3 * hole.max()
