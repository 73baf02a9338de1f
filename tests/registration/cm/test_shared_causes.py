"""Naming the input every view shares (:mod:`fluoronav.registration.cm.shared_causes`): the CM's
size measured from hand-projected landmarks, the scaled CM, and which refusal names what (the
registration itself stood in for; its checks: tests/registration/cm/test_checks.py)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
import torch

import fluoronav.registration.cm.shared_causes as shared_causes
from fluoronav.errors import RegistrationRefused
from fluoronav.geometry import se3
from fluoronav.geometry.carm import carm_camera, orbit_camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.registration.cm.checks import CMCheckConfig
from fluoronav.registration.cm.config import CMRegistrationConfig
from fluoronav.registration.cm.shared_causes import (
    RefusedCM,
    centreline_shape,
    landmark_scale,
    name_fbg_cause,
    name_scale_cause,
    name_shared_cause,
    scaled_cm_config,
)
from fluoronav.registration.cm.views import CMView


@dataclass
class _Reg:
    """A stand-in CM registration (what the naming reads of one)."""

    control_points_deg: np.ndarray = field(default_factory=lambda: np.zeros(5))
    world_from_cm: np.ndarray = field(default_factory=lambda: np.eye(4)[None])


def _views(scale: float, reading: np.ndarray) -> tuple[list[CMView], list[np.ndarray]]:
    """Three C-arm views (AP and orbits ±25° about z) of the CM's landmarks at ``scale`` times their
    size (about the CM's base), projected by hand: ``u ~ K (R X + t)``."""
    ab = CMKinematics(CMConfig()).landmarks_cm(torch.as_tensor(reading, dtype=torch.float64)).numpy()
    world_from_cm = se3.make(np.eye(3), [5.0, -3.0, 10.0])
    pts = se3.apply(world_from_cm, scale * ab)
    ap = carm_camera()
    cams = [ap] + [orbit_camera(ap, angle_deg=a, isocenter_world=np.zeros(3)) for a in (-25.0, 25.0)]
    views, lms = [], []
    for k, c in enumerate(cams):
        P = c.K @ c.camera_from_world[:3]
        h = (P @ np.c_[pts, np.ones(2)].T).T
        lms.append(h[:, :2] / h[:, 2:])
        views.append(CMView(np.zeros((8, 8), np.float32), c, landmarks_px=lms[-1], name=f"v{k}"))
    return views, lms


@pytest.mark.parametrize("scale", [0.9, 1.0, 1.1])
def test_the_cms_size_in_the_views_is_measured_from_its_landmarks(scale: float) -> None:
    reading = np.array([2.0, -1.0, 3.0, 0.5, -2.0])
    views, lms = _views(scale, reading)
    assert landmark_scale(views, lms, reading, CMConfig()) == pytest.approx(scale, abs=1e-6)
    # one view with landmarks cannot tell
    assert landmark_scale(views, [lms[0], None, None], reading, CMConfig()) is None


def test_the_scaled_cm_is_larger_in_every_length_with_the_same_line_integral() -> None:
    cm = CMConfig()
    big = scaled_cm_config(cm, 1.1)
    assert big.total_length_mm == pytest.approx(38.5) and big.notch_pitch_mm == pytest.approx(1.1)
    assert big.outer_diameter_mm == pytest.approx(6.6) and big.n_notches == cm.n_notches
    assert big.density_g_cm3 * 1.1 == pytest.approx(cm.density_g_cm3)
    assert big.max_bend_deg == pytest.approx(cm.max_bend_deg)  # a similar CM bends alike


def _patched(monkeypatch: pytest.MonkeyPatch, fits: dict[str, Any]) -> list[dict[str, Any]]:
    """The registration stood in for: it fits (giving the shape ``fits["shape"]``) where the
    setting it is run with is in ``fits`` (``"free_shape"``, ``"scaled"``), else refuses."""
    calls: list[dict[str, Any]] = []

    def registered(views: Any, lms: Any, tries: Any, diag: Any, **kw: Any) -> _Reg:
        cfg = kw["config"]
        kind = "scaled" if cfg.cm_config.total_length_mm != 35.0 else "free_shape"
        calls.append({"kind": kind, **kw})
        if kind not in fits:
            raise RegistrationRefused("cm", "edge_ncc", "still no fit", view="AP")
        return _Reg(control_points_deg=fits[kind])

    monkeypatch.setattr(shared_causes, "register_cm_checked", registered)
    return calls


_CFG = CMRegistrationConfig(control_point_sigma_deg=0.085, control_point_tolerance_deg=0.0)
_CHECKS = CMCheckConfig(max_shape_departure_sigmas=4.0)


def _refused(check: str = "edge_ncc") -> RegistrationRefused:
    return RegistrationRefused("cm", check, "NCC 0.54 (at least 0.7)", view="orbit +20")


def _failed(
    refused: RegistrationRefused, views: Any = (), lms: Any = (), reading: np.ndarray | None = None
) -> RefusedCM:
    reading = np.zeros(5) if reading is None else reading
    return RefusedCM(refused, views, lms, [], reading, _CFG, _CHECKS, 0)


def test_a_view_that_fails_because_the_fbg_reading_is_off_names_the_reading(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Held to a reading 1.5° off the CM fails a view; with the shape free it fits every view 1.5°
    (18 σ) from the reading: the refusal names the FBG reading and keeps the view's failure."""
    calls = _patched(monkeypatch, {"free_shape": np.array([0.0, 1.5, 0.0, 0.0, 0.0])})
    refused, rec = _refused(), {}
    out = name_fbg_cause(_failed(refused), rec)
    assert out is not refused and out.check == "fbg_reading" and out.view == ""
    assert "+1.50° at control point 1" in out.detail and "orbit +20" in out.detail
    assert calls[0]["config"].control_point_tolerance_deg == 6.0  # searched ±6° of the reading
    assert calls[0]["checks"].max_shape_departure_sigmas is None
    assert rec["fits"] and rec["departure_sigmas"] == pytest.approx(1.5 / 0.085)


def test_a_ct_whose_spacing_is_off_is_named_with_the_factor(monkeypatch: pytest.MonkeyPatch) -> None:
    """The CM's landmarks triangulate 10 % too far apart; at 1.1× its size it fits every view, with
    its shape held to the reading: ``ct_scale``, naming the factor; the FBG reading is tried first."""
    reading = np.zeros(5)
    views, lms = _views(1.1, reading)
    calls = _patched(monkeypatch, {"scaled": reading})
    rec: dict[str, Any] = {}
    out = name_shared_cause(_failed(_refused(), views, lms, reading), rec)
    assert out.check == "ct_scale" and "1.100×" in out.detail and "orbit +20" in out.detail
    assert [c["kind"] for c in calls] == ["free_shape", "scaled"]
    assert calls[1]["config"].cm_config.total_length_mm == pytest.approx(38.5)
    assert calls[1]["checks"].max_shape_departure_sigmas == 4.0  # the shape held to the reading
    assert rec["ct_scale"] == {"factor": pytest.approx(1.1), "fits": True}
    assert rec["fbg_reading"] == {"fits": False}


def test_a_cm_of_its_own_size_is_not_tested_as_the_cts_scale(monkeypatch: pytest.MonkeyPatch) -> None:
    reading = np.zeros(5)
    views, lms = _views(1.02, reading)  # within the 3 % the landmarks' error allows
    calls = _patched(monkeypatch, {"scaled": reading})
    refused = _refused()
    out = name_scale_cause(_failed(refused, views, lms, reading))
    assert out is refused and not calls


def test_where_no_shared_input_explains_it_the_views_refusal_stands_and_says_so(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    reading = np.zeros(5)
    views, lms = _views(1.1, reading)
    _patched(monkeypatch, {})  # nothing fits
    out = name_shared_cause(_failed(_refused(), views, lms, reading))
    assert out.check == "edge_ncc" and out.view == "orbit +20"
    assert "neither the FBG reading nor the CT's scale (the CM's size in the views 1.100×)" in out.detail
    # the free shape that agrees with the reading does not name it either
    _patched(monkeypatch, {"free_shape": np.full(5, 0.1)})
    near = name_fbg_cause(_failed(_refused()))
    assert near.check == "edge_ncc"


def test_a_failure_that_is_not_a_views_check_is_not_searched(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = _patched(monkeypatch, {"free_shape": np.full(5, 2.0), "scaled": np.zeros(5)})
    refused = _refused("robot_motion")
    out = name_shared_cause(_failed(refused))
    assert out is refused and not calls


def _scaled_scene(case: Any, factor: float) -> tuple[list[CMView], np.ndarray]:
    """The case's views with every camera's centre moved ``factor`` times as far from the CM's base
    (its images kept): the cameras a CT whose spacing reads ``factor`` times the true one registers;
    and the initial pose moved alike."""
    p = case.world_from_cm_true[0][:3, 3]
    views = []
    for v in case.views:
        T = np.asarray(v.camera.camera_from_world, np.float64)
        R, centre = T[:3, :3], -T[:3, :3].T @ T[:3, 3]
        moved = se3.make(R, -R @ (p + factor * (centre - p)))
        views.append(dataclasses.replace(v, camera=v.camera.with_pose(moved)))
    W0 = np.asarray(case.initial_world_from_cm, np.float64).copy()
    W0[:3, 3] = p + factor * (W0[:3, 3] - p)
    return views, W0


@pytest.mark.slow
def test_physics_images_of_a_scene_registered_in_a_scaled_ct_name_its_scale() -> None:
    """Three noise-free physics views of the CM (384²) with cameras placed as a CT 10 % too large
    places them: the CM of its own size fails a view; the shared causes name the CT's scale with the
    factor within 2 % (the landmarks are the true projections)."""
    from fluoronav.registration.cm.checks import register_cm_checked
    from fluoronav.registration.cm.config import default_cm_levels
    from fluoronav.simulation.cm_case import cm_case_from_simulation, simulate_cm_case

    case = cm_case_from_simulation(
        simulate_cm_case(
            "multi-view", seed=4, image_size=384, photons_per_pixel=None, rotation_deg=2.0, translation_mm=2.0
        )
    )
    views, W0 = _scaled_scene(case, 1.1)
    lms = [v.landmarks_px for v in views]
    reading = np.asarray(case.control_points_true_deg, np.float64)
    cfg = CMRegistrationConfig(levels=default_cm_levels(refine=False, popsize=30))
    checks = CMCheckConfig()
    kw: dict[str, Any] = dict(initial_control_points_deg=reading, config=cfg, checks=checks, seed=0)
    with pytest.raises(RegistrationRefused) as refused:
        register_cm_checked(views, lms, [[W0]], {}, **kw)
    assert refused.value.check in ("landmark_residual", "edge_ncc")
    rec: dict[str, Any] = {}
    failed = RefusedCM(refused.value, views, lms, [[W0]], reading, cfg, checks, 1)
    out = name_shared_cause(failed, rec)
    assert out.check == "ct_scale", out
    assert rec["ct_scale"]["factor"] == pytest.approx(1.1, abs=0.02)


def test_centreline_shape_finds_the_shape_the_centrelines_favour() -> None:
    """A centreline cost least at an offset of the reading (within the tolerance, on the half-step
    grid): the search finds that shape and returns its starts."""
    reading = np.array([1.0, -2.0, 4.0, 0.0, 3.0])
    offset = np.array([-3.0, -1.5, 2.0, 0.5, -2.5])

    def starts_for(shape: np.ndarray) -> tuple[list[list[np.ndarray]], float]:
        return [[np.full((4, 4), float(shape.sum()))]], float(np.sum((shape - reading - offset) ** 2))

    shape, tries = centreline_shape(starts_for, reading, 6.0, 1.0)
    np.testing.assert_allclose(shape, reading + offset, atol=1e-9)
    assert tries[0][0][0, 0] == pytest.approx((reading + offset).sum())
    # never past the tolerance: a minimum 8° off stops at 6°
    far, _ = centreline_shape(
        lambda s: ([[np.eye(4)]], float(np.sum((s - reading - 8.0) ** 2))), reading, 6.0, 1.0
    )
    np.testing.assert_allclose(far, reading + 6.0, atol=1e-9)


def test_the_free_shape_starts_where_the_centrelines_favour_then_from_a_straight_cm(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A reading 3° off at every point: the registration with the shape free starts from the shape
    the centrelines favour (3° below the reading) and fits: named; where that fits nothing, a straight
    CM's starts are searched; without ``starts_for`` the reading's own starts only."""
    reading = np.full(5, 3.0)
    calls: list[dict[str, Any]] = []

    def starts_for(shape: np.ndarray) -> tuple[list[list[np.ndarray]], float]:
        return [[se3.make(np.eye(3), shape[:3])]], float(np.sum(shape**2))

    def registered(views: Any, lms: Any, tries: Any, diag: Any, **kw: Any) -> _Reg:
        calls.append({"tries": tries, **kw})
        if np.any(np.abs(kw["initial_control_points_deg"]) > fits_within):
            raise RegistrationRefused("cm", "edge_ncc", "still no fit", view="AP")
        return _Reg(control_points_deg=np.zeros(5))

    monkeypatch.setattr(shared_causes, "register_cm_checked", registered)
    failed = dataclasses.replace(_failed(_refused(), reading=reading), starts_for=starts_for)
    fits_within = 0.1
    rec: dict[str, Any] = {}
    out = name_fbg_cause(failed, rec)
    assert out.check == "fbg_reading" and rec["fits"] and len(calls) == 1
    assert rec["centreline_shape_deg"] == [0.0] * 5
    np.testing.assert_allclose(calls[0]["tries"][0][0][:3, 3], 0.0)
    assert calls[0]["config"].control_point_tolerance_deg == 6.0
    # the favoured shape fits nothing: a straight CM's starts (seed + 2), then nothing
    calls.clear()
    failed = dataclasses.replace(failed, starts_for=lambda s: ([[np.eye(4)]], float(np.sum((s - 1.0) ** 2))))
    fits_within = 0.5
    assert name_fbg_cause(failed).check == "fbg_reading"
    assert len(calls) == 2 and calls[1]["seed"] == 2
    np.testing.assert_allclose(calls[1]["initial_control_points_deg"], 0.0)
    fits_within = -1.0
    calls.clear()
    assert name_fbg_cause(failed).check == "edge_ncc" and len(calls) == 2
    # without starts_for: the reading's own starts, once
    calls.clear()
    none = name_fbg_cause(_failed(_refused(), reading=reading))
    assert none.check == "edge_ncc" and len(calls) == 1
