"""``fluoronav render``: outputs, units and one-line input errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk  # noqa: N813

from fluoronav.cli.main import main
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.carm import carm_camera_from_world


def _run(args: list[str]) -> int:
    try:
        main(args)
    except SystemExit as exc:
        return int(exc.code or 0)
    return 0


@pytest.fixture()
def ct_and_camera(tmp_path: Path) -> tuple[Path, Path, np.ndarray]:
    """A 3D NIfTI of air with a water block 10 mm thick along y, and an AP camera through its middle."""
    hu = np.full((12, 14, 16), -1000.0, np.float32)  # (z, y, x)
    hu[3:9, 2:12, 4:12] = 0.0  # water: y indices 2..11 → 10 voxels of 1 mm
    image = sitk.GetImageFromArray(hu)
    image.SetSpacing((1.0, 1.0, 1.0))
    image.SetOrigin((-7.5, -6.5, -5.5))  # volume centre at the world origin
    ct = tmp_path / "ct.nii.gz"
    sitk.WriteImage(image, str(ct))
    T = carm_camera_from_world(lao_rao_deg=0.0, cran_caud_deg=90.0, source_to_isocenter_mm=300.0)
    K = np.array([[600.0, 0.0, 10.0], [0.0, 600.0, 8.0], [0.0, 0.0, 1.0]])
    cam = tmp_path / "camera.json"
    Camera(17, 21, K, T).save(cam)
    return ct, cam, hu


def test_render_writes_line_integrals_and_png(ct_and_camera, tmp_path: Path) -> None:
    ct, cam, _ = ct_and_camera
    out, png = tmp_path / "sub" / "drr.npy", tmp_path / "drr.png"
    assert (
        _run(
            [
                "render",
                "--ct",
                str(ct),
                "--camera",
                str(cam),
                "--out",
                str(out),
                "--png",
                str(png),
                "--mu-water",
                "0.03",
                "--device",
                "cpu",
            ]
        )
        == 0
    )
    drr = np.load(out)
    assert drr.dtype == np.float32 and drr.shape == (17, 21)
    # the principal ray runs along world y through the middle of the block: 10 mm of water
    assert drr[8, 10] == pytest.approx(0.03 * 10.0, rel=1e-4)
    assert drr[0, 0] == 0.0  # misses the block (and the air is μ = 0)
    from PIL import Image

    img = np.asarray(Image.open(png))
    assert img.dtype == np.uint8 and img.shape == (17, 21) and img.min() == 0 and img.max() == 255
    # same seed, same output; μ scales linearly with --mu-water
    out2 = tmp_path / "drr2.npy"
    assert (
        _run(
            [
                "render",
                "--ct",
                str(ct),
                "--camera",
                str(cam),
                "--out",
                str(out2),
                "--mu-water",
                "0.015",
                "--device",
                "cpu",
            ]
        )
        == 0
    )
    np.testing.assert_allclose(np.load(out2), drr / 2.0, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize(
    "case, fragment",
    [
        ("missing_ct", "not found"),
        ("bad_camera", "not valid JSON"),
        ("camera_missing_keys", "missing"),
        ("image_2d", "2D"),
        ("bad_cm", "control_points_deg"),
        ("cm_not_json", "not valid JSON"),
        ("bad_mu", "--mu-water"),
    ],
)
def test_render_input_errors_one_line(
    ct_and_camera, tmp_path: Path, capsys, case: str, fragment: str
) -> None:
    ct, cam, hu = ct_and_camera
    out = tmp_path / "drr.npy"
    args = ["--ct", str(ct), "--camera", str(cam), "--out", str(out), "--device", "cpu"]
    named: Path | str
    if case == "missing_ct":
        named = tmp_path / "nope.nii.gz"
        args[1] = str(named)
    elif case == "bad_camera":
        named = tmp_path / "bad.json"
        named.write_text("{rows: 3")
        args[3] = str(named)
    elif case == "camera_missing_keys":
        named = tmp_path / "partial.json"
        named.write_text(json.dumps({"rows": 4, "cols": 4}))
        args[3] = str(named)
    elif case == "image_2d":
        named = tmp_path / "slice.nii.gz"
        sitk.WriteImage(sitk.GetImageFromArray(hu[5]), str(named))
        args[1] = str(named)
    elif case in ("bad_cm", "cm_not_json"):
        named = tmp_path / "cm.json"
        if case == "bad_cm":
            named.write_text(
                json.dumps({"world_from_cm": np.eye(4).tolist(), "control_points_deg": [1, 2, 3]})
            )
        else:
            named.write_text("[1, 2")
        args += ["--cm", str(named)]
    else:
        named = "--mu-water"
        args += ["--mu-water", "-1"]
    assert _run(["render", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and str(named) in err and fragment in err, err
    assert not out.exists()


def test_render_phantom(tmp_path: Path) -> None:
    pytest.importorskip("fluoronav.anatomy.io")
    T = carm_camera_from_world(lao_rao_deg=0.0, cran_caud_deg=90.0, source_to_isocenter_mm=450.0)
    cam = tmp_path / "camera.json"
    Camera(32, 32, np.array([[120.0, 0.0, 15.5], [0.0, 120.0, 15.5], [0.0, 0.0, 1.0]]), T).save(cam)
    out = tmp_path / "drr.npy"
    assert (
        _run(
            [
                "render",
                "--ct",
                "phantom",
                "--camera",
                str(cam),
                "--out",
                str(out),
                "--seed",
                "1",
                "--device",
                "cpu",
            ]
        )
        == 0
    )
    drr = np.load(out)
    assert drr.shape == (32, 32) and np.isfinite(drr).all() and drr.max() > 1.0  # bone along the way


def test_render_adds_cm_integral(ct_and_camera, tmp_path: Path) -> None:
    cm_module = pytest.importorskip("fluoronav.rendering.cm")
    import torch

    from fluoronav.manipulator.config import CMConfig

    ct, cam_path, _ = ct_and_camera
    cam = Camera.load(cam_path)
    # CM axis along world x, in front of the block (towards the source), bent a little
    world_from_cm = np.eye(4)
    world_from_cm[:3, :3] = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    world_from_cm[:3, 3] = [-15.0, 20.0, 0.0]
    cp = [2.0, -1.0, 3.0, 0.5, 1.0]
    cm_file = tmp_path / "cm.json"
    cm_file.write_text(json.dumps({"world_from_cm": world_from_cm.tolist(), "control_points_deg": cp}))
    plain, with_cm = tmp_path / "plain.npy", tmp_path / "cm.npy"
    common = ["--ct", str(ct), "--camera", str(cam_path), "--mu-water", "0.02", "--device", "cpu"]
    assert _run(["render", *common, "--out", str(plain)]) == 0
    assert _run(["render", *common, "--out", str(with_cm), "--cm", str(cm_file)]) == 0
    added = np.load(with_cm) - np.load(plain)
    config = CMConfig()
    expected = (
        cm_module.CMRenderer(config, mu_per_mm=0.02 * (1.0 + config.hu_value / 1000.0))
        .render(
            torch.as_tensor(cam.camera_from_world @ world_from_cm)[None, None],
            torch.tensor([cp], dtype=torch.float64),
            torch.as_tensor(cam.K)[None],
            cam.rows,
            cam.cols,
        )[0, 0]
        .numpy()
    )
    assert expected.max() > 0.1  # the CM is in view
    np.testing.assert_allclose(added, expected, atol=1e-5)
