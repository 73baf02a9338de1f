"""Which one is wrong where the verification's detections and the kinematics disagree: the images decide.

An ideal world: three physics-simulated views of the CM (384², noise-free), their cameras known in the
CT frame and the femur at the identity (the verification's bones stand in); the verification's CM
registration from the detections stands in too (its refusal or its result and diagnostics are given),
and the CM registered at the kinematic prediction is the real one, on the images. A wrong structure
is the CM's landmarks moved 10 mm across the beams and projected into every view (the views agree on
it); a hand-eye matrix 10 mm off is a prediction 10 mm from the CM.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch

import fluoronav.navigation.verification as verification
from fluoronav.errors import RegistrationRefused
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.navigation.checks.safety import SafetyConfig
from fluoronav.navigation.config import NavigationConfig, VerificationConfig
from fluoronav.navigation.disagreement import ImagesAtPrediction, images_side_with
from fluoronav.navigation.result import NavigationRefused, NavigationResult, StageRecord
from fluoronav.registration.cm.checks import CMCheckConfig
from fluoronav.registration.stages import StageTimer
from fluoronav.registration.view_set import (
    FluoroView,
    ViewDetection,
    ViewSetBones,
    ViewSetPrior,
    ViewSetRegistration,
)
from fluoronav.simulation.cm_case import cm_case_from_simulation, simulate_cm_case
from fluoronav.simulation.navigation.faults import FAULTS

#: the wrong structure's and the hand-eye error's offset at the CM, mm
OFFSET_MM = 10.0


@pytest.fixture(autouse=True)
def _single_thread_torch() -> Any:
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def scene() -> SimpleNamespace:
    """The CM in three views: its true pose and shape, the views, and a direction across the beams."""
    kw: dict[str, Any] = dict(image_size=384, photons_per_pixel=None, rotation_deg=5.0, translation_mm=5.0)
    case = cm_case_from_simulation(simulate_cm_case("multi-view", seed=4, **kw))
    assert case.world_from_cm_true is not None and case.control_points_true_deg is not None
    ap_beam = np.linalg.inv(case.views[0].camera.camera_from_world)[:3, 2]
    across = np.cross(ap_beam, [0.0, 0.0, 1.0])
    return SimpleNamespace(
        case=case,
        W=np.asarray(case.world_from_cm_true[0]),
        cp=np.asarray(case.control_points_true_deg, np.float64),
        across=across / np.linalg.norm(across),
    )


def _moved(W: np.ndarray, shift_mm: np.ndarray) -> np.ndarray:
    out = W.copy()
    out[:3, 3] += shift_mm
    return out


def _views(
    scene: SimpleNamespace, n: int, detection_shift_mm: float, shifted: tuple[int, ...] | None = None
) -> list[FluoroView]:
    """The first ``n`` views, each with the landmarks of the CM moved by ``detection_shift_mm``
    across the beams as its detection (consistent over the views; only the views ``shifted`` where
    given, the others right)."""
    kin = CMKinematics(scene.case.config.cm_config)
    ab_cm = kin.landmarks_cm(torch.as_tensor(scene.cp)).numpy()
    W = _moved(scene.W, detection_shift_mm * scene.across)
    ab = ab_cm @ W[:3, :3].T + W[:3, 3]
    ab_true = ab_cm @ scene.W[:3, :3].T + scene.W[:3, 3]
    out = []
    for k, v in enumerate(scene.case.views[:n]):
        lm = v.camera.project(ab if shifted is None or k in shifted else ab_true)
        det = ViewDetection(lm, lm.copy(), np.zeros(v.image.shape, bool), np.ones(2), "case")
        out.append(FluoroView(v.name, np.asarray(v.image, np.float32), v.camera, det))
    return out


def _verify(
    scene: SimpleNamespace,
    monkeypatch: pytest.MonkeyPatch,
    *,
    n_views: int = 3,
    detection_shift_mm: float = 0.0,
    handeye_mm: float = 0.0,
    passed: dict[str, Any] | None = None,
    config: NavigationConfig | None = None,
    shifted: tuple[int, ...] | None = None,
    gap_mm: float | None = None,
) -> tuple[Any, NavigationResult, list[str]]:
    """``register_verification`` of the scene's views: its CM registration from the detections refuses
    (their landmarks ``prediction_gap_mm`` from the prediction, the views agreeing) or, with
    ``passed`` (the CM stage's diagnostics), stands at a pose ``motion_tip_mm`` from the prediction;
    ``shifted``: the views whose detections are moved (all by default); ``gap_mm``: the refusal's
    ``prediction_gap_mm`` (default 10 mm with a shift or a hand-eye error, else 0.5 mm).
    → (the registration or the refusal, the result, what was registered: "bones")."""
    views = _views(scene, n_views, detection_shift_mm, shifted)
    cameras = tuple(v.camera for v in views)
    femur = SimpleNamespace(world_from_bone=np.eye(4))
    bones = ViewSetBones(pelvis=(), cameras=cameras, femur=femur)  # type: ignore[arg-type]
    calls: list[str] = []

    def register_view_set(views_: list[FluoroView], volume: Any, **kw: Any) -> ViewSetRegistration:
        with kw["recorder"]("cm") as rec:
            if passed is not None:
                rec.diagnostics.update(passed)
                cm = SimpleNamespace(control_points_deg=scene.cp, name="from the detections")
                return ViewSetRegistration(tuple(views_), (), cameras, femur, cm)  # type: ignore[arg-type]
            gap = gap_mm if gap_mm is not None else OFFSET_MM if detection_shift_mm or handeye_mm else 0.5
            rec.diagnostics.update(prediction_gap_mm=gap, init_cost_px=1.0, views={}, views_used=[])
            rec.passed = False
        raise RegistrationRefused("cm", "landmark_residual", "registered landmarks 11.9 mm off", view="view0")

    def register_bones(*args: Any, **kw: Any) -> ViewSetBones:
        calls.append("bones")
        return bones

    monkeypatch.setattr(verification, "register_view_set", register_view_set)
    monkeypatch.setattr(verification, "register_view_set_bones", register_bones)
    cfg = config or NavigationConfig(device="cpu", seed=0, preflight=None)
    result = NavigationResult(config=cfg)
    result.first = SimpleNamespace(cm=SimpleNamespace(control_points_deg=scene.cp))  # type: ignore[assignment]
    result.stages["verify_detect"] = StageRecord()
    predicted = _moved(scene.W, handeye_mm * scene.across)
    prior = ViewSetPrior(np.eye(4), predicted, predicted, cfg.safety.max_motion_tip_mm, 1.0)
    case = SimpleNamespace(
        cm_config=scene.case.config.cm_config, volume=None, side="left", verification=object()
    )
    try:
        out: Any = verification.register_verification(
            views,
            case,  # type: ignore[arg-type]
            result,
            prior,
            local=False,
            seed=0,
            recorder=StageTimer(result.stages).within("verify_"),
        )
    except NavigationRefused as exc:
        out = exc
    return out, result, calls


def test_a_wrong_structure_detected_is_named_and_the_cm_at_the_prediction_goes_on(
    scene: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The detections 10 mm off, the kinematics right: the CM registered at the prediction fits every
    image, so the detection, not the hand-eye matrix, is named, and the verification goes on with it."""
    reg, res, calls = _verify(scene, monkeypatch, detection_shift_mm=OFFSET_MM)
    assert isinstance(reg, ViewSetRegistration), reg
    assert calls == ["bones"]
    diag = res.stages["verify_cm"].diagnostics
    assert res.stages["verify_cm"].passed is True
    assert diag["at_prediction"]["images_side_with"] == "detection"
    assert diag["motion_tip_mm"] < 1.0 and all(v["edge_ncc"] > 0.9 for v in diag["views"].values())
    off = diag["detection_disagrees"]
    assert set(off) == {f"{v.name} (verify)" for v in scene.case.views} and min(off.values()) > 5.0
    assert diag["from_detections"]["views_used"] == []  # the detections' registration, kept aside
    assert len(res.warnings) == 1 and res.warnings[0].startswith(
        "detection_disagrees: the landmarks detected"
    )
    assert "hand-eye matrix and the joint readings agree with the images" in res.warnings[0]
    tip = CMKinematics(scene.case.config.cm_config).tip_cm(torch.as_tensor(scene.cp)).numpy()
    true_tip = scene.W[:3, :3] @ tip + scene.W[:3, 3]
    assert np.linalg.norm(reg.tip_ct_mm - true_tip) < 1.0


def test_a_wrong_detection_is_refused_naming_it_where_the_settings_do_not_go_on(
    scene: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = NavigationConfig(
        device="cpu", seed=0, preflight=None, verification=VerificationConfig(go_on_at_prediction=False)
    )
    exc, res, _ = _verify(scene, monkeypatch, detection_shift_mm=OFFSET_MM, config=cfg)
    assert isinstance(exc, NavigationRefused)
    assert (exc.stage, exc.check) == ("verify_cm", "detection_disagrees")
    assert exc.view == ", ".join(f"{v.name} (verify)" for v in scene.case.views)
    assert "the detector found another structure" in exc.detail and "hand-eye matrix" in exc.detail
    assert "go_on_at_prediction is off" in exc.detail and not res.warnings


def test_a_handeye_matrix_off_with_right_detections_names_the_kinematics(
    scene: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The prediction 10 mm from the CM (a hand-eye matrix that is off), the detections right: no CM
    at the prediction, the refusal names the hand-eye matrix and the joint readings as before."""
    handeye_mm = FAULTS["handeye_10mm"].handeye_error_mm
    assert handeye_mm is not None
    exc, res, _ = _verify(scene, monkeypatch, handeye_mm=handeye_mm)
    assert isinstance(exc, NavigationRefused)
    assert (exc.stage, exc.check, exc.view) == ("verify_cm", "kinematics_disagree", "view0")
    at = res.stages["verify_cm"].diagnostics["at_prediction"]
    assert at["images_side_with"] == "kinematics" and at["motion_tip_mm"] > 3.0  # no CM stays there
    assert "check the hand-eye matrix and the joint readings" in exc.detail
    assert "registered from the kinematic prediction on the images alone, the CM's outline fits" in exc.detail
    assert f"ends {at['motion_tip_mm']:.1f} mm from the prediction" in exc.detail
    assert exc.detail.endswith("(landmark_residual: registered landmarks 11.9 mm off)")


def test_one_verification_view_says_it_cannot_tell(
    scene: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    exc, res, calls = _verify(scene, monkeypatch, n_views=1, detection_shift_mm=OFFSET_MM)
    assert isinstance(exc, NavigationRefused) and exc.check == "detection_or_kinematics"
    assert (
        "one image cannot tell whether its detection" in exc.detail
        and "second verification view" in exc.detail
    )
    assert calls == [] and "at_prediction" not in res.stages["verify_cm"].diagnostics


def test_a_view_check_refusal_where_the_detections_agree_goes_on_at_the_prediction(
    scene: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The detections' registration refused on a view's check, its detections 0.5 mm from the
    prediction and right: the CM registered at the prediction fits every view, and it goes on with
    that CM, saying why."""
    reg, res, calls = _verify(scene, monkeypatch)
    assert isinstance(reg, ViewSetRegistration), reg
    assert calls == ["bones"] and res.stages["verify_cm"].passed is True
    diag = res.stages["verify_cm"].diagnostics
    assert diag["at_prediction"]["images_side_with"] == "neither" and diag["detection_disagrees"] == {}
    assert len(res.warnings) == 1 and res.warnings[0].startswith(
        "landmark_residual: the CM registered from the detections failed its checks in view0 "
        "(registered landmarks 11.9 mm off); registered from the kinematic prediction on the images alone"
    )


def test_one_wrong_detection_that_failed_a_view_check_is_named(
    scene: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One view's detection 10 mm off, the others right, the detections' CM within the bound of the
    prediction and refused on that view's check: the CM at the prediction fits every view and that
    view's detection is named."""
    reg, res, calls = _verify(scene, monkeypatch, detection_shift_mm=OFFSET_MM, shifted=(1,), gap_mm=1.5)
    assert isinstance(reg, ViewSetRegistration) and calls == ["bones"], reg
    off = res.stages["verify_cm"].diagnostics["detection_disagrees"]
    name = f"{scene.case.views[1].name} (verify)"
    assert list(off) == [name] and off[name] > 5.0
    assert len(res.warnings) == 1 and res.warnings[0].startswith(
        "detection_disagrees: the landmarks detected in"
    )
    assert (
        "the CM registered from the detections failed its checks (landmark_residual in view0"
        in res.warnings[0]
    )


def test_a_view_check_refusal_stands_where_no_cm_fits_at_the_prediction(
    scene: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The prediction 10 mm from the CM and the refusal's gap within the bound: no CM at the
    prediction, the refusal stands as it was."""
    exc, res, calls = _verify(scene, monkeypatch, handeye_mm=OFFSET_MM, gap_mm=0.5)
    assert isinstance(exc, NavigationRefused) and exc.check == "landmark_residual" and calls == ["bones"]
    assert res.stages["verify_cm"].diagnostics["at_prediction"]["motion_tip_mm"] > 3.0 and not res.warnings


def test_a_registration_that_stood_on_the_wrong_structure_is_replaced_by_the_cm_at_the_prediction(
    scene: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The detections' CM passed its checks 10 mm from the prediction (on the other structure): the
    CM at the prediction fits the images, the detections lie elsewhere: it goes on with that CM."""
    passed = {"motion_tip_mm": OFFSET_MM, "views_used": ["view0 (verify)"], "views": {}, "tries": 1}
    reg, res, calls = _verify(scene, monkeypatch, detection_shift_mm=OFFSET_MM, passed=passed)
    assert isinstance(reg, ViewSetRegistration) and calls == []  # its own bones
    diag = res.stages["verify_cm"].diagnostics
    assert diag["from_detections"]["motion_tip_mm"] == OFFSET_MM and diag["motion_tip_mm"] < 1.0
    assert getattr(reg.cm, "name", "") != "from the detections" and res.warnings


def test_a_registration_that_stood_on_the_cm_is_left_to_the_correct_stage_where_the_kinematics_are_off(
    scene: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A hand-eye matrix 10 mm off and the detections' CM where the images show it: the CM at the
    prediction does not fit, the registration stands (the kinematics are judged in ``correct``)."""
    passed = {"motion_tip_mm": OFFSET_MM, "views_used": ["view0 (verify)"], "views": {}, "tries": 1}
    reg, res, _ = _verify(scene, monkeypatch, handeye_mm=OFFSET_MM, passed=passed)
    assert isinstance(reg, ViewSetRegistration) and getattr(reg.cm, "name", "") == "from the detections"
    diag = res.stages["verify_cm"].diagnostics
    assert diag["at_prediction"]["images_side_with"] == "kinematics" and diag["motion_tip_mm"] == OFFSET_MM
    assert not res.warnings


@pytest.mark.parametrize(
    ("ncc", "offsets", "tip_mm", "side"),
    [
        ((0.9, 0.9, 0.9), (12.0, 11.0, 0.4), 0.5, "detection"),  # two views' detections off
        ((0.9, 0.9, 0.9), (0.4, 0.5, 0.4), 0.5, "neither"),  # the detections agree with it
        ((0.9, 0.9, 0.9), (12.0, 11.0, 0.4), 4.0, "kinematics"),  # it left the prediction
        ((0.9, 0.3, 0.2), (12.0, 11.0, 0.4), 0.5, "kinematics"),  # one view alone fits: no CM there
        ((0.9, 0.9, 0.2), (0.4, 0.5, 12.0), 0.5, "neither"),  # the view off does not fit
    ],
)
def test_the_images_side_with_the_detection_only_where_the_cm_at_the_prediction_fits_them(
    ncc: tuple[float, ...], offsets: tuple[float, ...], tip_mm: float, side: str
) -> None:
    names = ("a", "b", "c")
    at = ImagesAtPrediction(
        cm=SimpleNamespace(),  # type: ignore[arg-type]
        edge_ncc=dict(zip(names, ncc, strict=True)),
        detection_offset_mm=dict(zip(names, offsets, strict=True)),
        motion_tip_mm=tip_mm,
        motion_rotation_deg=0.0,
    )
    assert images_side_with(at, CMCheckConfig(), SafetyConfig()) == side
    assert set(at.to_dict()["views"]) == set(names)
