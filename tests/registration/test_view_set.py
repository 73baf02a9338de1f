"""One set of views registered (``register_view_set``): what it hands each stage.

The registrations are stand-ins that record their arguments: this tests the chain (one device for
every stage, the prior's starts and landmark gate, the stages' records and refusals), not the
registrations themselves (tests/registration/bone, cm, centerline; the whole chain on simulated
images: tests/navigation/test_demo.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch

import fluoronav.registration.view_set as view_set
from fluoronav.errors import RegistrationRefused
from fluoronav.geometry import se3
from fluoronav.geometry.camera import Camera, DetectorSpec
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.registration.bone import PELVIS_PRESET, PELVIS_REFINE_PRESET, femur_config
from fluoronav.registration.cm import CMRegistrationConfig
from fluoronav.registration.stages import StageRecord, timed_stages
from fluoronav.registration.view_set import (
    FluoroView,
    ViewDetection,
    ViewSetPrior,
    ViewSetSeeds,
    ViewSetSettings,
    register_view_set,
)

SIZE = 32
SIDE = "left"


def _rigid(deg: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return se3.make(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), t)


def _views(n: int = 3, detected: int = 3) -> list[FluoroView]:
    out = []
    for k in range(n):
        cam = Camera.from_detector(
            DetectorSpec(rows=SIZE, cols=SIZE, pixel_spacing_mm=1.0, sdd_mm=1000.0),
            _rigid(10.0 * k, (0.0, 0.0, 500.0)),
        )
        lm = np.array([[8.0 + k, 10.0], [20.0, 22.0 - k]])
        det = ViewDetection(lm, np.linspace(lm[0], lm[1], 5), np.ones((SIZE, SIZE), bool), np.ones(2), "case")
        image = np.full((SIZE, SIZE), 0.5, np.float32)
        out.append(FluoroView(f"view{k}", image, cam, det if k < detected else None))
    return out


@dataclass
class _Calls:
    """What the stand-ins were given."""

    pelvis: list[dict[str, Any]] = field(default_factory=list)
    femur: list[dict[str, Any]] = field(default_factory=list)
    init: list[dict[str, Any]] = field(default_factory=list)
    cm: list[dict[str, Any]] = field(default_factory=list)
    unchecked: list[dict[str, Any]] = field(default_factory=list)


MULTIVIEW_STARTS = [np.diag([1.0, 1.0, 1.0, 1.0])]


@pytest.fixture
def calls(monkeypatch: pytest.MonkeyPatch) -> _Calls:
    c = _Calls()

    def bone_result(world_from_bone: np.ndarray, camera: Camera | None = None) -> SimpleNamespace:
        cam = np.eye(4) if camera is None else camera.camera_from_world @ world_from_bone
        return SimpleNamespace(
            world_from_bone=world_from_bone,
            camera_from_bone=cam[None],
            cost=-0.5,
            converged=True,
            reason="converged",
            seconds=0.1,
        )

    def pelvis(views: list[Any], volume: Any, **kw: Any) -> list[SimpleNamespace]:
        c.pelvis.append(kw)
        return [bone_result(np.eye(4), v.camera) for v in views]

    def femur(views: list[Any], volume: Any, **kw: Any) -> SimpleNamespace:
        c.femur.append(kw)
        return bone_result(_rigid(3.0, (1.0, 2.0, 3.0)))

    def footprints(cameras: list[Camera], *a: Any, **kw: Any) -> np.ndarray:
        return np.zeros((len(cameras), SIZE, SIZE), bool)

    def init(cameras: list[Camera], landmarks_px: np.ndarray, *a: Any, **kw: Any) -> SimpleNamespace:
        c.init.append(kw)
        n = len(cameras)
        return SimpleNamespace(landmarks_px=landmarks_px, cost_px=0.5, landmark_inliers=np.ones((n, 2), bool))

    def checked(views: list[Any], lms: list[Any], tries: list[Any], diag: dict[str, Any], **kw: Any) -> Any:
        c.cm.append({"tries": tries, "views": views, **kw})
        diag.update(cost=-1.0)
        return SimpleNamespace(cost=-1.0, converged=True, reason="converged")

    def unchecked(views: list[Any], starts: list[Any], **kw: Any) -> Any:
        c.unchecked.append({"starts": starts, **kw})
        return SimpleNamespace(cost=-1.0, converged=True, reason="converged")

    monkeypatch.setattr(view_set, "instrument_masks", lambda masks, *a: [None] * len(masks))
    monkeypatch.setattr(view_set, "register_pelvis_per_view", pelvis)
    monkeypatch.setattr(view_set, "register_femur", femur)
    monkeypatch.setattr(view_set, "bone_footprints", footprints)
    monkeypatch.setattr(view_set, "centerline_initialize_multiview", init)
    monkeypatch.setattr(
        view_set, "multiview_start_poses", lambda init, max_starts: MULTIVIEW_STARTS[:max_starts]
    )
    monkeypatch.setattr(view_set, "register_cm_checked", checked)
    monkeypatch.setattr(view_set, "register_cm_multistart", unchecked)
    return c


VOLUME = SimpleNamespace(landmarks_world={f"femoral_head_{SIDE}": np.array([5.0, 0.0, 0.0])})
CP = np.full(CMConfig().n_control_points, 3.0)
PRIOR = ViewSetPrior(
    ct_from_femur=_rigid(-2.0, (0.5, 0.0, 0.0)),
    femur_from_cm_start=_rigid(20.0, (30.0, 0.0, 10.0)),
    femur_from_cm_predicted=_rigid(25.0, (31.0, 1.0, 10.0)),
    max_motion_tip_mm=2.5,
)


def _register(settings: ViewSetSettings, prior: ViewSetPrior | None = None, **kw: Any) -> Any:
    return register_view_set(
        kw.pop("views", _views()),
        VOLUME,  # type: ignore[arg-type]
        side=SIDE,
        cm_config=CMConfig(),
        initial_control_points_deg=CP,
        settings=settings,
        seed=kw.pop("seed", 100),
        prior=prior,
        **kw,
    )


def test_the_device_is_given_once_and_reaches_every_stage(calls: _Calls) -> None:
    settings = ViewSetSettings(
        device="cuda:3",
        pelvis=replace(PELVIS_PRESET, device="cpu"),
        femur=replace(femur_config(views=3), device="cpu"),
        pelvis_refine=replace(PELVIS_REFINE_PRESET, device="cpu"),
        cm=CMRegistrationConfig(device="cpu", roi_size_full_px=400),
    )
    cm_config = CMConfig()
    register_view_set(
        _views(),
        VOLUME,  # type: ignore[arg-type]
        side=SIDE,
        cm_config=cm_config,
        initial_control_points_deg=CP,
        settings=settings,
        prior=PRIOR,
    )
    configs = [kw["config"] for kw in calls.pelvis + calls.femur + calls.cm]
    assert len(configs) == 4  # the pelvis twice (the second without the femur), femur, CM
    assert [cfg.device for cfg in configs] == ["cuda:3"] * 4
    # otherwise the sub-configs as given; the CM's geometry is the one passed
    assert calls.pelvis[1]["config"] == replace(PELVIS_REFINE_PRESET, device="cuda:3")
    assert calls.cm[0]["config"].roi_size_full_px == 400 and calls.cm[0]["config"].cm_config is cm_config


def test_without_a_prior_the_cm_starts_from_the_views(calls: _Calls) -> None:
    reg = _register(
        ViewSetSettings(max_cm_starts=1), seed=ViewSetSeeds(pelvis=7, femur=8, pelvis_refine=9, cm=10)
    )
    assert [kw["seed"] for kw in calls.pelvis + calls.femur + calls.cm] == [7, 8, 10]
    assert calls.femur[0]["initial_world_from_femur"] is None
    assert calls.init[0]["landmark_prior_world"] is None
    assert calls.cm[0]["tries"] == [MULTIVIEW_STARTS[:1]] and calls.cm[0]["predicted"] is None
    assert [v.name for v in calls.cm[0]["views"]] == ["view0", "view1", "view2"]
    assert reg.cm_init is not None and reg.detections == tuple(v.detection for v in reg.views)


def test_a_prior_changes_the_start_the_landmark_gate_and_the_checks(calls: _Calls) -> None:
    reg = _register(ViewSetSettings(), PRIOR, name="verify")
    F = reg.femur.world_from_bone  # the femur registered anew
    expected = F @ PRIOR.femur_from_cm_predicted
    # the start: the prior's pose on the new femur, then (where it fails) the predicted one
    tries = calls.cm[0]["tries"]
    assert len(tries) == 2
    np.testing.assert_array_equal(tries[0][0], F @ PRIOR.femur_from_cm_start)
    np.testing.assert_array_equal(tries[1][0], expected)
    # the gate of the detected landmarks: the landmarks of the CM where the prediction puts it
    landmarks_cm = CMKinematics(CMConfig()).landmarks_cm(torch.as_tensor(CP, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(calls.init[0]["landmark_prior_world"], se3.apply(expected, landmarks_cm))
    # the motion check: the predicted pose and its tolerance
    predicted = calls.cm[0]["predicted"]
    np.testing.assert_array_equal(predicted.world_from_reference, F)
    np.testing.assert_array_equal(predicted.reference_from_cm, PRIOR.femur_from_cm_predicted)
    assert predicted.max_tip_mm == 2.5
    # the bones: the femur starts at the prior's, and each view's pelvis again without the femur
    np.testing.assert_array_equal(calls.femur[0]["initial_world_from_femur"], PRIOR.ct_from_femur)
    seeds = ViewSetSeeds.from_seed(100)
    assert [kw["seed"] for kw in calls.pelvis] == [seeds.pelvis, seeds.pelvis_refine]
    assert [v.name for v in calls.cm[0]["views"]] == ["view0 (verify)", "view1 (verify)", "view2 (verify)"]


def test_a_prior_without_a_prediction_starts_once_and_checks_no_motion(calls: _Calls) -> None:
    _register(ViewSetSettings(pelvis_refine=None), replace(PRIOR, femur_from_cm_predicted=None))
    assert len(calls.cm[0]["tries"]) == 1 and calls.cm[0]["predicted"] is None
    assert calls.init[0]["landmark_prior_world"] is None
    assert len(calls.pelvis) == 1  # no second pelvis registration without its settings


def test_the_stages_are_recorded_in_order(calls: _Calls) -> None:
    records: dict[str, StageRecord] = {}
    _register(ViewSetSettings(), PRIOR, recorder=timed_stages(records))
    assert list(records) == ["pelvis", "femur", "cm"]
    views = records["pelvis"].diagnostics["views"]
    assert list(views) == ["view0", "view1", "view2"]
    assert {"cost", "converged", "reason", "femur_left_out", "cost_without_femur"} <= set(views["view0"])
    assert records["femur"].diagnostics["converged"] is True
    assert records["cm"].diagnostics["init_cost_px"] == 0.5 and records["cm"].diagnostics["cost"] == -1.0
    assert all(r.passed for r in records.values())


def test_unchecked_settings_register_the_cm_from_the_first_starts(calls: _Calls) -> None:
    reg = _register(ViewSetSettings(cm_checks=None), PRIOR)
    assert not calls.cm and len(calls.unchecked) == 1
    [start] = calls.unchecked[0]["starts"]  # the predicted pose is a second start only for checks
    np.testing.assert_array_equal(start, reg.femur.world_from_bone @ PRIOR.femur_from_cm_start)


def test_two_views_without_a_cm_refuse_the_first_registration(calls: _Calls) -> None:
    records: dict[str, StageRecord] = {}
    with pytest.raises(RegistrationRefused) as err:
        _register(ViewSetSettings(), views=_views(detected=1), recorder=timed_stages(records))
    assert err.value.stage == "cm" and err.value.check == "views_with_cm"
    assert records["cm"].passed is False and not calls.init and not calls.cm


def test_a_refusal_of_the_cm_marks_its_stage(monkeypatch: pytest.MonkeyPatch, calls: _Calls) -> None:
    def refuse(*a: Any, **kw: Any) -> Any:
        raise RegistrationRefused("cm", "edge_ncc", "NCC 0.1", view="view1")

    monkeypatch.setattr(view_set, "register_cm_checked", refuse)
    records: dict[str, StageRecord] = {}
    with pytest.raises(RegistrationRefused, match="stage cm, view view1, check edge_ncc"):
        _register(ViewSetSettings(), recorder=timed_stages(records))
    assert records["cm"].passed is False and records["femur"].passed is True
