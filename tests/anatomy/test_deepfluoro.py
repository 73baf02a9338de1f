"""The DeepFluoro reader on a synthetic file of the documented layout: round trip, frames, flips."""

from __future__ import annotations

import itertools

import h5py
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fluoronav.anatomy.deepfluoro import DeepFluoroFile, _bone_by_name, line_integral
from fluoronav.anatomy.deepfluoro_frames import fluoronav_camera
from fluoronav.errors import InputError
from fluoronav.simulation.deepfluoro_synthetic import SyntheticDeepFluoro

SPEC = "17-1882"


def _stored(truth: SyntheticDeepFluoro) -> dict:
    """The file read with plain h5py, as the layout documents it (no reader code)."""
    with h5py.File(truth.path, "r") as f:
        pp = f["proj-params"]
        g = f[SPEC]
        out = {
            "K": pp["intrinsic"][()],
            "E": pp["extrinsic"][()],
            "rows": int(pp["num-rows"][()]),
            "vol": g["vol/pixels"][()],
            "origin": g["vol/origin"][()],
            "spacing": g["vol/spacing"][()],
            "seg": g["vol-seg/image/pixels"][()],
            "lm3": {k: g["vol-landmarks"][k][()] for k in g["vol-landmarks"]},
            "proj": [],
        }
        for k in sorted(g["projections"]):
            p = g["projections"][k]
            out["proj"].append(
                {
                    "image": p["image/pixels"][()],
                    "G": p["gt-poses/cam-to-pelvis-vol"][()],
                    "lm2": {n: p["gt-landmarks"][n][()] for n in p["gt-landmarks"]},
                    "rot": int(p["rot-180-for-up"][()]),
                }
            )
    return out


def test_the_file_follows_the_documented_layout_and_projection(deepfluoro_file: SyntheticDeepFluoro) -> None:
    s = _stored(deepfluoro_file)
    n = s["rows"]
    nz, ny, nx = deepfluoro_file.volume.data.shape
    assert s["vol"].shape == (nz, ny, nx) and s["vol"].dtype == np.float32  # row-major (z, y, x)
    assert s["seg"].dtype == np.uint8 and s["origin"].shape == (3, 1) and s["spacing"].shape == (3, 1)
    assert len(s["lm3"]) == 14 and all(v.shape == (3, 1) for v in s["lm3"].values())
    assert s["K"][0, 0] < 0 and s["K"][1, 1] < 0  # negative focal lengths, as xReg writes them
    assert [p["rot"] for p in s["proj"]] == [0, 0, 1]
    sdd = -s["K"][0, 0] * deepfluoro_file.cameras[0].pixel_spacing_mm
    for p in s["proj"]:
        assert p["image"].shape == (n, n) and p["image"].dtype == np.float32
        # xReg's projection: [u, v, 1] ∝ intrinsic · extrinsic · inv(cam-to-pelvis-vol) · p
        P = s["E"] @ np.linalg.inv(p["G"])
        for name, x in s["lm3"].items():
            q = P @ np.append(x.reshape(3), 1.0)
            uvw = s["K"] @ q[:3]
            np.testing.assert_allclose(uvw[:2] / uvw[2], p["lm2"][name].reshape(2), atol=1e-6)
            assert -sdd < q[2] < 0  # z towards the source: the anatomy lies between source and detector


def test_reader_round_trips_the_synthetic_file(deepfluoro_file: SyntheticDeepFluoro) -> None:
    truth = deepfluoro_file
    with DeepFluoroFile(truth.path) as f:
        assert f.specimens == (SPEC,) and f.resolve_specimen("1") == SPEC
        assert f.projection_indices(SPEC) == (0, 1, 2)
        vol = f.volume(SPEC)
        np.testing.assert_array_equal(vol.data, truth.volume.data)
        np.testing.assert_allclose(vol.origin_mm, truth.volume.origin_mm, atol=1e-9)
        np.testing.assert_allclose(vol.spacing_mm, truth.volume.spacing_mm, atol=1e-9)
        np.testing.assert_array_equal(vol.labels, truth.volume.labels)  # hemipelves → pelvis, femurs
        assert vol.label_names == {1: "pelvis", 2: "femur_left", 3: "femur_right"}
        marks = f.landmarks_world(SPEC)
        assert marks.keys() == truth.landmarks_world.keys()
        for k, p in truth.landmarks_world.items():
            np.testing.assert_allclose(marks[k], p, atol=1e-9)
        np.testing.assert_allclose(vol.landmarks_world["femoral_head_left"], marks["FH-l"], atol=0)
        for k, cam in enumerate(truth.cameras):
            p = f.projection(SPEC, k)
            assert p.rot_180_for_up == truth.rot_180_for_up[k]
            np.testing.assert_allclose(p.camera.K, cam.K, atol=1e-6)
            np.testing.assert_allclose(p.camera.camera_from_world, cam.camera_from_world, atol=1e-6)
            np.testing.assert_allclose(p.world_from_femur["left"], truth.world_from_femur_left[k], atol=1e-6)
            np.testing.assert_allclose(p.world_from_femur["right"], np.eye(4), atol=1e-6)
            # the stored intensities, log-transformed, are the simulated line integral (a constant apart)
            li = line_integral(p.image)[10:-10, 10:-10]
            ref = truth.images[k][10:-10, 10:-10]
            np.testing.assert_allclose(li - li.mean(), ref - ref.mean(), atol=1e-5)


def test_landmarks_project_onto_their_2d_annotations(deepfluoro_file: SyntheticDeepFluoro) -> None:
    with DeepFluoroFile(deepfluoro_file.path) as f:
        marks = f.landmarks_world(SPEC)
        for p in f.projections(SPEC):
            uv = np.stack([p.landmarks_px[n] for n in marks])
            np.testing.assert_allclose(p.camera.project(np.stack(list(marks.values()))), uv, atol=1e-6)
            assert np.all(p.camera.to_camera(np.stack(list(marks.values())))[:, 2] > 0)  # in front
            res = p.landmark_residual_px(marks)
            assert res is not None and res < 1e-6
            # the same after the collimator crop
            img, cam = p.cropped_line_integral()
            b = (p.camera.rows - cam.rows) // 2
            assert b == 6 and img.shape == (cam.rows, cam.cols)
            np.testing.assert_allclose(cam.project(marks["FH-l"]), p.landmarks_px["FH-l"] - b, atol=1e-6)


def test_rot_180_image_is_turned_upright(deepfluoro_file: SyntheticDeepFluoro) -> None:
    s = _stored(deepfluoro_file)
    with DeepFluoroFile(deepfluoro_file.path) as f:
        marks = f.landmarks_world(SPEC)
        for k in range(3):
            p = f.projection(SPEC, k)
            if p.rot_180_for_up:
                # rotated by 180°, then mirrored left-right: rows reversed only
                assert p.flip.flip_rows and not p.flip.flip_cols
                np.testing.assert_array_equal(p.image, s["proj"][k]["image"][::-1, :])
            else:
                assert p.flip.flip_cols and not p.flip.flip_rows
                np.testing.assert_array_equal(p.image, s["proj"][k]["image"][:, ::-1])
            # the patient is "up": the iliac spines above the pubic symphysis
            asis = p.camera.project(marks["ASIS-l"])[1]
            ips = p.camera.project(marks["IPS-l"])[1]
            assert asis < ips


@pytest.mark.parametrize(("sx", "sy", "rot"), list(itertools.product((-1, 1), (-1, 1), (False, True))))
def test_camera_reproduces_the_projection_for_any_signs(sx: int, sy: int, rot: bool) -> None:
    rng = np.random.default_rng(sx + 2 * sy + 4 * rot + 10)
    rows, cols = 120, 160
    K = np.array([[sx * 900.0, 0.0, 70.3], [0.0, sy * 910.0, 58.9], [0.0, 0.0, 1.0]])
    P = np.eye(4)
    P[:3, :3] = Rotation.random(random_state=rng.integers(1 << 30)).as_matrix()
    pts = rng.normal(size=(20, 3)) * 30.0
    P[:3, 3] = -P[:3, :3] @ pts.mean(axis=0) + [0.0, 0.0, 600.0 * rng.choice([-1.0, 1.0])]
    cam, flip = fluoronav_camera(
        K,
        P,
        rows=rows,
        cols=cols,
        rot_180_for_up=rot,
        point_in_front_ct=pts.mean(axis=0),
        pixel_spacing_mm=0.2,
    )
    uvw = (K @ (pts @ P[:3, :3].T + P[:3, 3]).T).T
    np.testing.assert_allclose(cam.project(pts), flip.pixels(uvw[:, :2] / uvw[:, 2:]), atol=1e-9)
    assert np.all(cam.to_camera(pts)[:, 2] > 0) and cam.K[0, 0] > 0 and cam.K[1, 1] > 0
    assert np.linalg.det(cam.camera_from_world[:3, :3]) == pytest.approx(1.0)


def test_xreg_texture_correction_shifts_the_ground_truth(deepfluoro_file: SyntheticDeepFluoro) -> None:
    x = deepfluoro_file.landmarks_world["SPS-l"]
    with (
        DeepFluoroFile(deepfluoro_file.path) as f,
        DeepFluoroFile(deepfluoro_file.path, xreg_texture_correction=True) as g,
    ):
        a, b = f.projection(SPEC, 0), g.projection(SPEC, 0)
    # cam-to-pelvis-vol shifted by −0.5 mm per CT axis: the CT point x shows where x + 0.5 did
    np.testing.assert_allclose(b.camera.project(x), a.camera.project(x + 0.5), atol=1e-6)
    assert np.linalg.norm(b.camera.project(x) - a.camera.project(x)) > 0.1


def test_bad_files_and_names(tmp_path, deepfluoro_file: SyntheticDeepFluoro) -> None:
    bad = tmp_path / "x.h5"
    bad.write_text("not hdf5", encoding="utf-8")
    with pytest.raises(InputError, match="HDF5"):
        DeepFluoroFile(bad)
    with h5py.File(tmp_path / "empty.h5", "w"):
        pass
    with pytest.raises(InputError, match="proj-params"):
        DeepFluoroFile(tmp_path / "empty.h5")
    with DeepFluoroFile(deepfluoro_file.path) as f, pytest.raises(InputError, match="no specimen"):
        f.volume("18-2800")
    assert _bone_by_name("left-hemipelvis") == "pelvis" and _bone_by_name("upper-sacrum") == "pelvis"
    assert _bone_by_name("right-femur") == "femur_right" and _bone_by_name("left_femur") == "femur_left"
    assert _bone_by_name("background") is None


def test_float32_matrices_as_xreg_writes_them(deepfluoro_file: SyntheticDeepFluoro, tmp_path) -> None:
    """The real file most likely stores matrices, points and spacings as float32 (xReg's CoordScalar)."""
    single = tmp_path / "float32.h5"
    with h5py.File(deepfluoro_file.path, "r") as src, h5py.File(single, "w") as dst:

        def copy(name: str, obj: object) -> None:
            if isinstance(obj, h5py.Dataset):
                data = obj[()]
                if isinstance(data, np.ndarray) and data.dtype == np.float64:
                    data = data.astype(np.float32)
                dst.create_dataset(name, data=data)

        src.visititems(copy)
    with DeepFluoroFile(single) as f:
        marks = f.landmarks_world(SPEC)
        for k, cam in enumerate(deepfluoro_file.cameras):
            p = f.projection(SPEC, k)
            res = p.landmark_residual_px(marks)
            assert res is not None and res < 1e-2
            np.testing.assert_allclose(p.camera.camera_from_world, cam.camera_from_world, atol=1e-3)
