"""Cameras from X-ray DICOM geometry tags."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk  # noqa: N813

from fluoronav.errors import InputError
from fluoronav.geometry import carm_camera
from fluoronav.geometry.camera import DetectorSpec
from fluoronav.geometry.dicom import camera_from_dicom, camera_from_dicom_tags


def _write_dicom(path: Path, tags: dict[str, str], rows: int = 96, cols: int = 128) -> None:
    img = sitk.GetImageFromArray(np.zeros((rows, cols), np.uint16))
    for k, v in tags.items():
        img.SetMetaData(k, v)
    sitk.WriteImage(img, str(path))


def test_tags_give_the_carm_camera_of_the_same_angles(tmp_path: Path) -> None:
    tags = {
        "0018|1164": "0.388\\0.388",
        "0018|1110": "1020",
        "0018|1111": "480",
        "0018|1510": "-30",  # RAO 30: detector to the patient's right, source to the left
        "0018|1511": "10",  # CRA 10: detector towards the head
    }
    path = tmp_path / "frame.dcm"
    _write_dicom(path, tags)
    cam = camera_from_dicom(path)
    ref = carm_camera(
        lao_rao_deg=30.0,
        cran_caud_deg=100.0,
        source_to_isocenter_mm=480.0,
        detector=DetectorSpec(rows=96, cols=128, pixel_spacing_mm=0.388, sdd_mm=1020.0),
    )
    np.testing.assert_allclose(cam.K, ref.K, atol=1e-9)
    np.testing.assert_allclose(cam.camera_from_world, ref.camera_from_world, atol=1e-9)
    assert (cam.rows, cam.cols) == (96, 128)
    # RAO: the source is on the patient's left (+x in LPS); CRA: the source is below the isocentre
    assert cam.source_world[0] > 0 and cam.source_world[2] < 0
    np.testing.assert_allclose(np.linalg.norm(cam.source_world), 480.0)


def test_missing_tags_fall_back_and_bad_tags_are_one_line_errors(tmp_path: Path) -> None:
    cam = camera_from_dicom_tags({}, rows=768, cols=768)
    assert cam.pixel_spacing_mm == pytest.approx(0.388)  # the CIOS pitch binned to 768²
    with pytest.raises(InputError, match="not numeric"):
        camera_from_dicom_tags({"0018|1110": "far"}, rows=10, cols=10, source="x.dcm")
    with pytest.raises(InputError, match="implausible"):
        camera_from_dicom_tags({"0018|1110": "400", "0018|1111": "500"}, rows=10, cols=10)
    bad = tmp_path / "bad.dcm"
    bad.write_bytes(b"not a dicom")
    with pytest.raises(InputError) as info:
        camera_from_dicom(bad)
    assert "\n" not in str(info.value) and "bad.dcm" in str(info.value)
