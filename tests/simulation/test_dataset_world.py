"""Data sets in a simulated world and of navigation scenes: the ideal default unchanged, true labels,
the world recorded, negatives at the same views, resume."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

import fluoronav.simulation.dataset as ds
from fluoronav import __version__
from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.runner import task_seeds
from fluoronav.simulation.dataset import DatasetSpec, simulate_dataset
from fluoronav.simulation.dataset_check import check_dataset
from fluoronav.simulation.instrument import build_instrument, built_landmarks_cm
from fluoronav.simulation.scene import sample_scene
from fluoronav.simulation.world import REALISTIC, CArmWorld, World
from fluoronav.simulation.xray import SimulationConfig, XraySimulator

NAV = DatasetSpec(n_phantoms=1, image_size=64, seed=6060, phantom_spacing_mm=2.0, scenes="navigation")
#: the realistic world on a coarse patient (the 0.5 mm one is too large for a test)
COARSE_REALISTIC = dataclasses.replace(
    REALISTIC, name="realistic-coarse", ct=dataclasses.replace(REALISTIC.ct, patient_spacing_mm=2.0)
)


def _rows(d: Path) -> dict[int, dict]:
    rows = [json.loads(line) for line in (d / "manifest.jsonl").read_text().splitlines()]
    return {r["id"]: r for r in rows}


def _arrays(d: Path, row: dict) -> dict[str, np.ndarray]:
    with np.load(d / row["file"]) as z:
        return {k: z[k] for k in z.files}


def _projected(row: dict, points_cm: np.ndarray) -> np.ndarray:
    """(N, 2) points of the CM frame projected by hand with the row's K and pose."""
    K = np.asarray(row["camera"]["K"])
    camera_from_world = np.asarray(row["camera"]["camera_from_world"])
    T = camera_from_world @ np.asarray(row["world_from_cm"])
    x = (np.c_[points_cm, np.ones(len(points_cm))] @ T.T)[:, :3] @ K.T
    return x[:, :2] / x[:, 2:]


@pytest.fixture(scope="module")
def navigation(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("nav")
    simulate_dataset(d, 3, NAV, workers=0, contact_sheet_png=False)
    return d


def test_ideal_default_is_the_xray_simulators_output(tmp_path: Path) -> None:
    spec = DatasetSpec(n_phantoms=2, image_size=64, seed=5, phantom_spacing_mm=2.0)
    simulate_dataset(tmp_path, 2, spec, workers=0, contact_sheet_png=False)
    rows = _rows(tmp_path)
    for i, seed in enumerate(task_seeds(spec.seed, 2)):
        # the data set's sample as the paper's sampling and the X-ray simulator make it
        rng = np.random.default_rng(seed)
        phantom_seed = 1000 * spec.seed + int(rng.integers(2))
        sim = XraySimulator(
            hip_phantom(seed=phantom_seed, spacing_mm=2.0), config=SimulationConfig(image_size=64)
        )
        image = sim.simulate(
            sample_scene(sim.volume, rng, sampling=spec.sampling), seed=int(rng.integers(2**62))
        )
        got = _arrays(tmp_path, rows[i])
        np.testing.assert_array_equal(got["image"], image.image)
        np.testing.assert_array_equal(got["mask"], image.mask)
        np.testing.assert_array_equal(got["landmarks_px"], image.landmarks_px)
        assert rows[i]["camera"] == image.camera.to_dict()
        assert rows[i]["world"] == "ideal" and rows[i]["scene"] == "paper"
    meta = json.loads((tmp_path / "dataset.json").read_text())
    assert meta["world"]["name"] == "ideal" and meta["seed"] == 5 and meta["version"] == __version__


def test_navigation_labels_are_the_projection_of_the_cm_ends(navigation: Path) -> None:
    assert check_dataset(navigation, n=3) == []
    kin = CMKinematics(CMConfig())
    for row in _rows(navigation).values():
        assert row["scene"] == "navigation" and row["stage"] in ("working", "approach", "inserted")
        assert row["world"] == "ideal" and row["femur_side"] == "left"
        ab_cm = kin.landmarks_cm(torch.as_tensor(row["control_points_deg"], dtype=torch.float64)).numpy()
        np.testing.assert_allclose(row["landmarks_px"], _projected(row, ab_cm), atol=1e-6)
        z = _arrays(navigation, row)
        np.testing.assert_allclose(z["landmarks_px"], row["landmarks_px"])
        assert z["mask"].any()
        assert np.all((z["landmarks_px"] >= 0) & (z["landmarks_px"] <= 63))  # the CM is in the image


def test_flexed_world_labels_follow_the_imaging_camera(navigation: Path, tmp_path: Path) -> None:
    shift_mm = 2.0
    world = World(name="flex", carm=CArmWorld(flex_detector_shift_mm=shift_mm))
    simulate_dataset(tmp_path, 3, dataclasses.replace(NAV, world=world), workers=0, contact_sheet_png=False)
    ideal, flexed = _rows(navigation), _rows(tmp_path)
    kin = CMKinematics(CMConfig())
    for i, row in flexed.items():
        assert row["world"] == "flex"
        # the same scene (the world draws from its own stream), seen with the detector shifted
        assert row["world_from_cm"] == ideal[i]["world_from_cm"]
        K, K0 = np.asarray(row["camera"]["K"]), np.asarray(ideal[i]["camera"]["K"])
        shift_px = np.linalg.norm(K[:2, 2] - K0[:2, 2]) * row["pixel_spacing_mm"]
        assert shift_px == pytest.approx(shift_mm)
        ab_cm = kin.landmarks_cm(torch.as_tensor(row["control_points_deg"], dtype=torch.float64)).numpy()
        np.testing.assert_allclose(row["landmarks_px"], _projected(row, ab_cm), atol=1e-6)


def test_negatives_at_the_same_views(navigation: Path, tmp_path: Path) -> None:
    simulate_dataset(tmp_path, 3, dataclasses.replace(NAV, with_cm=False), workers=0, contact_sheet_png=False)
    assert check_dataset(tmp_path, n=3) == []
    positives = _rows(navigation)
    for i, row in _rows(tmp_path).items():
        assert row["landmarks_px"] is None and row["has_cm"] is False
        for key in ("camera", "world_from_cm", "stage", "view", "ct"):
            assert row[key] == positives[i][key]
        assert not _arrays(tmp_path, row)["mask"].any()


@pytest.mark.slow  # a data set made twice (resume, mixed): the default run's budget
def test_killed_navigation_run_resumes_to_identical_samples(
    navigation: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = ds._make_sample
    done: list[int] = []

    def crash_after_one(sample_id: int, seed: int, **kw: object) -> dict:
        if done:
            raise KeyboardInterrupt
        done.append(sample_id)
        return real(sample_id, seed, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(ds, "_make_sample", crash_after_one)
    with pytest.raises(KeyboardInterrupt):
        simulate_dataset(tmp_path, 3, NAV, workers=0, contact_sheet_png=False)
    monkeypatch.setattr(ds, "_make_sample", real)
    assert len(simulate_dataset(tmp_path, 3, NAV, workers=0, contact_sheet_png=False)) == 2
    reference = _rows(navigation)
    for i, row in _rows(tmp_path).items():
        assert row == reference[i]
        a, b = _arrays(tmp_path, row), _arrays(navigation, reference[i])
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
    with pytest.raises(ds.InputError):  # a directory keeps its world and scenes
        simulate_dataset(tmp_path, 3, dataclasses.replace(NAV, scenes="mixed"), workers=0)


@pytest.mark.slow  # a data set made twice (resume, mixed): the default run's budget
def test_mixed_paper_samples_are_the_paper_data_sets(tmp_path: Path) -> None:
    paper = DatasetSpec(n_phantoms=1, image_size=64, seed=77, phantom_spacing_mm=2.0)
    mixed = dataclasses.replace(paper, scenes="mixed", navigation_fraction=0.5)
    kinds = [mixed.scene_kind(s) for s in task_seeds(77, 4)]
    assert set(kinds) == {"paper", "navigation"}  # this seed's four samples hold both
    simulate_dataset(tmp_path / "p", 4, paper, workers=0, contact_sheet_png=False)
    simulate_dataset(tmp_path / "m", 4, mixed, workers=0, contact_sheet_png=False)
    p, m = _rows(tmp_path / "p"), _rows(tmp_path / "m")
    for i, kind in enumerate(kinds):
        assert m[i]["scene"] == kind
        if kind == "paper":
            assert m[i] == p[i]
            np.testing.assert_array_equal(
                _arrays(tmp_path / "m", m[i])["image"], _arrays(tmp_path / "p", p[i])["image"]
            )
    assert json.loads((tmp_path / "m" / "dataset.json").read_text())["spec"]["navigation_fraction"] == 0.5


def test_realistic_world_data_set(tmp_path: Path) -> None:
    spec = DatasetSpec(n_phantoms=1, image_size=64, seed=4, world=COARSE_REALISTIC, scenes="mixed")
    simulate_dataset(tmp_path, 2, spec, workers=0, contact_sheet_png=False)
    assert check_dataset(tmp_path, n=2) == []
    meta = json.loads((tmp_path / "dataset.json").read_text())
    assert meta["world"] == json.loads(json.dumps(COARSE_REALISTIC.to_dict()))
    for i, seed in enumerate(task_seeds(4, 2)):
        row = _rows(tmp_path)[i]
        assert row["world"] == "realistic-coarse"
        # the labels are those of the CM as built, drawn first from the sample's world stream
        world_rng = np.random.default_rng([ds._WORLD_STREAM, seed])
        built = build_instrument(COARSE_REALISTIC.instrument, CMConfig(), world_rng)
        ab_cm = built_landmarks_cm(built, row["control_points_deg"]).numpy()
        np.testing.assert_allclose(row["landmarks_px"], _projected(row, ab_cm), atol=1e-6)


def test_spec_is_checked() -> None:
    with pytest.raises(ValueError, match="scenes"):
        DatasetSpec(scenes="robot")
    with pytest.raises(ValueError, match="navigation_fraction"):
        DatasetSpec(scenes="mixed", navigation_fraction=1.5)
    with pytest.raises(ValueError, match="shaft"):  # the world's patient has the navigation's shaft
        DatasetSpec(world=COARSE_REALISTIC, shaft_length_mm=200.0)
    DatasetSpec(world=COARSE_REALISTIC, cts=("ct.nii.gz",), shaft_length_mm=200.0)  # no world patient


@pytest.mark.slow
def test_navigation_same_seed_same_samples_with_two_workers(navigation: Path, tmp_path: Path) -> None:
    simulate_dataset(tmp_path, 3, NAV, workers=2, contact_sheet_png=False)
    reference = _rows(navigation)
    for i, row in _rows(tmp_path).items():
        assert row == reference[i]
        a, b = _arrays(tmp_path, row), _arrays(navigation, reference[i])
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
