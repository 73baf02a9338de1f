"""The registration studies in a simulated world (``fluoronav study WORKFLOW --world``;
:mod:`fluoronav.studies.world_trials`): the ideal world is the studies' trials as before, bit for
bit, and each source changes what it should of the images, of what the registration is given and of
the truth (the sources themselves: tests/simulation; in the navigation: tests/navigation)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import fluoronav.studies.pipeline as pipeline
from fluoronav.errors import InputError
from fluoronav.geometry.camera import Camera
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.runner import finish_row, new_row
from fluoronav.simulation.articulated import anatomy_and_simulator
from fluoronav.simulation.instrument import InstrumentWorld
from fluoronav.simulation.protocol import sample_trial, simulate_trial_images
from fluoronav.simulation.world import (
    IDEAL,
    CArmWorld,
    CTWorld,
    FBGWorld,
    MotionWorld,
    World,
    load_world,
)
from fluoronav.studies.pipeline import StudyConfig, run_study, run_trial
from fluoronav.studies.world_trials import WorldTrial, simulate_world_trial, world_rng

SIZE = 128  # simulated images only (the registrations need ≥ 384)
SEED = 7


def _world_trial(
    workflow: str,
    world: World,
    rng: np.random.Generator | None = None,
    world_generator: np.random.Generator | None = None,
) -> WorldTrial:
    return simulate_world_trial(
        workflow,
        "phantom",
        0,
        world,
        image_size=SIZE,
        device="cpu",
        rng=np.random.default_rng(SEED) if rng is None else rng,
        world_rng=world_rng(SEED) if world_generator is None else world_generator,
    )


def _legacy(
    workflow: str, ct: str, phantom_seed: int, image_size: int, device: str, rng: np.random.Generator
) -> WorldTrial:
    """A trial as the studies simulated it before worlds: the protocol on the CT, its images with its
    cameras, the registration given both."""
    volume, simulator = anatomy_and_simulator(ct, phantom_seed, image_size, device)
    trial = sample_trial(workflow, volume, rng)
    images = simulate_trial_images(trial, simulator, seed=int(rng.integers(2**31)), image_size=image_size)
    cameras = tuple(im.camera for im in images)
    return WorldTrial(volume, volume, trial, images, cameras, trial.oracle_landmarks_px, None)


_Generators = tuple[np.random.Generator, np.random.Generator]


@pytest.fixture(scope="module")
def ideal_runs() -> dict[str, tuple[WorldTrial, _Generators]]:
    """Per workflow an ideal world's trial and its generators after it (the trial's, the world's)."""
    out = {}
    for wf in ("single-view", "multi-view", "multi-cm"):
        rng, world_generator = np.random.default_rng(SEED), world_rng(SEED)
        out[wf] = (_world_trial(wf, IDEAL, rng, world_generator), (rng, world_generator))
    return out


@pytest.fixture(scope="module")
def ideal(ideal_runs: dict[str, tuple[WorldTrial, _Generators]]) -> dict[str, WorldTrial]:
    return {wf: run[0] for wf, run in ideal_runs.items()}


def _same_images(a: WorldTrial, b: WorldTrial) -> bool:
    return all(np.array_equal(u.image, v.image) for u, v in zip(a.images, b.images, strict=True))


def _same_camera(a: Camera, b: Camera) -> bool:
    return bool(
        (a.rows, a.cols, a.pixel_spacing_mm) == (b.rows, b.cols, b.pixel_spacing_mm)
        and np.array_equal(a.K, b.K)
        and np.array_equal(a.camera_from_world, b.camera_from_world)
    )


def _stored_scale(w: WorldTrial) -> float:
    """Stored pixels per full-detector pixel."""
    return w.images[0].camera.cols / w.trial.cameras[0].cols


@pytest.mark.parametrize("workflow", ["single-view", "multi-view", "multi-cm"])
def test_the_ideal_world_simulates_the_trial_of_the_studies_before_worlds(
    workflow: str, ideal_runs: dict[str, tuple[WorldTrial, _Generators]]
) -> None:
    w, (trial_generator, world_generator) = ideal_runs[workflow]
    rng = np.random.default_rng(SEED)
    old = _legacy(workflow, "phantom", 0, SIZE, "cpu", rng)
    assert _same_images(w, old)
    for u, v in zip(w.images, old.images, strict=True):
        assert np.array_equal(u.mask, v.mask) and np.array_equal(u.landmarks_px, v.landmarks_px)
        assert _same_camera(u.camera, v.camera)
    for f in dataclasses.fields(w.trial):
        a, b = getattr(w.trial, f.name), getattr(old.trial, f.name)
        if f.name == "cameras":
            assert all(_same_camera(u, v) for u, v in zip(a, b, strict=True))
        else:
            assert a == b if not isinstance(a, np.ndarray) else np.array_equal(a, b), f.name
    # the registration is given the images' own cameras, the CT they are rendered from, the oracle
    assert all(c is im.camera for c, im in zip(w.cameras, w.images, strict=True))
    assert w.case_ct is w.patient and w.oracle_landmarks_px is w.trial.oracle_landmarks_px
    assert w.tip_cm_true is None
    # the trial's generator made the same draws as before worlds, the world's none
    assert trial_generator.bit_generator.state == rng.bit_generator.state
    assert world_generator.bit_generator.state == world_rng(SEED).bit_generator.state


def _study_row(cfg: StudyConfig, seed: int, monkeypatch: pytest.MonkeyPatch | None = None) -> dict[str, Any]:
    if monkeypatch is not None:  # the studies' simulation before worlds

        def legacy(workflow: str, ct: str, phantom_seed: int, world: World, **kw: Any) -> WorldTrial:
            assert world is IDEAL
            return _legacy(workflow, ct, phantom_seed, kw["image_size"], kw["device"], kw["rng"])

        monkeypatch.setattr(pipeline, "simulate_world_trial", legacy)
    row = run_trial(0, seed, cfg=cfg)
    for k in ("seconds", "seconds_registration", "seconds_bones"):
        row.pop(k, None)
    return row


ROW_CFG = StudyConfig(
    workflow="centerline", trials=1, seed=0, oracle_landmarks=True, image_size=384, register_bones=False
)


@pytest.mark.parametrize("workflow", ["centerline", pytest.param("single-view", marks=pytest.mark.slow)])
def test_the_ideal_world_leaves_a_trials_row_unchanged(
    workflow: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = dataclasses.replace(ROW_CFG, workflow=workflow)
    row = _study_row(cfg, 1234)
    assert row["status"] == "ok", row["reason"]
    before = _study_row(cfg, 1234, monkeypatch)
    assert row == before


def test_the_c_arm_source_flexes_each_position_once_and_gives_the_case_a_calibration_error(
    ideal: dict[str, WorldTrial],
) -> None:
    carm = CArmWorld(sdd_error_sd_frac=0.01, principal_point_error_sd_px=6.0, flex_detector_shift_mm=1.0)
    w, ref = _world_trial("multi-cm", World(name="carm", carm=carm)), ideal["multi-cm"]
    s = _stored_scale(w)
    # one C-arm position: one flexed camera for its four images and one case camera
    assert all(_same_camera(im.camera, w.images[0].camera) for im in w.images)
    assert all(c is w.cameras[0] for c in w.cameras)
    flexed, nominal, case = w.images[0].camera, ref.images[0].camera, w.cameras[0]
    np.testing.assert_array_equal(flexed.camera_from_world, nominal.camera_from_world)
    np.testing.assert_array_equal(case.camera_from_world, nominal.camera_from_world)
    shift_px = np.linalg.norm(flexed.K[:2, 2] - nominal.K[:2, 2]) / s  # full-detector pixels
    np.testing.assert_allclose(shift_px, 1.0 / carm.detector_pixel_mm, rtol=1e-9)
    np.testing.assert_array_equal(flexed.K[:2, :2], nominal.K[:2, :2])  # the flex shifts only
    ratio = case.K[0, 0] / nominal.K[0, 0]
    assert ratio != 1.0 and abs(ratio - 1.0) < 0.05  # the case's focal length is off
    assert not _same_images(w, ref)
    # the oracle landmarks move with the images' (the protocol's noise kept)
    moved = (w.oracle_landmarks_px - ref.oracle_landmarks_px) * s
    for im, r, m in zip(w.images, ref.images, moved, strict=True):
        np.testing.assert_allclose(m, im.landmarks_px - r.landmarks_px, atol=1e-6)


def test_the_c_arm_flex_alone_gives_the_case_the_nominal_cameras(ideal: dict[str, WorldTrial]) -> None:
    w = _world_trial("multi-view", World(name="flex", carm=CArmWorld(flex_detector_shift_mm=1.0)))
    for case, im, ref in zip(w.cameras, w.images, ideal["multi-view"].images, strict=True):
        np.testing.assert_array_equal(case.K, ref.camera.K)  # nominal: the flex is not known
        assert not np.array_equal(im.camera.K, ref.camera.K)


def test_the_fbg_source_reads_the_true_shape_and_changes_nothing_else(ideal: dict[str, WorldTrial]) -> None:
    w, ref = _world_trial("single-view", World(name="fbg", fbg=FBGWorld(bias_deg=0.3))), ideal["single-view"]
    np.testing.assert_allclose(
        np.abs(w.trial.initial_control_points_deg - w.trial.control_points_deg), 0.3, atol=1e-12
    )
    assert _same_images(w, ref) and np.array_equal(w.trial.world_from_cm, ref.trial.world_from_cm)
    assert np.array_equal(w.trial.oracle_landmarks_px, ref.trial.oracle_landmarks_px)


def test_the_instrument_source_shows_the_cm_as_built_and_its_tip_is_the_truth(
    ideal: dict[str, WorldTrial],
) -> None:
    instrument = dataclasses.replace(InstrumentWorld.realistic(), angle_scale_sd=0.3)
    w, ref = (
        _world_trial("single-view", World(name="instrument", instrument=instrument)),
        ideal["single-view"],
    )
    assert w.tip_cm_true is not None
    cp = torch.as_tensor(w.trial.control_points_deg, dtype=torch.float64)
    assert np.linalg.norm(w.tip_cm_true - CMKinematics().tip_cm(cp).numpy()) > 0.05
    assert np.array_equal(w.trial.world_from_cm, ref.trial.world_from_cm)  # the same pose, another CM
    assert not _same_images(w, ref)
    # the oracle's B is the built CM's, where the image shows it
    moved = (w.oracle_landmarks_px[0] - ref.oracle_landmarks_px[0]) * _stored_scale(w)
    np.testing.assert_allclose(moved, w.images[0].landmarks_px - ref.images[0].landmarks_px, atol=1e-6)
    assert np.linalg.norm(moved[1]) > 0.0 and np.allclose(moved[0], 0.0, atol=1e-9)


def test_motion_within_a_set_moves_the_anatomy_of_each_view_not_of_a_lone_one(
    ideal: dict[str, WorldTrial],
) -> None:
    world = World(name="motion", motion=MotionWorld(within_set_mm=3.0, within_set_deg=1.0))
    w, ref = _world_trial("multi-view", world), ideal["multi-view"]
    for im, r in zip(w.images, ref.images, strict=True):
        assert np.abs(im.image - r.image).mean() > 1e-3
        assert np.array_equal(im.landmarks_px, r.landmarks_px)  # the robot's CM stays
    assert np.array_equal(w.trial.world_from_patient, ref.trial.world_from_patient)  # the truth: the set's
    # one image is its own set: nothing moves, nothing is drawn
    assert _same_images(_world_trial("single-view", world), ideal["single-view"])
    between = World(name="between", motion=MotionWorld(between_sets_mm=3.0, between_sets_deg=1.0))
    assert _same_images(_world_trial("multi-view", between), ref)


def test_the_ct_source_renders_the_patient_and_gives_the_registration_the_case_ct(
    ideal: dict[str, WorldTrial],
) -> None:
    # a coarse patient: the realistic 0.5 mm one takes GBs
    world = World(
        name="ct", ct=CTWorld(patient_spacing_mm=1.0, ct_spacing_mm=(2.0, 2.0, 2.0), hu_noise_sd=15)
    )
    w, ref = _world_trial("single-view", world), ideal["single-view"]
    assert w.case_ct is not w.patient and w.case_ct.spacing_mm == (2.0, 2.0, 2.0)
    assert w.patient.spacing_mm == (1.0, 1.0, 1.0)
    # the 1 mm patient is the studies' phantom: the same images, the same truth; the CT is coarser
    assert _same_images(w, ref)
    np.testing.assert_array_equal(w.trial.femoral_head_ct, w.patient.landmarks_world["femoral_head_left"])


# ----- the study: a trial's errors, its records, the CLI ------------------------------------------
def test_the_tip_error_of_a_built_instrument_is_measured_against_its_own_tip() -> None:
    instrument = dataclasses.replace(InstrumentWorld.realistic(), angle_scale_sd=0.3)
    world = World(name="instrument", instrument=instrument, fbg=FBGWorld(noise_sd_deg=0.1))
    cfg = dataclasses.replace(ROW_CFG, world=world)
    row = _study_row(cfg, 1234)
    assert row["status"] == "ok", row["reason"]
    rng = np.random.default_rng(1234)
    phantom_seed = 1000 * cfg.seed + int(rng.integers(cfg.n_phantoms))
    w = simulate_world_trial(
        "single-view",
        "phantom",
        phantom_seed,
        world,
        image_size=384,
        device="cpu",
        rng=rng,
        world_rng=world_rng(1234),
    )
    assert w.tip_cm_true is not None
    kin = CMKinematics(w.trial.cm_config)
    cp_est = torch.as_tensor(w.trial.initial_control_points_deg, dtype=torch.float64)  # the centreline's
    W_est, W_true = np.asarray(row["est_world_from_cm"]), np.asarray(row["true_world_from_cm"])
    tip_est = W_est[:3, :3] @ kin.tip_cm(cp_est).numpy() + W_est[:3, 3]
    tip_true = W_true[:3, :3] @ w.tip_cm_true + W_true[:3, 3]
    model_tip = kin.tip_cm(torch.as_tensor(w.trial.control_points_deg, dtype=torch.float64)).numpy()
    assert np.linalg.norm(w.tip_cm_true - model_tip) > 0.05  # the truth is not the model's tip
    np.testing.assert_allclose(row["tip_mm"], np.linalg.norm(tip_est - tip_true), atol=2e-3)


def _fake_trial(trial_id: int, seed: int, *, cfg: StudyConfig) -> dict[str, Any]:
    row = new_row(trial_id, seed, cfg.workflow)
    row["tip_mm"] = 1.0
    return finish_row(row, 0.0)


def test_a_study_records_its_world_and_resumes_only_in_it(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(pipeline, "run_trial", _fake_trial)
    monkeypatch.setattr(pipeline, "study_figures", lambda rows, out, workflow: None)
    world = World(name="fbg", fbg=FBGWorld(noise_sd_deg=0.1))
    cfg = StudyConfig(workflow="multi-view", trials=1, seed=0, oracle_landmarks=True, world=world)
    summary = run_study(cfg, tmp_path / "s", workers=0)
    assert summary["world"] == world.to_dict()
    for name in ("config.json", "summary.json"):
        recorded = json.loads((tmp_path / "s" / name).read_text(encoding="utf-8"))["world"]
        assert recorded == world.to_dict()
        assert load_world(str(_write(tmp_path / f"{name}.world.json", recorded))) == world
    with pytest.raises(InputError, match="other settings"):
        run_study(dataclasses.replace(cfg, world=IDEAL), tmp_path / "s", workers=0)
    # a study from before worlds ran in the ideal one: it resumes there
    ideal_cfg = dataclasses.replace(cfg, world=IDEAL)
    run_study(ideal_cfg, tmp_path / "old", workers=0)
    path = tmp_path / "old" / "config.json"
    d = json.loads(path.read_text(encoding="utf-8"))
    del d["world"]
    path.write_text(json.dumps(d), encoding="utf-8")
    assert run_study(dataclasses.replace(ideal_cfg, trials=2), tmp_path / "old", workers=0)["completed"] == 2


def _write(path: Path, d: dict[str, Any]) -> Path:
    path.write_text(json.dumps(d), encoding="utf-8")
    return path


def test_the_cli_gives_a_registration_study_its_world_and_refuses_it_elsewhere(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from fluoronav.cli.main import main

    seen: list[StudyConfig] = []

    def record(cfg: StudyConfig, out: Path, **kw: object) -> dict[str, Any]:
        seen.append(cfg)
        return {"completed": 0, "trials": cfg.trials, "failed": 0, "metrics": {}}

    monkeypatch.setattr(pipeline, "run_study", record)
    path = _write(tmp_path / "small.json", {"fbg": {"bias_deg": 0.1}})
    base = ["study", "--trials", "1", "--seed", "0", "--out", str(tmp_path / "out")]
    main([base[0], "multi-view", *base[1:], "--world", str(path)])
    main([base[0], "centerline", *base[1:]])
    assert [c.world for c in seen] == [World(name="small", fbg=FBGWorld(bias_deg=0.1)), IDEAL]
    with pytest.raises(SystemExit) as exc:
        main([base[0], "hand-eye", *base[1:], "--world", "realistic"])
    assert exc.value.code == 2  # a usage error: study hand-eye has no --world option
    assert "No such option: --world" in capsys.readouterr().err
