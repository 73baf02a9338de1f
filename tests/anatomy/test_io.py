"""CT I/O: exact round trips (NIfTI, NRRD, MetaImage, DICOM series), siblings and input errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk  # noqa: N813

from fluoronav.anatomy import Volume
from fluoronav.anatomy import io as ctio
from fluoronav.anatomy.io import load_ct, resolve_ct, save_volume, split_stem
from fluoronav.anatomy.landmarks import write_fcsv
from fluoronav.errors import InputError

SPACING = (0.75, 1.25, 2.5)
ORIGIN = (-100.5, 37.25, -812.125)


def _rotation() -> np.ndarray:
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    t = np.deg2rad(27.0)
    return np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K


def _volume(with_extras: bool = True) -> Volume:
    rng = np.random.default_rng(7)
    data = rng.integers(-1024, 3000, size=(6, 7, 9)).astype(np.float32)
    data[0, 0, 0] = 12.375  # a non-integer HU must survive too
    labels = np.zeros(data.shape, dtype=np.uint8)
    labels[2:4, 3:5, 1:6] = 1
    labels[4:, :2, 6:] = 3
    extras: dict = {}
    if with_extras:
        extras = {
            "labels": labels,
            "label_names": {1: "pelvis", 3: "femur_right"},
            "landmarks_world": {"entry_left": np.array([1.5, -2.25, 3.0]), "p": np.array([0.1, 0.2, 0.3])},
        }
    return Volume(data=data, spacing_mm=SPACING, origin_mm=ORIGIN, direction=_rotation(), name="ct", **extras)


def _assert_same(a: Volume, b: Volume, geom_atol: float) -> None:
    np.testing.assert_array_equal(a.data, b.data)
    assert b.data.dtype == np.float32
    np.testing.assert_allclose(b.spacing_mm, a.spacing_mm, rtol=0, atol=geom_atol)
    np.testing.assert_allclose(b.origin_mm, a.origin_mm, rtol=0, atol=geom_atol * 1000)
    np.testing.assert_allclose(b.direction, a.direction, rtol=0, atol=geom_atol)


@pytest.mark.parametrize(
    ("suffix", "atol"),
    [(".nrrd", 1e-14), (".nhdr", 1e-14), (".mha", 0.0), (".mhd", 0.0), (".nii.gz", 1e-6), (".nii", 1e-6)],
)
def test_round_trip_with_labels_and_landmarks(tmp_path: Path, suffix: str, atol: float) -> None:
    v = _volume()
    written = save_volume(v, tmp_path / f"ct{suffix}")
    assert [p.name for p in written] == [
        f"ct{suffix}",
        f"ct_labels{suffix}",
        "ct.labels.json",
        "ct_landmarks.json",
    ]
    w = load_ct(tmp_path / f"ct{suffix}")
    # MetaImage is bit-exact; NRRD stores direction·spacing (1 ulp); NIfTI keeps geometry in float32
    _assert_same(v, w, atol)
    assert w.name == "ct"
    assert w.labels is not None and w.labels.dtype == np.uint8
    np.testing.assert_array_equal(w.labels, v.labels)
    assert w.label_names == v.label_names
    assert set(w.landmarks_world) == set(v.landmarks_world)
    for k, p in v.landmarks_world.items():
        np.testing.assert_array_equal(w.landmarks_world[k], p)


def test_plain_volume_has_no_extras(tmp_path: Path) -> None:
    v = _volume(with_extras=False)
    assert save_volume(v, tmp_path / "a.mha") == [tmp_path / "a.mha"]
    w = load_ct(tmp_path / "a.mha")
    assert w.labels is None and w.label_names == {} and w.landmarks_world == {}


def test_explicit_label_and_fcsv_landmark_paths(tmp_path: Path) -> None:
    v = _volume()
    save_volume(v.replace(landmarks_world={}, labels=None), tmp_path / "ct.nrrd")
    seg = tmp_path / "other" / "seg.nrrd"
    seg.parent.mkdir()
    save_volume(v.replace(data=v.labels.astype(np.float32), labels=None, landmarks_world={}), seg)
    (seg.parent / "seg.labels.json").write_text(json.dumps({"labels": {"1": "pelvis"}}))
    marks = write_fcsv(tmp_path / "marks.fcsv", v.landmarks_world, coordinate_system="RAS")
    w = load_ct(tmp_path / "ct.nrrd", labels_path=seg, landmarks_path=marks)
    np.testing.assert_array_equal(w.labels, v.labels)
    assert w.label_names == {1: "pelvis", 3: "label_3"}
    np.testing.assert_allclose(w.landmarks_world["entry_left"], [1.5, -2.25, 3.0], atol=1e-12)


def test_sibling_fcsv_wins_over_json(tmp_path: Path) -> None:
    v = _volume()
    save_volume(v, tmp_path / "ct.mha")
    write_fcsv(tmp_path / "ct_landmarks.fcsv", {"only": np.array([1.0, 2.0, 3.0])})
    assert list(load_ct(tmp_path / "ct.mha").landmarks_world) == ["only"]


def _write_dicom_series(
    volume: Volume, folder: Path, series_uid: str, n_slices: int | None = None, extra: dict | None = None
) -> None:
    """A CT DICOM series written slice by slice with SimpleITK (int16, positions and orientation)."""
    folder.mkdir(parents=True, exist_ok=True)
    img = sitk.GetImageFromArray(volume.data.astype(np.int16))
    img.SetSpacing(volume.spacing_mm)
    img.SetOrigin(volume.origin_mm)
    img.SetDirection(volume.direction.ravel().tolist())
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    d = volume.direction
    orientation = "\\".join(f"{c:.12f}" for c in (*d[:, 0], *d[:, 1]))
    nz = img.GetDepth() if n_slices is None else n_slices
    for k in range(nz):
        s = img[:, :, k]
        pos = img.TransformIndexToPhysicalPoint((0, 0, k))
        for tag, value in [
            ("0008|0060", "CT"),
            ("0020|000d", "1.2.826.0.1.3680043.2.1125.1"),
            ("0020|000e", series_uid),
            ("0020|0037", orientation),
            ("0020|0032", "\\".join(f"{c:.6f}" for c in pos)),
            ("0020|0013", str(k + 1)),
            ("0018|0050", str(volume.spacing_mm[2])),
            ("0008|0018", f"{series_uid}.{k + 1}"),
            *(extra or {}).items(),
        ]:
            s.SetMetaData(tag, value)
        writer.SetFileName(str(folder / f"{series_uid[-3:]}_{k:03d}.dcm"))
        writer.Execute(s)


def test_dicom_series_round_trip_picks_largest_series(tmp_path: Path) -> None:
    v = _volume(with_extras=False)
    v = v.replace(data=np.round(v.data))  # DICOM stores int16
    _write_dicom_series(v, tmp_path / "dcm", "1.2.826.0.1.3680043.2.1125.100")
    _write_dicom_series(v, tmp_path / "dcm", "1.2.826.0.1.3680043.2.1125.200", n_slices=3)
    w = load_ct(tmp_path / "dcm")
    assert w.name == "dcm"
    # positions are written with 6 decimals, orientation with 12
    _assert_same(v, w, 1e-5)


def test_dicom_rescale_slope_intercept_applied(tmp_path: Path) -> None:
    # GDCM stores (HU − intercept) / slope and records the tags; reading must give HU back
    v = _volume(with_extras=False)
    hu = np.round(v.data / 2.0) * 2.0  # exactly representable with slope 2
    extra = {"0028|1052": "-1024", "0028|1053": "2"}
    _write_dicom_series(v.replace(data=hu), tmp_path / "dcm", "1.2.826.0.1.3680043.2.1125.300", extra=extra)
    one = sitk.ImageFileReader()
    one.SetFileName(str(next((tmp_path / "dcm").iterdir())))
    one.ReadImageInformation()
    assert float(one.GetMetaData("0028|1052")) == -1024.0 and float(one.GetMetaData("0028|1053")) == 2.0
    np.testing.assert_array_equal(load_ct(tmp_path / "dcm").data, hu)


def test_split_stem() -> None:
    assert split_stem("a/b/ct.nii.gz") == ("ct", ".nii.gz")
    assert split_stem("ct.NRRD") == ("ct", ".NRRD")


def test_resolve_ct_dispatch(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import fluoronav.anatomy.phantom as phantom

    calls = []
    monkeypatch.setattr(phantom, "hip_phantom", lambda *, seed: calls.append(seed) or _volume())
    assert resolve_ct("phantom", seed=5).name == "ct" and calls == [5]
    save_volume(_volume(with_extras=False), tmp_path / "x.mha")
    assert resolve_ct(str(tmp_path / "x.mha")).name == "x"
    with pytest.raises(InputError):
        resolve_ct(str(tmp_path / "phantom"))


# ------------------------------------------------------------------------------------------------
# Errors: one-line InputError naming the file
# ------------------------------------------------------------------------------------------------


def _expect_error(path: Path, fragment: str, **kwargs: object) -> None:
    with pytest.raises(InputError) as info:
        load_ct(path, **kwargs)  # type: ignore[arg-type]
    assert Path(info.value.source) == path
    assert fragment in info.value.problem, info.value.problem
    assert "\n" not in str(info.value)


def _mha_with_header(tmp_path: Path, name: str, old: bytes, new: bytes) -> Path:
    src = tmp_path / "src.mha"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((3, 4, 5), np.int16)), str(src))
    raw = src.read_bytes()
    assert old in raw
    out = tmp_path / name
    out.write_bytes(raw.replace(old, new, 1))
    return out


def test_missing_and_empty_and_garbage(tmp_path: Path) -> None:
    _expect_error(tmp_path / "nope.nii.gz", "not found")
    (tmp_path / "empty.nii.gz").write_bytes(b"")
    _expect_error(tmp_path / "empty.nii.gz", "empty file")
    (tmp_path / "junk.nrrd").write_bytes(b"this is not an image\n" * 10)
    _expect_error(tmp_path / "junk.nrrd", "unreadable")
    (tmp_path / "dir").mkdir()
    _expect_error(tmp_path / "dir", "no DICOM series")


def test_2d_images_are_not_cts(tmp_path: Path) -> None:
    png = tmp_path / "x.png"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((8, 9), np.uint8)), str(png))
    _expect_error(png, "2D image")
    nii = tmp_path / "x.nii.gz"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((8, 9), np.float32)), str(nii))
    _expect_error(nii, "2D image")
    rgb = tmp_path / "rgb.png"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((8, 9, 3), np.uint8), isVector=True), str(rgb))
    _expect_error(rgb, "channel")


def test_singleton_dimension(tmp_path: Path) -> None:
    f = tmp_path / "thin.mha"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((1, 8, 9), np.float32)), str(f))
    _expect_error(f, "singleton")


@pytest.mark.parametrize(
    ("old", "new", "fragment"),
    [
        (b"ElementSpacing = 1 1 1", b"ElementSpacing = 0 1 1", "spacing"),
        (b"ElementSpacing = 1 1 1", b"ElementSpacing = -1 1 1", "spacing"),
        (b"ElementSpacing = 1 1 1", b"ElementSpacing = 1 nan 1", "spacing"),
        (b"TransformMatrix = 1 0 0 0 1 0 0 0 1", b"TransformMatrix = 1 0.5 0 0 1 0 0 0 1", "orthonormal"),
    ],
)
def test_bad_geometry(tmp_path: Path, old: bytes, new: bytes, fragment: str) -> None:
    _expect_error(_mha_with_header(tmp_path, "bad.mha", old, new), fragment)


@pytest.mark.parametrize("pixdim", [0.0, -1.0])
def test_nifti_without_positive_spacing(tmp_path: Path, pixdim: float) -> None:
    f = tmp_path / "s.nii"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((3, 4, 5), np.float32)), str(f))
    raw = bytearray(f.read_bytes())
    raw[80:84] = np.float32(pixdim).tobytes()  # pixdim[1]
    f.write_bytes(bytes(raw))
    _expect_error(f, "spacing")


def test_nrrd_zero_spacing(tmp_path: Path) -> None:
    f = tmp_path / "z.nrrd"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((3, 4, 5), np.float32)), str(f))
    raw = f.read_bytes().replace(b"space directions: (1,0,0)", b"space directions: (0,0,0)", 1)
    f.write_bytes(raw)
    _expect_error(f, "spacing")


def test_non_finite_values(tmp_path: Path) -> None:
    data = np.zeros((3, 4, 5), np.float32)
    data[1, 2, 3] = np.nan
    f = tmp_path / "nan.nrrd"
    sitk.WriteImage(sitk.GetImageFromArray(data), str(f))
    _expect_error(f, "non-finite")


def test_bad_siblings_name_their_file(tmp_path: Path) -> None:
    v = _volume()
    save_volume(v, tmp_path / "ct.mha")
    # labels on another grid
    other = v.replace(data=v.labels[:, :, :-1].astype(np.float32), labels=None, landmarks_world={})
    save_volume(other, tmp_path / "seg.mha")
    with pytest.raises(InputError) as info:
        load_ct(tmp_path / "ct.mha", labels_path=tmp_path / "seg.mha")
    assert info.value.source == str(tmp_path / "seg.mha") and "grid" in info.value.problem
    # label names that do not parse
    (tmp_path / "ct.labels.json").write_text("{\n 1: 'x'}")
    with pytest.raises(InputError) as info:
        load_ct(tmp_path / "ct.mha")
    assert info.value.source == str(tmp_path / "ct.labels.json") and "line 2" in info.value.problem
    (tmp_path / "ct.labels.json").write_text('{"1": "pelvis"}')
    # landmarks that do not parse
    (tmp_path / "ct_landmarks.json").write_text('{"landmarks": {"a": [1, 2]}}')
    with pytest.raises(InputError) as info:
        load_ct(tmp_path / "ct.mha")
    assert info.value.source == str(tmp_path / "ct_landmarks.json")


def test_non_integer_labels(tmp_path: Path) -> None:
    v = _volume(with_extras=False)
    save_volume(v, tmp_path / "ct.mha")
    save_volume(v.replace(data=v.data + 0.5), tmp_path / "ct_labels.mha")
    with pytest.raises(InputError, match="integers"):
        load_ct(tmp_path / "ct.mha")


def test_itk_reason_is_one_line() -> None:
    assert "\n" not in ctio._itk_reason(RuntimeError("a\nb\nITK ERROR: thing failed\n"))
