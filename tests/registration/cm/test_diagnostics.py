"""CM registration diagnostics: they pass the true pose and flag broken registrations.

Physics-simulated images (XraySimulator, 384², noise-free, three views); the "registration" is the
registration's own machinery held at a given pose (one generation of a vanishing step), so that the
diagnostics see exactly the ROI and DRR a converged registration at that pose would leave.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fluoronav.registration.centerline import mirror_about_chord
from fluoronav.registration.cm import CMRegistrationConfig, CMView, register_cm
from fluoronav.registration.cm.checks import CMCheckConfig, judge_cm_views
from fluoronav.registration.cm.diagnostics import cm_view_diagnostics, edge_ncc
from fluoronav.registration.levels import CM_SIGMA, LevelConfig
from fluoronav.simulation.cm_case import cm_case_from_simulation, simulate_cm_case

HOLD = CMRegistrationConfig(
    levels=(
        LevelConfig(sigma=tuple(1e-9 for _ in CM_SIGMA), downsample=4, stride=5, popsize=4, max_iters=1),
    ),
    response="linear",
)


@pytest.fixture(scope="module")
def cases():
    kw = dict(image_size=384, photons_per_pixel=None, rotation_deg=5.0, translation_mm=5.0)
    return tuple(cm_case_from_simulation(simulate_cm_case("multi-view", seed=s, **kw)) for s in (4, 5))


def _at(views: list[CMView], W: np.ndarray, cp: np.ndarray) -> list[dict]:
    r = register_cm(views, initial_world_from_cm=W, initial_control_points_deg=cp, config=HOLD)
    diags = cm_view_diagnostics(
        r, [v.landmarks_px for v in views], [v.camera.pixel_spacing_mm for v in views]
    )
    return [d.to_dict() for d in diags]


def _judge(views: list[CMView], diags: list[dict]) -> list[bool]:
    return [v.passed for v in judge_cm_views([v.name for v in views], diags, CMCheckConfig())]


def test_the_true_pose_passes_every_check(cases) -> None:
    case, _ = cases
    d = _at(case.views, case.world_from_cm_true[0], case.control_points_true_deg)
    # landmarks: the case's are the truth + U(−3, 3) full-detector px (≤ 0.82 mm apart)
    assert all(v["landmark_residual_mm"] < 0.85 for v in d)
    assert all(v["edge_ncc"] > 0.9 for v in d)
    assert _judge(case.views, d) == [True, True, True]


@pytest.mark.parametrize("shift_cm", [(3.0, 0.0, 0.0), (0.0, 0.0, 5.0)])
def test_a_shifted_pose_fails_in_every_view(cases, shift_cm) -> None:
    case, _ = cases
    W = case.world_from_cm_true[0].copy()
    W[:3, 3] += W[:3, :3] @ np.asarray(shift_cm)
    d = _at(case.views, W, case.control_points_true_deg)
    assert all(v["landmark_residual_mm"] > 3.0 for v in d)
    assert all(v["edge_ncc"] < 0.3 for v in d)
    assert _judge(case.views, d) == [False, False, False]


def test_the_mirrored_cm_keeps_its_landmarks_but_fails_on_its_outline(cases) -> None:
    case, _ = cases
    cp = case.control_points_true_deg  # bent by up to 4°: the mirror image is another outline
    d = _at(case.views, mirror_about_chord(case.world_from_cm_true[0], cp, None), cp)
    assert all(v["landmark_residual_mm"] < 0.85 for v in d)
    assert all(v["edge_ncc"] < 0.5 for v in d)
    assert _judge(case.views, d) == [False, False, False]


def test_a_wrong_view_image_fails_in_that_view_only(cases) -> None:
    case, other = cases
    views = list(case.views)
    views[1] = replace(views[1], image=other.views[1].image, landmarks_px=other.views[1].landmarks_px)
    d = _at(views, case.world_from_cm_true[0], case.control_points_true_deg)
    assert d[1]["edge_ncc"] < 0.3 and d[1]["landmark_residual_mm"] > 3.0
    assert _judge(views, d) == [True, False, True]


def test_edge_ncc_of_an_image_with_itself_and_without_edges() -> None:
    rng = np.random.default_rng(0)
    drr = np.zeros((40, 50))
    drr[15:25, 10:40] = 1.0
    assert edge_ncc(drr + 0.01 * rng.standard_normal(drr.shape), drr) > 0.95
    assert edge_ncc(np.roll(drr, 8, axis=0), drr) < 0.2
    assert edge_ncc(rng.random((40, 50)), np.zeros((40, 50))) == 0.0
