"""Per-view checks of a bone registration (:mod:`fluoronav.registration.bone.checks`) on small
physics images of the coarse phantom: a correct view passes, a mirrored one fails and is named."""

from __future__ import annotations

import numpy as np
import pytest

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.registration.bone import (
    BoneLevel,
    BoneRegistrationConfig,
    register_pelvis_per_view,
    views_from_images,
)
from fluoronav.registration.bone.checks import (
    BoneCheckConfig,
    bone_view_diagnostics,
    judge_bone_view,
    judge_pelvis_views,
    mirrored_view,
)
from fluoronav.registration.levels import LevelConfig
from fluoronav.simulation.articulated import ArticulatedSimulator
from fluoronav.simulation.physics import XrayPhysics
from fluoronav.simulation.protocol import sample_trial, simulate_trial_images
from fluoronav.simulation.xray import SimulationConfig

#: a light pelvis schedule (as tests/registration/bone/test_bone.py's)
QUICK = BoneRegistrationConfig(
    levels=(
        BoneLevel(
            LevelConfig(sigma=(3, 3, 3, 6, 6, 12), popsize=12, max_iters=40), image_px=64, voxel_mm=4.0
        ),
        BoneLevel(
            LevelConfig(sigma=(1, 1, 1, 2, 2, 4), popsize=10, max_iters=30), image_px=128, voxel_mm=2.0
        ),
    )
)
SIZE = 128


@pytest.fixture(scope="module")
def volume():
    return hip_phantom(seed=0, spacing_mm=2.0)


@pytest.fixture(scope="module")
def trial(volume):
    return sample_trial("multi-view", volume, np.random.default_rng(1))


@pytest.fixture(scope="module")
def views(volume, trial):
    cfg = SimulationConfig(physics=XrayPhysics(energy_bin_keV=3.0, photons_per_pixel=None))
    sim = ArticulatedSimulator(volume, config=cfg)
    return views_from_images(simulate_trial_images(trial, sim, seed=0, image_size=SIZE))


def _pelvis(views, volume, trial):
    return register_pelvis_per_view(
        views, volume, initial_world_from_patient=trial.initial_world_from_patient, config=QUICK, seed=3
    )


def test_a_correct_view_passes_and_its_mirror_fails(volume, trial, views):
    cfg = BoneCheckConfig()
    view = views[1]
    flipped = mirrored_view(view)
    np.testing.assert_array_equal(flipped.image[:, ::-1], view.image)
    for v, passes in ((view, True), (flipped, False)):
        (res,) = _pelvis([v], volume, trial)
        (d,) = bone_view_diagnostics([v], volume, "pelvis", res.camera_from_bone, cfg)
        verdict = judge_bone_view(
            "v", "pelvis", d, min_edge_ncc=cfg.min_edge_ncc, min_grad_ncc=cfg.min_grad_ncc
        )
        assert verdict.passed is passes, (d, verdict)
    # the truth's pose passes too: the check is about the image, not the optimiser
    (d,) = bone_view_diagnostics(
        [view], volume, "pelvis", (view.camera.camera_from_world @ trial.world_from_patient)[None], cfg
    )
    assert judge_bone_view(
        "v", "pelvis", d, min_edge_ncc=cfg.min_edge_ncc, min_grad_ncc=cfg.min_grad_ncc
    ).passed


def test_a_mirrored_view_is_left_out_and_named(volume, trial, views):
    cfg = BoneCheckConfig()
    given = [views[0], mirrored_view(views[1]), views[2]]
    names = ["AP", "orbit +20", "orbit -15"]
    pelvis = _pelvis(given, volume, trial)
    record: dict = {}
    kept, left_out = judge_pelvis_views(
        given,
        volume,
        pelvis,
        names,
        cfg,
        initial_world_from_patient=trial.initial_world_from_patient,
        pelvis_config=QUICK,
        seed=3,
        record=record,
    )
    assert kept == [0, 2]
    assert left_out == {
        "orbit +20": "mirrored: view orbit +20 looks mirrored left–right: check the detector orientation"
    }
    assert record["orbit +20"]["check"] == "mirrored"
    assert record["orbit +20"]["mirrored_edge_ncc"] > record["orbit +20"]["edge_ncc"] + cfg.mirror_margin
    assert "check" not in record["AP"]
