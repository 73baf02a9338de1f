"""The world's config (presets, JSON) and its C-arm, FBG and motion errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from fluoronav.errors import InputError
from fluoronav.geometry.camera import CIOS_FUSION, Camera
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.simulation.world import (
    IDEAL,
    REALISTIC,
    CArmWorld,
    FBGWorld,
    MotionWorld,
    World,
    case_camera,
    fbg_reading,
    flexed_camera,
    load_world,
    patient_motion,
)


def _camera() -> Camera:
    pose = np.eye(4)
    pose[:3, 3] = (5.0, -3.0, 450.0)  # world origin 450 mm from the source
    return Camera.from_detector(CIOS_FUSION, pose)


def _points() -> np.ndarray:
    return np.array([[0.0, 0.0, 0.0], [40.0, -25.0, 10.0], [-60.0, 30.0, -20.0]])


def test_ideal_is_identity_and_draws_nothing() -> None:
    rng = np.random.default_rng(1)
    state = rng.bit_generator.state
    cam = _camera()
    cp = np.array([1.0, -2.0, 0.5, 3.0, -1.0])
    assert case_camera(cam, IDEAL.carm, rng) is cam
    assert flexed_camera(cam, IDEAL.carm, rng) is cam
    assert fbg_reading(cp, IDEAL.fbg, rng) is cp
    m = IDEAL.motion
    for t, r in ((m.between_sets_mm, m.between_sets_deg), (m.within_set_mm, m.within_set_deg)):
        assert np.array_equal(patient_motion(t, r, rng, center_world=np.ones(3)), np.eye(4))
    assert rng.bit_generator.state == state
    assert IDEAL.is_ideal and not REALISTIC.is_ideal
    assert World() == IDEAL


def test_case_camera_errors_of_configured_size() -> None:
    cfg = CArmWorld(sdd_error_sd_frac=0.01, principal_point_error_sd_px=3.0)
    cam = _camera()
    rng = np.random.default_rng(2)
    cams = [case_camera(cam, cfg, rng) for _ in range(2000)]
    ratio = np.array([c.K[0, 0] / cam.K[0, 0] for c in cams])
    dpp = np.array([c.K[:2, 2] - cam.K[:2, 2] for c in cams])
    assert ratio.std() == pytest.approx(0.01, rel=0.1)
    assert abs(ratio.mean() - 1.0) < 0.001
    assert dpp.std(axis=0) == pytest.approx([3.0, 3.0], rel=0.1)
    c = cams[0]
    assert np.array_equal(c.camera_from_world, cam.camera_from_world)
    assert c.K[1, 1] == pytest.approx(c.K[0, 0]) and c.sdd_mm == pytest.approx(1020.0 * ratio[0])
    # a point's projection moves by the focal scaling about the principal point plus its shift
    uv, uv_case = cam.project(_points()), c.project(_points())
    expected = c.K[:2, 2] + ratio[0] * (uv - cam.K[:2, 2])
    np.testing.assert_allclose(uv_case, expected, atol=1e-9)
    assert np.linalg.norm(uv_case[0] - uv[0]) > 0.1
    # on a 4× binned camera the principal point error is in the binned camera's pixels
    small = cam.downsample(4)
    dpp_small = np.array([case_camera(small, cfg, rng).K[:2, 2] - small.K[:2, 2] for _ in range(2000)])
    assert dpp_small.std() == pytest.approx(0.75, rel=0.1)


def test_flexed_camera_moves_every_projection_by_the_detector_shift() -> None:
    cfg = CArmWorld(flex_detector_shift_mm=1.0)
    cam = _camera()
    rng = np.random.default_rng(3)
    moves = []
    for _ in range(50):
        flexed = flexed_camera(cam, cfg, rng)
        d = flexed.project(_points()) - cam.project(_points())
        np.testing.assert_allclose(d, np.broadcast_to(d[0], d.shape), atol=1e-9)  # a pure translation
        assert np.linalg.norm(d[0]) == pytest.approx(1.0 / CIOS_FUSION.pixel_spacing_mm)
        assert np.array_equal(flexed.K[:2, :2], cam.K[:2, :2])
        moves.append(d[0])
    angles = np.arctan2(*np.array(moves).T)
    assert np.ptp(angles) > 3.0  # directions spread round the circle


def test_fbg_reading_noise_and_bias() -> None:
    truth = np.zeros((4000, 5))
    rng = np.random.default_rng(4)
    bias = fbg_reading(truth, FBGWorld(bias_deg=0.1), rng) - truth
    # one sign per reading, the same on its five control points, both signs drawn
    np.testing.assert_allclose(np.abs(bias), 0.1)
    assert np.all(bias == bias[:, :1])
    assert 0.45 < np.mean(bias[:, 0] > 0) < 0.55
    noise = fbg_reading(truth, FBGWorld(noise_sd_deg=0.2), rng) - truth
    assert noise.std() == pytest.approx(0.2, rel=0.03)
    assert abs(noise.mean()) < 0.01
    single = fbg_reading(np.ones(5), FBGWorld(noise_sd_deg=0.2, bias_deg=0.1), rng)
    assert single.shape == (5,) and abs(abs(single.mean() - 1.0) - 0.1) < 0.3


def test_realistic_fbg_tip_error_in_literature_range() -> None:
    """Sefati et al.: FBG tip error 0.50 ± 0.18 mm (TMECH 2021); max 0.78–2.45 mm (Sensors J 2021)."""
    kin = CMKinematics()
    rng = np.random.default_rng(5)
    truth = rng.uniform(-5.0, 5.0, (2000, 5))
    reading = fbg_reading(truth, REALISTIC.fbg, rng)

    def tip(cp: np.ndarray) -> np.ndarray:
        return kin.tip_cm(torch.as_tensor(cp, dtype=torch.float64)).numpy()

    err = np.linalg.norm(tip(reading) - tip(truth), axis=1)
    assert 0.40 <= err.mean() <= 0.60
    assert np.percentile(err, 95) <= 1.2
    assert err.max() <= 2.45


def test_patient_motion_is_rigid_of_the_given_size() -> None:
    rng = np.random.default_rng(6)
    c = np.array([10.0, -20.0, 30.0])
    T = patient_motion(2.0, 0.5, rng, center_world=c)
    R = T[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.degrees(Rotation.from_matrix(R).magnitude()) == pytest.approx(0.5)
    assert np.linalg.norm(T[:3, :3] @ c + T[:3, 3] - c) == pytest.approx(2.0)  # the centre only translates
    pure_rotation = patient_motion(0.0, 3.0, rng, center_world=c)
    np.testing.assert_allclose(pure_rotation[:3, :3] @ c + pure_rotation[:3, 3], c, atol=1e-12)


def test_load_presets_and_round_trip(tmp_path: Path) -> None:
    assert load_world("ideal") is IDEAL
    assert load_world("realistic") is REALISTIC
    p = tmp_path / "w.json"
    p.write_text(json.dumps(REALISTIC.to_dict()), encoding="utf-8")
    assert load_world(str(p)) == REALISTIC
    d = REALISTIC.to_dict()
    assert d["name"] == "realistic" and d["ct"]["ct_spacing_mm"] == [0.8, 0.8, 1.5]
    assert d["fbg"] == {"noise_sd_deg": 0.06, "bias_deg": 0.06, "stated_sigma_deg": None}
    json.dumps(d)  # JSON-ready


def test_load_subset_takes_ideal_values(tmp_path: Path) -> None:
    p = tmp_path / "fbg_only.json"
    p.write_text('{"fbg": {"noise_sd_deg": 0.5}}', encoding="utf-8")
    w = load_world(str(p))
    assert w.name == "fbg_only"
    assert w.fbg == FBGWorld(noise_sd_deg=0.5)
    assert (w.ct, w.carm, w.motion) == (IDEAL.ct, IDEAL.carm, IDEAL.motion)
    p.write_text('{"motion": {"within_set_mm": 1}, "ct": {"ct_spacing_mm": null}}', encoding="utf-8")
    assert load_world(str(p)).motion == MotionWorld(within_set_mm=1.0)


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ('{"fbg": {"noise_deg": 0.5}}', "unknown field"),
        ('{"optics": {}}', "unknown key"),
        ('{"fbg": {"noise_sd_deg": "a"}}', "non-negative number"),
        ('{"fbg": {"noise_sd_deg": null}}', "cannot be null"),
        ('{"ct": {"ct_spacing_mm": [1, 1]}}', "three positive numbers"),
        ('{"fbg": [1]}', "JSON object"),
        ('{"fbg": {"noise_sd_deg": 0.5}', "not valid JSON"),
        ("[1, 2]", "JSON object"),
    ],
)
def test_bad_world_file_is_one_line_input_error(tmp_path: Path, text: str, reason: str) -> None:
    p = tmp_path / "bad.json"
    p.write_text(text, encoding="utf-8")
    with pytest.raises(InputError, match=reason) as exc:
        load_world(str(p))
    assert "\n" not in str(exc.value) and str(p) in str(exc.value)


def test_unknown_world_name_or_missing_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="unknown world"):
        load_world("paradise")
    with pytest.raises(InputError, match="not found"):
        load_world(str(tmp_path / "missing.json"))


def test_fbg_states_its_accuracy_honestly_unless_told_otherwise(tmp_path: Path) -> None:
    """The case states the reading's RMS error (noise and bias) unless the world sets another σ; the
    ideal world's case states none; a σ that is not positive is bad input naming the file."""
    assert FBGWorld().stated_sigma() is None
    assert FBGWorld(noise_sd_deg=0.06, bias_deg=0.06).stated_sigma() == pytest.approx(0.0848528, abs=1e-6)
    assert FBGWorld(noise_sd_deg=1.5, stated_sigma_deg=0.085).stated_sigma() == 0.085
    p = tmp_path / "liar.json"
    p.write_text('{"fbg": {"noise_sd_deg": 1.5, "stated_sigma_deg": 0.0}}')
    with pytest.raises(InputError, match=r"liar\.json.*stated_sigma_deg must be positive"):
        load_world(str(p))
