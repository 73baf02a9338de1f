"""``study deepfluoro`` and ``fluoronav deepfluoro`` on a synthetic file of the DeepFluoro layout."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk  # noqa: N813

from fluoronav.cli.main import main
from fluoronav.geometry import se3
from fluoronav.geometry.camera import Camera
from fluoronav.simulation.deepfluoro_synthetic import SyntheticDeepFluoro
from fluoronav.simulation.protocol import perturb_about
from fluoronav.studies.deepfluoro import DeepFluoroStudyConfig, pelvis_errors, run_deepfluoro_study
from fluoronav.studies.deepfluoro_view import detector_image


def test_pelvis_errors_of_a_known_motion() -> None:
    K = np.array([[1000.0, 0.0, 49.5], [0.0, 1000.0, 49.5], [0.0, 0.0, 1.0]])
    cam = Camera(100, 100, K, se3.make(np.eye(3), [0.0, 0.0, 500.0]), pixel_spacing_mm=0.5)
    marks = {"a": np.array([30.0, 0.0, 0.0]), "b": np.array([-30.0, 0.0, 0.0])}
    c = np.zeros(3)
    rot = perturb_about(np.eye(4), c, np.random.default_rng(0), rotation_deg=2.0, translation_mm=0.0)
    e = pelvis_errors(rot, marks, cam, c)
    assert e["rotation_deg"] == pytest.approx(2.0) and e["translation_mm"] == pytest.approx(0.0, abs=1e-9)
    shift = se3.make(np.eye(3), [0.0, 0.0, 3.0])  # along the beam: 3 mm in 3D, little at the detector
    e = pelvis_errors(shift, marks, cam, c)
    assert e["mtre_mm"] == pytest.approx(3.0) and e["translation_mm"] == pytest.approx(3.0)
    assert e["reprojection_mm"] == pytest.approx(1000.0 * 30.0 * (1 / 500 - 1 / 503) * 0.5)


def test_study_recovers_the_pelvis_from_perturbed_starts(
    deepfluoro_file: SyntheticDeepFluoro, tmp_path: Path
) -> None:
    out = tmp_path / "df"
    cfg = DeepFluoroStudyConfig(data=str(deepfluoro_file.path), seed=11)
    summary = run_deepfluoro_study(cfg, out, workers=0)
    rows = list(csv.DictReader((out / "trials.csv").open(encoding="utf-8")))
    assert [int(r["projection"]) for r in rows] == [0, 1, 2] and summary["trials"] == 3
    for r in rows:
        assert r["status"] == "ok", r["reason"]
        assert float(r["start_rotation_deg"]) == pytest.approx(3.0)
        assert float(r["start_mtre_mm"]) > 5.0
        assert float(r["rotation_deg"]) < 0.5 and float(r["mtre_mm"]) < 1.0
        assert float(r["translation_mm"]) < 1.0 and float(r["reprojection_mm"]) < 1.0
        assert float(r["gt_landmark_residual_px"]) < 1e-6 and r["checks_passed"] == "True"
    assert rows[2]["rot_180_for_up"] == "True"
    assert summary["workflow"] == "deepfluoro" and summary["within_1deg"] == 1.0
    assert summary["within_mtre_mm"]["1"] == 1.0 and summary["checks"]["passed"] == 3
    assert "xReg (Grupp et al., IJCARS 15(5):759-769, 2020)" in summary["anchors"]
    assert (out / "figures" / "deepfluoro_errors.png").is_file()
    # a rerun resumes: nothing to do, the rows stay
    before = (out / "trials.csv").read_text(encoding="utf-8")
    run_deepfluoro_study(cfg, out, workers=0)
    assert (out / "trials.csv").read_text(encoding="utf-8") == before
    # and fluoronav report shows it beside the published figures
    main(["report", str(out), "--out", str(tmp_path / "r")])
    md = (tmp_path / "r" / "table_i.md").read_text(encoding="utf-8")
    assert "Real data: DeepFluoro" in md and "| 3/3 | 100 % | 100 % |" in md and "| 86 % |" in md


def test_study_refuses_other_settings_in_the_same_directory(
    deepfluoro_file: SyntheticDeepFluoro, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "config.json").write_text(json.dumps({"workflow": "deepfluoro", "seed": 1}), encoding="utf-8")
    with pytest.raises(SystemExit) as info:
        main(
            [
                "study",
                "deepfluoro",
                "--data",
                str(deepfluoro_file.path),
                "--seed",
                "2",
                "--out",
                str(tmp_path),
            ]
        )
    assert info.value.code == 2 and "other settings" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main(["study", "deepfluoro", "--seed", "2", "--out", str(tmp_path / "x")])
    assert info.value.code == 2 and "--data" in capsys.readouterr().err


def test_detector_image_lies_on_the_detector_plane() -> None:
    cam = Camera(
        rows=40,
        cols=60,
        K=np.array([[500.0, 0.0, 31.0], [0.0, 500.0, 18.5], [0.0, 0.0, 1.0]]),
        camera_from_world=se3.make(np.eye(3)[[1, 0, 2]] * [[1], [-1], [1]], [5.0, -7.0, 400.0]),
        pixel_spacing_mm=2.0,
    )
    img = sitk.Image(detector_image(np.zeros((40, 60), np.float32), cam))
    for u, v in ((0, 0), (31, 18.5), (59, 39)):
        p = np.asarray(img.TransformContinuousIndexToPhysicalPoint((float(u), float(v), 0.0)))
        # on the ray through pixel (u, v), at the source-to-detector distance (1000 mm) in depth
        np.testing.assert_allclose(cam.project(p), [u, v], atol=1e-9)
        assert cam.to_camera(p)[2] == pytest.approx(1000.0)


@pytest.mark.slow
def test_one_projection_with_slicer_files(deepfluoro_file: SyntheticDeepFluoro, tmp_path: Path) -> None:
    out = tmp_path / "view"
    args = ["deepfluoro", "--data", str(deepfluoro_file.path), "--specimen", "1", "--projection", "1"]
    main([*args, "--out", str(out), "--seed", "4", "--device", "cpu"])
    reg = json.loads((out / "registration.json").read_text(encoding="utf-8"))
    assert reg["errors"]["rotation_deg"] < 0.5 and reg["errors"]["mtre_mm"] < 1.0
    assert reg["errors"]["femur_left_rotation_deg"] < 2.0 and "femur_right_rotation_deg" not in reg["errors"]
    names = {p.name for p in (out / "slicer").iterdir()}
    assert {"xray.nrrd", "pelvis.vtk", "femur_left.vtk", "ct_from_camera.h5", "source.mrk.json"} <= names
    assert (out / "overlay.png").stat().st_size > 1000
