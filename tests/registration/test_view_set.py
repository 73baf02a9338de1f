"""One set of views registered (``register_view_set``): what it hands each stage.

The registrations are stand-ins that record their arguments: this tests the chain (one device for
every stage, the prior's starts and the agreement with its prediction, the stages' records and
refusals), not the registrations themselves (tests/registration/bone, cm, centerline; the whole
chain on simulated images: tests/navigation/test_demo.py). The bones' checks are stand-ins too (a
view's image says whether its pelvis or its femur fails), but for one test on physics images: a
mirrored view of three is left out and the femur registered from the other two.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

import fluoronav.registration.bone.checks as bone_checks
import fluoronav.registration.cm.shared_causes as shared_causes
import fluoronav.registration.view_set.bones as view_set_bones
import fluoronav.registration.view_set.cm as view_set_cm
import fluoronav.registration.view_set.views as view_set_views
from fluoronav.errors import RegistrationRefused
from fluoronav.geometry import se3
from fluoronav.geometry.camera import Camera, DetectorSpec
from fluoronav.manipulator.config import CMConfig
from fluoronav.registration.bone import PELVIS_PRESET, PELVIS_REFINE_PRESET, femur_config
from fluoronav.registration.bone.checks import BoneCheckConfig, BoneViewDiagnostics
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
#: image values of a view whose pelvis, or whose femur, fails its checks (the stand-in's diagnostics)
BAD_PELVIS, BAD_FEMUR = 0.9, 0.8


def _rigid(deg: float, t: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return se3.make(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), t)


def _views(n: int = 3, detected: int = 3, values: dict[int, float] | None = None) -> list[FluoroView]:
    out = []
    for k in range(n):
        cam = Camera.from_detector(
            DetectorSpec(rows=SIZE, cols=SIZE, pixel_spacing_mm=1.0, sdd_mm=1000.0),
            _rigid(10.0 * k, (0.0, 0.0, 500.0)),
        )
        lm = np.array([[8.0 + k, 10.0], [20.0, 22.0 - k]])
        det = ViewDetection(lm, np.linspace(lm[0], lm[1], 5), np.ones((SIZE, SIZE), bool), np.ones(2), "case")
        image = np.full((SIZE, SIZE), (values or {}).get(k, 0.5), np.float32)
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
    motion: list[Any] = field(default_factory=list)


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
        c.femur.append({**kw, "views": len(views)})
        return bone_result(_rigid(3.0, (1.0, 2.0, 3.0)))

    def footprints(cameras: list[Camera], *a: Any, **kw: Any) -> np.ndarray:
        return np.zeros((len(cameras), SIZE, SIZE), bool)

    def init(cameras: list[Camera], landmarks_px: np.ndarray, *a: Any, **kw: Any) -> SimpleNamespace:
        c.init.append(kw)
        n = len(cameras)
        return SimpleNamespace(
            landmarks_px=landmarks_px,
            landmarks_world=np.zeros((2, 3)),
            cost_px=0.5,
            landmark_inliers=np.ones((n, 2), bool),
        )

    def checked(views: list[Any], lms: list[Any], tries: list[Any], diag: dict[str, Any], **kw: Any) -> Any:
        c.cm.append({"tries": tries, "views": views, **kw})
        diag.update(cost=-1.0)
        return SimpleNamespace(cost=-1.0, converged=True, reason="converged")

    def unchecked(views: list[Any], starts: list[Any], **kw: Any) -> Any:
        c.unchecked.append({"starts": starts, **kw})
        return SimpleNamespace(cost=-1.0, converged=True, reason="converged")

    monkeypatch.setattr(view_set_views, "instrument_masks", lambda masks, *a: [None] * len(masks))
    monkeypatch.setattr(view_set_bones, "register_pelvis_per_view", pelvis)
    monkeypatch.setattr(view_set_bones, "register_femur", femur)
    monkeypatch.setattr(view_set_bones, "bone_footprints", footprints)
    monkeypatch.setattr(view_set_cm, "centerline_initialize_multiview", init)
    monkeypatch.setattr(
        view_set_cm, "multiview_start_poses", lambda init, max_starts: MULTIVIEW_STARTS[:max_starts]
    )
    monkeypatch.setattr(view_set_cm, "register_cm_checked", checked)

    def agreement(predicted: Any, cm: Any, cm_config: Any) -> dict[str, float]:
        c.motion.append(predicted)
        return {"motion_tip_mm": 4.2, "motion_rotation_deg": 1.5}

    monkeypatch.setattr(view_set_cm, "motion_agreement", agreement)
    # the stand-in registrations carry no tip: a fusion (tested in test_view_set_fusion.py) finds
    # them inconsistent unless a test says otherwise
    monkeypatch.setattr(view_set_cm, "_fuse", lambda cm, *a: (cm, {"mahalanobis": 9.0}))

    def diagnostics(views: list[Any], volume: Any, label: str, *a: Any) -> list[BoneViewDiagnostics]:
        bad = BAD_PELVIS if label == "pelvis" else BAD_FEMUR
        return [
            BoneViewDiagnostics(0.1, 0.05)
            if np.isclose(np.mean(v.image), bad)
            else BoneViewDiagnostics(0.9, 0.5)
            for v in views
        ]

    monkeypatch.setattr(view_set_cm, "register_cm_multistart", unchecked)
    monkeypatch.setattr(bone_checks, "bone_view_diagnostics", diagnostics)
    monkeypatch.setattr(bone_checks, "register_pelvis_per_view", pelvis)
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
    assert "landmark_prior_world" not in calls.init[0]
    assert calls.cm[0]["tries"] == [MULTIVIEW_STARTS[:1]] and not calls.motion
    assert [v.name for v in calls.cm[0]["views"]] == ["view0", "view1", "view2"]
    assert reg.cm_init is not None and reg.detections == tuple(v.detection for v in reg.views)


def test_a_prior_adds_the_prediction_to_the_images_starts_and_reports_the_agreement(calls: _Calls) -> None:
    records: dict[str, StageRecord] = {}
    reg = _register(ViewSetSettings(), PRIOR, name="verify", recorder=timed_stages(records))
    F = reg.femur.world_from_bone  # the femur registered anew
    expected = F @ PRIOR.femur_from_cm_predicted
    # the images' own starts and the prediction screened together; the plan's pose where they fail
    tries = calls.cm[0]["tries"]
    assert len(tries) == 2 and len(tries[0]) == len(MULTIVIEW_STARTS) + 1
    for got, want in zip(tries[0], [*MULTIVIEW_STARTS, expected], strict=True):
        np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(tries[1][0], F @ PRIOR.femur_from_cm_start)
    # the detections are not gated by the prediction
    assert "landmark_prior_world" not in calls.init[0]
    # the agreement with the prediction is measured and recorded, not judged
    [predicted] = calls.motion
    np.testing.assert_array_equal(predicted.world_from_reference, F)
    np.testing.assert_array_equal(predicted.reference_from_cm, PRIOR.femur_from_cm_predicted)
    assert predicted.max_tip_mm == 2.5 and "predicted" not in calls.cm[0]
    assert records["cm"].diagnostics["motion_tip_mm"] == 4.2
    # the bones: the femur starts at the prior's, and each view's pelvis again without the femur
    np.testing.assert_array_equal(calls.femur[0]["initial_world_from_femur"], PRIOR.ct_from_femur)
    seeds = ViewSetSeeds.from_seed(100)
    assert [kw["seed"] for kw in calls.pelvis] == [seeds.pelvis, seeds.pelvis_refine]
    assert [v.name for v in calls.cm[0]["views"]] == ["view0 (verify)", "view1 (verify)", "view2 (verify)"]


def test_a_prior_with_one_view_of_the_cm_starts_from_the_plan_then_the_prediction(calls: _Calls) -> None:
    reg = _register(ViewSetSettings(), PRIOR, views=_views(detected=1))
    F = reg.femur.world_from_bone
    tries = calls.cm[0]["tries"]
    assert [len(t) for t in tries] == [1, 1] and not calls.init
    np.testing.assert_array_equal(tries[0][0], F @ PRIOR.femur_from_cm_start)
    np.testing.assert_array_equal(tries[1][0], F @ PRIOR.femur_from_cm_predicted)


def test_local_bones_start_from_the_given_cameras_with_the_local_levels_only(calls: _Calls) -> None:
    settings = ViewSetSettings(local=True)
    views = _views()
    records: dict[str, StageRecord] = {}
    _register(settings, PRIOR, views=views, recorder=timed_stages(records))
    assert all("cost" in v for v in records["pelvis"].diagnostics["views"].values())
    # one pelvis registration per view (no ladder first), from the given cameras, femur left out
    [pelvis] = calls.pelvis
    assert pelvis["config"] == settings.pelvis_local
    np.testing.assert_array_equal(pelvis["initial_world_from_patient"], np.broadcast_to(np.eye(4), (3, 4, 4)))
    [femur] = calls.femur
    assert femur["config"] == settings.femur_local
    np.testing.assert_array_equal(femur["initial_world_from_femur"], PRIOR.ct_from_femur)


def test_a_prediction_of_stated_uncertainty_that_the_images_agree_with_is_the_only_start(
    calls: _Calls, monkeypatch: pytest.MonkeyPatch
) -> None:
    from fluoronav.registration.cm.config import local_cm_levels

    monkeypatch.setattr(view_set_cm, "landmark_gap_mm", lambda *a: 1.0)
    fused: list[float] = []

    def fuse(cm: Any, views: Any, predicted: Any, sigma: float, *a: Any) -> tuple[Any, dict[str, float]]:
        fused.append(sigma)
        return cm, {"fusion_shift_mm": 0.1, "mahalanobis": 0.5}

    monkeypatch.setattr(view_set_cm, "_fuse", fuse)
    records: dict[str, StageRecord] = {}
    reg = _register(
        ViewSetSettings(), replace(PRIOR, prediction_sigma_mm=0.9), recorder=timed_stages(records)
    )
    [cm] = calls.cm  # no second registration: the one from the prediction passed
    [[start]] = cm["tries"]
    np.testing.assert_array_equal(start, reg.femur.world_from_bone @ PRIOR.femur_from_cm_predicted)
    assert cm["config"].levels == local_cm_levels(3)
    diag = records["cm"].diagnostics
    assert diag["from_prediction"] is True and diag["prediction_gap_mm"] == 1.0
    # consistent with the prediction (0.5 σ): the tip is fused with it, and the agreement measured
    # again after the fusion (the images' own kept beside it)
    assert fused == [0.9] and diag["fusion_shift_mm"] == 0.1 and diag["fusion_mahalanobis"] == 0.5
    assert diag["image_motion_tip_mm"] == 4.2 and len(calls.motion) == 2


def test_one_view_far_from_the_prediction_is_registered_from_its_own_starts(
    calls: _Calls, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(view_set_cm, "landmark_gap_mm", lambda *a: 7.5)
    records: dict[str, StageRecord] = {}
    _register(
        ViewSetSettings(),
        replace(PRIOR, prediction_sigma_mm=0.9),
        views=_views(detected=1),
        recorder=timed_stages(records),
    )
    [cm] = calls.cm
    assert [len(t) for t in cm["tries"]] == [1, 1]  # the plan's start, then the prediction
    assert records["cm"].diagnostics["from_prediction"] is False


def test_several_views_try_the_prediction_whatever_their_triangulation_says(
    calls: _Calls, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One wrong detection can throw the triangulated landmarks far off while the kinematics are
    right: with several views, the views' checks judge the registration from the prediction."""
    monkeypatch.setattr(view_set_cm, "landmark_gap_mm", lambda *a: 43.0)
    monkeypatch.setattr(
        view_set_cm, "_fuse", lambda cm, *a: (cm, {"mahalanobis": 9.0, "fusion_shift_mm": 1.0})
    )
    records: dict[str, StageRecord] = {}
    _register(ViewSetSettings(), replace(PRIOR, prediction_sigma_mm=0.9), recorder=timed_stages(records))
    [cm] = calls.cm
    assert len(cm["tries"]) == 1 and len(cm["tries"][0]) == 1
    diag = records["cm"].diagnostics
    assert diag["from_prediction"] is True and diag["prediction_gap_mm"] == 43.0
    # inconsistent with the prediction (9 σ): not fused, for the caller to judge
    assert (
        diag["fusion_mahalanobis"] == 9.0 and "fusion_shift_mm" not in diag and diag["motion_tip_mm"] == 4.2
    )


def test_a_failed_registration_from_the_prediction_falls_back_to_the_images_starts(
    calls: _Calls, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(view_set_cm, "landmark_gap_mm", lambda *a: 1.0)
    original = view_set_cm.register_cm_checked

    def failing_once(*a: Any, **kw: Any) -> Any:
        if len(calls.cm) == 0:
            calls.cm.append({"tries": a[2], **kw})
            raise RegistrationRefused("cm", "edge_ncc", "NCC 0.50 (at least 0.7)", view="view0 (verify)")
        return original(*a, **kw)

    monkeypatch.setattr(view_set_cm, "register_cm_checked", failing_once)
    records: dict[str, StageRecord] = {}
    _register(ViewSetSettings(), replace(PRIOR, prediction_sigma_mm=0.9), recorder=timed_stages(records))
    assert [len(c["tries"]) for c in calls.cm] == [1, 2]
    diag = records["cm"].diagnostics
    assert diag["from_prediction"] is False and "edge_ncc" in diag["from_prediction_refused"]


def test_known_bones_register_no_bone(calls: _Calls) -> None:
    views = _views()
    femur = SimpleNamespace(world_from_bone=_rigid(4.0, (1.0, 0.0, 0.0)))
    known = view_set_bones.ViewSetBones(
        pelvis=tuple(SimpleNamespace() for _ in views),
        cameras=tuple(v.camera for v in views),
        femur=femur,  # type: ignore[arg-type]
    )
    records: dict[str, StageRecord] = {}
    reg = _register(ViewSetSettings(), PRIOR, views=views, known_bones=known, recorder=timed_stages(records))
    assert not calls.pelvis and not calls.femur and len(calls.cm) == 1
    assert records["pelvis"].diagnostics == {"known": True} and records["femur"].diagnostics == {
        "known": True
    }
    np.testing.assert_array_equal(reg.ct_from_femur, femur.world_from_bone)


def test_a_prior_without_a_prediction_measures_no_agreement(calls: _Calls) -> None:
    reg = _register(ViewSetSettings(pelvis_refine=None), replace(PRIOR, femur_from_cm_predicted=None))
    tries = calls.cm[0]["tries"]
    np.testing.assert_array_equal(tries[0][-1], reg.femur.world_from_bone @ PRIOR.femur_from_cm_start)
    assert not calls.motion
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
    starts = calls.unchecked[0]["starts"]  # the first try's: the images' own and the prediction
    np.testing.assert_array_equal(starts[-1], reg.femur.world_from_bone @ PRIOR.femur_from_cm_predicted)


def test_two_views_without_a_cm_refuse_the_first_registration(calls: _Calls) -> None:
    records: dict[str, StageRecord] = {}
    with pytest.raises(RegistrationRefused) as err:
        _register(ViewSetSettings(), views=_views(detected=1), recorder=timed_stages(records))
    assert err.value.stage == "cm" and err.value.check == "views_with_cm"
    assert records["cm"].passed is False and not calls.init and not calls.cm


def test_a_refusal_of_the_cm_marks_its_stage(monkeypatch: pytest.MonkeyPatch, calls: _Calls) -> None:
    def refuse(*a: Any, **kw: Any) -> Any:
        raise RegistrationRefused("cm", "edge_ncc", "NCC 0.1", view="view1")

    monkeypatch.setattr(view_set_cm, "register_cm_checked", refuse)
    monkeypatch.setattr(shared_causes, "register_cm_checked", refuse)  # nor does a shared input explain it
    records: dict[str, StageRecord] = {}
    with pytest.raises(RegistrationRefused, match="stage cm, view view1, check edge_ncc"):
        _register(ViewSetSettings(), recorder=timed_stages(records))
    assert records["cm"].passed is False and records["femur"].passed is True


def test_a_view_whose_pelvis_fails_is_left_out_of_the_later_stages(calls: _Calls) -> None:
    records: dict[str, StageRecord] = {}
    reg = _register(ViewSetSettings(), views=_views(values={1: BAD_PELVIS}), recorder=timed_stages(records))
    assert [v.name for v in reg.views] == ["view0", "view2"] and len(reg.cameras_ct) == len(reg.pelvis) == 2
    assert calls.femur[0]["views"] == 2 and len(calls.femur) == 1
    assert [v.name for v in calls.cm[0]["views"]] == ["view0", "view2"]
    assert list(reg.left_out) == ["view1"] and reg.left_out["view1"].startswith("edge_ncc: ")
    assert records["pelvis"].diagnostics["left_out"] == reg.left_out and records["pelvis"].passed
    assert records["pelvis"].diagnostics["views"]["view1"]["check"] == "edge_ncc"
    # the failed view's mirror was tried once, at the pelvis's coarse level only
    assert len(calls.pelvis) == 2 and len(calls.pelvis[1]["config"].levels) == 1


def test_too_few_views_whose_pelvis_passes_refuse(calls: _Calls) -> None:
    records: dict[str, StageRecord] = {}
    with pytest.raises(RegistrationRefused, match="stage pelvis, view view1, check edge_ncc") as err:
        _register(
            ViewSetSettings(),
            views=_views(values={1: BAD_PELVIS, 2: BAD_PELVIS}),
            recorder=timed_stages(records),
        )
    assert err.value.stage == "pelvis" and err.value.view == "view1"
    assert records["pelvis"].passed is False and not calls.femur and not calls.cm


def test_a_view_whose_femur_fails_is_left_out_and_the_femur_registered_again(calls: _Calls) -> None:
    records: dict[str, StageRecord] = {}
    reg = _register(ViewSetSettings(), views=_views(values={2: BAD_FEMUR}), recorder=timed_stages(records))
    assert [kw["views"] for kw in calls.femur] == [3, 2]
    assert [kw["seed"] for kw in calls.femur] == [ViewSetSeeds.from_seed(100).femur] * 2
    assert [v.name for v in calls.cm[0]["views"]] == ["view0", "view1"]
    assert [v.name for v in reg.views] == ["view0", "view1"]
    assert list(reg.left_out) == ["view2"] and "femur" in reg.left_out["view2"]
    assert list(records["femur"].diagnostics["views"]) == ["view0", "view1"]
    assert records["femur"].diagnostics["left_out"] == reg.left_out


def test_without_bone_checks_every_view_goes_on(calls: _Calls) -> None:
    reg = _register(ViewSetSettings(bone_checks=None), views=_views(values={1: BAD_PELVIS, 2: BAD_FEMUR}))
    assert len(reg.views) == 3 and not reg.left_out and calls.femur[0]["views"] == 3


# ----- on physics images -----------------------------------------------------------------------------
def test_a_mirrored_view_of_three_is_left_out_and_the_femur_registered_from_the_others() -> None:
    from fluoronav.anatomy.phantom import hip_phantom
    from fluoronav.registration.bone import BoneLevel, BoneRegistrationConfig, views_from_images
    from fluoronav.registration.bone.checks import mirrored_view
    from fluoronav.registration.levels import LevelConfig
    from fluoronav.registration.view_set import register_view_set_bones
    from fluoronav.simulation.articulated import ArticulatedSimulator
    from fluoronav.simulation.physics import XrayPhysics
    from fluoronav.simulation.protocol import sample_trial, simulate_trial_images
    from fluoronav.simulation.xray import SimulationConfig

    volume = hip_phantom(seed=0, spacing_mm=2.0)
    sim = ArticulatedSimulator(
        volume, config=SimulationConfig(physics=XrayPhysics(energy_bin_keV=3.0, photons_per_pixel=None))
    )
    trial = sample_trial("multi-view", volume, np.random.default_rng(2))
    views = views_from_images(simulate_trial_images(trial, sim, seed=0, image_size=128))
    quick = BoneRegistrationConfig(
        levels=(
            BoneLevel(
                LevelConfig(sigma=(3, 3, 3, 6, 6, 12), popsize=12, max_iters=40), image_px=64, voxel_mm=4.0
            ),
            BoneLevel(
                LevelConfig(sigma=(1, 1, 1, 2, 2, 4), popsize=10, max_iters=30), image_px=128, voxel_mm=2.0
            ),
        )
    )
    bones = register_view_set_bones(
        [views[0], mirrored_view(views[1]), views[2]],
        volume,
        side=trial.side,
        settings=ViewSetSettings(pelvis=quick, bone_checks=BoneCheckConfig()),
        seeds=ViewSetSeeds.from_seed(0),
        names=["AP", "orbit +20", "orbit -15"],
        initial_world_from_pelvis=trial.initial_world_from_patient,
    )
    assert bones.kept == (0, 2)
    assert bones.left_out == {
        "orbit +20": "mirrored: view orbit +20 looks mirrored left–right: check the detector orientation"
    }
    ct_from_femur = np.linalg.inv(trial.world_from_patient) @ trial.world_from_femur
    entry = np.append(volume.landmarks_world[f"entry_{trial.side}"], 1.0)
    assert np.linalg.norm((bones.femur.world_from_bone @ entry - ct_from_femur @ entry)[:3]) < 1.0
    rot = bones.femur.world_from_bone[:3, :3] @ ct_from_femur[:3, :3].T
    assert np.degrees(np.arccos(np.clip((np.trace(rot) - 1) / 2, -1, 1))) < 1.0


def test_a_refusal_no_shared_input_explains_is_tried_one_view_left_out(
    monkeypatch: pytest.MonkeyPatch, calls: _Calls
) -> None:
    """The CM fails view0's check on all three views; no shared input explains it; registered on
    view0 and view2 alone it passes and lies far off view1's landmarks: the refusal names view1
    (check odd_view), what was tried recorded in the stage's ``odd_view``."""

    def refuse(*a: Any, **kw: Any) -> Any:
        raise RegistrationRefused("cm", "edge_ncc", "NCC 0.1", view="view0")

    @dataclass
    class _Far:
        landmarks_world: np.ndarray = field(
            default_factory=lambda: np.array([[[500.0, 0.0, 0.0], [510.0, 0.0, 0.0]]])
        )

    def without_view1(views: Any, *a: Any, **kw: Any) -> Any:
        if [v.name for v in views] == ["view0", "view2"]:
            return _Far()
        refuse()

    monkeypatch.setattr(view_set_cm, "register_cm_checked", refuse)
    monkeypatch.setattr(shared_causes, "register_cm_checked", without_view1)
    records: dict[str, StageRecord] = {}
    with pytest.raises(RegistrationRefused) as err:
        _register(ViewSetSettings(), recorder=timed_stages(records))
    assert (err.value.check, err.value.view) == ("odd_view", "view1")
    odd = records["cm"].diagnostics["odd_view"]
    assert odd["view1"]["fits"] and odd["view1"]["miss_mm"] > 2.0 and not odd["view0"]["fits"]
