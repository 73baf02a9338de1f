"""Slicer output: transform files in ITK's resampling direction, models in LPS, the femur surface
of a labelled sphere, the slicer/ folder, and plans read from .mrk.json markups."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk  # noqa: N813
from scipy.spatial.transform import Rotation

from fluoronav.anatomy.markups import MARKUPS_SCHEMA_ID, read_markup_nodes, read_markups
from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.manipulator.mesh import cm_surface_mesh, mesh_volume
from fluoronav.navigation.outputs.slicer import (
    cm_surface,
    femur_surface,
    read_model,
    read_transform,
    write_model,
    write_slicer_folder,
    write_transform,
)
from fluoronav.navigation.planning import load_plan


def _rigid(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    T[:3, 3] = rng.uniform(-300.0, 300.0, 3)
    return T


def _rigid_inverse(T: np.ndarray) -> np.ndarray:
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


# ---------------------------------------------------------------------------------------------
# transforms


@pytest.mark.parametrize("suffix", [".h5", ".tfm"])
@pytest.mark.parametrize("seed", range(5))
def test_transform_file_maps_ct_points_into_the_child_frame(tmp_path: Path, suffix: str, seed: int) -> None:
    ct_from_x = _rigid(seed)
    f = write_transform(tmp_path / f"ct_from_x{suffix}", ct_from_x)
    tx = sitk.ReadTransform(str(f))
    assert tx.GetName() == "AffineTransform"
    x_from_ct = _rigid_inverse(ct_from_x)
    for p in np.random.default_rng(100 + seed).uniform(-400.0, 400.0, (10, 3)):
        got = np.asarray(tx.TransformPoint(p.tolist()))
        np.testing.assert_allclose(got, x_from_ct[:3, :3] @ p + x_from_ct[:3, 3], rtol=0, atol=1e-9)
    np.testing.assert_allclose(read_transform(f), ct_from_x, rtol=0, atol=1e-9)


def test_read_transform_accepts_other_linear_itk_types(tmp_path: Path) -> None:
    # an Euler3D transform (as other ITK tools write) holding x_from_ct, with a centre
    euler = sitk.Euler3DTransform((10.0, -5.0, 2.0), 0.1, -0.2, 0.3, (4.0, 5.0, 6.0))
    f = tmp_path / "euler.tfm"
    sitk.WriteTransform(euler, str(f))
    ct_from_x = read_transform(f)
    for p in ([0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [-50.0, 20.0, 7.0]):
        x = np.asarray(euler.TransformPoint(p))
        np.testing.assert_allclose(ct_from_x[:3, :3] @ x + ct_from_x[:3, 3], p, atol=1e-9)


def _displacement_field(path: Path) -> None:
    field = sitk.Image([4, 4, 4], sitk.sitkVectorFloat64, 3)
    sitk.WriteTransform(sitk.DisplacementFieldTransform(field), str(path))


@pytest.mark.parametrize("case", ["missing", "garbage", "nonlinear", "singular"])
def test_bad_transform_files_raise_input_error(tmp_path: Path, case: str) -> None:
    f = tmp_path / f"{case}.h5"
    if case == "garbage":
        f.write_text("not a transform\n")
    elif case == "nonlinear":
        _displacement_field(f)
    elif case == "singular":
        f = tmp_path / "singular.tfm"
        sitk.WriteTransform(sitk.AffineTransform([1, 0, 0, 0, 1, 0, 0, 0, 0], [0, 0, 0]), str(f))
    with pytest.raises(InputError) as err:
        read_transform(f)
    assert f.name in str(err.value)


def test_write_transform_rejects_non_affine(tmp_path: Path) -> None:
    bad = np.eye(4)
    bad[3, 0] = 1.0
    with pytest.raises(ValueError, match="last row"):
        write_transform(tmp_path / "t.h5", bad)
    with pytest.raises(ValueError, match="end in"):
        write_transform(tmp_path / "t.json", np.eye(4))


# ---------------------------------------------------------------------------------------------
# models


@pytest.mark.parametrize("binary", [True, False])
def test_model_round_trip_and_space_header(tmp_path: Path, binary: bool) -> None:
    v, f = cm_surface(None, np.array([10.0, -20.0, 30.0, 5.0, 0.0]), segments=12)
    path = write_model(tmp_path / "m.vtk", v, f, binary=binary)
    head = path.read_bytes().split(b"\n", 3)
    assert head[0] == b"# vtk DataFile Version 4.2"
    assert b"SPACE=LPS" in head[1]
    assert head[2] == (b"BINARY" if binary else b"ASCII")
    v2, f2 = read_model(path)
    np.testing.assert_array_equal(v2, v)
    np.testing.assert_array_equal(f2, f)


def test_read_model_converts_a_ras_file(tmp_path: Path) -> None:
    path = tmp_path / "ras.vtk"
    path.write_text(
        "# vtk DataFile Version 4.2\n3D Slicer output. SPACE=RAS\nASCII\nDATASET POLYDATA\n"
        "POINTS 3 float\n1 2 3\n4 5 6\n7 8 9\nPOLYGONS 1 4\n3 0 1 2\n"
    )
    v, f = read_model(path)
    np.testing.assert_array_equal(v, [[-1, -2, 3], [-4, -5, 6], [-7, -8, 9]])
    np.testing.assert_array_equal(f, [[0, 1, 2]])
    path.write_text("# vtk DataFile Version 4.2\nx\nASCII\nDATASET STRUCTURED_POINTS\n")
    with pytest.raises(InputError, match=r"ras\.vtk"):
        read_model(path)


def test_cm_surface_accepts_kinematics_config_or_default() -> None:
    cps = np.array([5.0, 10.0, 0.0, -5.0, 20.0])
    want_v, want_f = cm_surface_mesh(None, cps, segments=16)
    for cm in (None, CMConfig(), CMKinematics()):
        v, f = cm_surface(cm, cps, segments=16)
        np.testing.assert_array_equal(v, want_v)
        np.testing.assert_array_equal(f, want_f)


# ---------------------------------------------------------------------------------------------
# femur surface

RADIUS_MM = 14.0


def _sphere_volume() -> tuple[Volume, np.ndarray, float]:
    shape = (36, 44, 52)  # (nz, ny, nx)
    spacing = (0.7, 0.9, 1.3)
    direction = Rotation.from_euler("zyx", [35.0, -20.0, 60.0], degrees=True).as_matrix()
    direction[:, 1] *= -1.0  # a left-handed grid (det −1), as some scanners write
    vol = Volume(np.zeros(shape, np.float32), spacing, (-120.0, 35.5, 410.0), direction, name="sphere")
    centre = vol.center_world + np.array([1.3, -2.1, 0.7])
    kk, jj, ii = np.meshgrid(*(np.arange(n) for n in shape), indexing="ij")
    ijk1 = np.stack([ii, jj, kk, np.ones_like(ii)], axis=-1).astype(np.float64)
    world = ijk1 @ vol.world_from_index.T
    labels = (np.linalg.norm(world[..., :3] - centre, axis=-1) <= RADIUS_MM).astype(np.uint8) * 2
    vol = vol.replace(labels=labels, label_names={1: "pelvis", 2: "femur_left"})
    return vol, centre, max(spacing)


def test_femur_surface_of_a_sphere_lies_at_its_radius_in_world() -> None:
    vol, centre, voxel = _sphere_volume()
    v, f = femur_surface(vol, "femur_left")
    r = np.linalg.norm(v - centre, axis=1)
    assert np.all(np.abs(r - RADIUS_MM) <= voxel), (r.min(), r.max())
    np.testing.assert_allclose(v.mean(axis=0), centre, atol=0.2 * voxel)
    # closed, outward-facing surface enclosing about the sphere's volume
    assert mesh_volume(v, f) == pytest.approx(4.0 / 3.0 * np.pi * RADIUS_MM**3, rel=0.05)


def test_femur_surface_respects_the_face_budget() -> None:
    vol, centre, voxel = _sphere_volume()
    _, full_f = femur_surface(vol, "femur_left")
    v, f = femur_surface(vol, "femur_left", max_faces=full_f.shape[0] // 3)
    assert f.shape[0] <= full_f.shape[0] // 3
    assert mesh_volume(v, f) > 0
    r = np.linalg.norm(v - centre, axis=1)
    assert np.all(np.abs(r - RADIUS_MM) <= 3 * voxel)


def test_femur_surface_missing_label() -> None:
    vol, _, _ = _sphere_volume()
    with pytest.raises(ValueError, match="femur_right"):
        femur_surface(vol, "femur_left".replace("left", "right"))
    with pytest.raises(ValueError, match="no voxels"):
        femur_surface(vol, "pelvis")
    with pytest.raises(ValueError, match="no label map"):
        femur_surface(vol.replace(labels=None), "femur_left")


# ---------------------------------------------------------------------------------------------
# the folder


def test_slicer_folder(tmp_path: Path) -> None:
    ct_from_cm, ct_from_femur, ct_from_carm = _rigid(1), _rigid(2), _rigid(3)
    cm_v, cm_f = cm_surface(None, np.array([0.0, 15.0, 25.0, 10.0, -5.0]), segments=16)
    fem_v = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 10.0]])
    fem_f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    entry, target = np.array([12.0, -30.5, 80.0]), np.array([15.0, -26.5, 68.0])
    landmarks = {"femoral_head_left": np.array([84.0, -10.5, -30.25]), "entry_left": entry}
    out = tmp_path / "slicer"
    paths = write_slicer_folder(
        out,
        ct_from_cm=ct_from_cm,
        ct_from_femur=ct_from_femur,
        cm_vertices_cm=cm_v,
        cm_faces=cm_f,
        femur_vertices_ct=fem_v,
        femur_faces=fem_f,
        plan_points={"entry": entry, "tip_target": target},
        landmarks=landmarks,
        extra_transforms={"ct_from_carm": ct_from_carm},
    )
    names = {
        "ct_from_cm.h5",
        "ct_from_femur.h5",
        "ct_from_carm.h5",
        "cm.vtk",
        "cm_in_cm_frame.vtk",
        "femur.vtk",
        "plan.mrk.json",
        "landmarks.mrk.json",
        "README.txt",
    }
    assert {p.name for p in paths} == names
    assert {p.name for p in out.iterdir()} == names
    for name, T in (
        ("ct_from_cm", ct_from_cm),
        ("ct_from_femur", ct_from_femur),
        ("ct_from_carm", ct_from_carm),
    ):
        np.testing.assert_allclose(read_transform(out / f"{name}.h5"), T, atol=1e-9)
    # the CM in CT coordinates is ct_from_cm applied to the CM-frame mesh
    v_ct, f_ct = read_model(out / "cm.vtk")
    np.testing.assert_allclose(v_ct, cm_v @ ct_from_cm[:3, :3].T + ct_from_cm[:3, 3], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(f_ct, cm_f)
    v_cm, _ = read_model(out / "cm_in_cm_frame.vtk")
    np.testing.assert_array_equal(v_cm, cm_v)
    # ... which the transform file maps back into the CM frame (what Slicer does under the node)
    tx = sitk.ReadTransform(str(out / "ct_from_cm.h5"))
    np.testing.assert_allclose(tx.TransformPoint(v_ct[7].tolist()), cm_v[7], atol=1e-9)
    np.testing.assert_array_equal(read_model(out / "femur.vtk")[0], fem_v)
    (plan,) = read_markup_nodes(out / "plan.mrk.json")
    assert (plan.type, plan.labels) == ("Line", ("entry", "tip_target"))
    np.testing.assert_array_equal(plan.points_lps, [entry, target])
    got = read_markups(out / "landmarks.mrk.json")
    assert list(got) == list(landmarks)
    readme = (out / "README.txt").read_text()
    for name in names - {"README.txt"}:
        assert name in readme
    # the plan file is a plan again
    p = load_plan(out / "plan.mrk.json")
    np.testing.assert_array_equal(p.entry_point_world_mm, entry)
    np.testing.assert_allclose(p.direction_world, (target - entry) / np.linalg.norm(target - entry))


def _small_folder(out: Path, **changes: object) -> list[Path]:
    kwargs: dict = {
        "ct_from_cm": np.eye(4),
        "ct_from_femur": np.eye(4),
        "cm_vertices_cm": np.eye(3),
        "cm_faces": np.array([[0, 1, 2]]),
        "femur_vertices_ct": np.eye(3),
        "femur_faces": np.array([[0, 1, 2]]),
        "plan_points": {"entry": np.zeros(3)},
        "landmarks": {},
    }
    kwargs.update(changes)
    return write_slicer_folder(out, **kwargs)


def test_slicer_folder_without_a_plan_or_with_one_point(tmp_path: Path) -> None:
    paths = _small_folder(tmp_path / "a", plan_points={})
    assert "plan.mrk.json" not in {p.name for p in paths} | {p.name for p in (tmp_path / "a").iterdir()}
    assert "plan.mrk.json" not in (tmp_path / "a" / "README.txt").read_text()
    _small_folder(tmp_path / "b")
    assert read_markup_nodes(tmp_path / "b" / "plan.mrk.json")[0].type == "Fiducial"


def test_slicer_folder_rejects_bad_extra_names(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="extra transform"):
        _small_folder(tmp_path, extra_transforms={"../escape": np.eye(4)})
    with pytest.raises(ValueError, match="extra transform"):
        _small_folder(tmp_path, extra_transforms={"ct_from_cm": np.eye(4)})


# ---------------------------------------------------------------------------------------------
# plans from markups


def _write_markups(path: Path, markups: list[dict]) -> Path:
    path.write_text(json.dumps({"@schema": MARKUPS_SCHEMA_ID, "markups": markups}))
    return path


def _pt(label: str, xyz: list[float]) -> dict:
    return {"label": label, "position": xyz, "positionStatus": "defined"}


def test_plan_from_a_ras_line(tmp_path: Path) -> None:
    f = _write_markups(
        tmp_path / "neck.mrk.json",
        [
            {
                "type": "Line",
                "name": "neck_axis",
                "coordinateSystem": "RAS",
                "controlPoints": [_pt("", [-12.0, 30.5, 80.0]), _pt("", [-12.0, 27.5, 84.0])],
            },
            {"type": "Fiducial", "controlPoints": [_pt("other", [1.0, 2.0, 3.0])]},
        ],
    )
    plan = load_plan(f)
    assert plan.target_name == "neck_axis"
    np.testing.assert_allclose(plan.entry_point_world_mm, [12.0, -30.5, 80.0])  # LPS
    np.testing.assert_allclose(plan.direction_world, [0.0, 0.6, 0.8])  # RAS (0, -3, 4) → LPS (0, 3, 4)/5
    assert plan.insertion_depth_mm == 0.0
    np.testing.assert_allclose(plan.tip_target_world_mm, plan.entry_point_world_mm)


def test_plan_from_entry_and_target_points(tmp_path: Path) -> None:
    f = _write_markups(
        tmp_path / "plan.mrk.json",
        [
            {
                "type": "Fiducial",
                "controlPoints": [
                    _pt("Target", [10.0, 0.0, 0.0]),
                    _pt("landmark", [5.0, 5.0, 5.0]),
                    _pt("entry", [10.0, 0.0, -20.0]),
                ],
            }
        ],
    )
    plan = load_plan(f)
    assert plan.target_name == "plan"  # the node's name: the file name without .mrk.json
    np.testing.assert_allclose(plan.entry_point_world_mm, [10.0, 0.0, -20.0])
    np.testing.assert_allclose(plan.direction_world, [0.0, 0.0, 1.0])


_LINE = {"type": "Line", "controlPoints": [_pt("a", [0.0, 0.0, 0.0]), _pt("b", [0.0, 0.0, 1.0])]}
BAD_PLANS: dict[str, object] = {
    "not_json": "{",
    "no_markups": {"@schema": MARKUPS_SCHEMA_ID},
    "nothing_usable": [{"type": "Fiducial", "controlPoints": [_pt("a", [1.0, 2.0, 3.0])]}],
    "two_lines": [_LINE, _LINE],
    "line_and_list": [
        _LINE,
        {
            "type": "Fiducial",
            "controlPoints": [_pt("entry", [0.0, 0.0, 0.0]), _pt("target", [1.0, 0.0, 0.0])],
        },
    ],
    "line_one_point": [{"type": "Line", "controlPoints": [_pt("a", [0.0, 0.0, 0.0])]}],
    "line_three_points": [{**_LINE, "controlPoints": [*_LINE["controlPoints"], _pt("c", [1.0, 1.0, 1.0])]}],
    "coincident": [{"type": "Line", "controlPoints": [_pt("a", [1.0, 2.0, 3.0]), _pt("b", [1.0, 2.0, 3.0])]}],
    "entry_only": [{"type": "Fiducial", "controlPoints": [_pt("entry", [0.0, 0.0, 0.0])]}],
    "two_entries": [
        {
            "type": "Fiducial",
            "controlPoints": [
                _pt("entry", [0.0, 0.0, 0.0]),
                _pt("ENTRY", [0.0, 0.0, 1.0]),
                _pt("target", [0.0, 0.0, 2.0]),
            ],
        }
    ],
    "bad_position": [{"type": "Line", "controlPoints": [_pt("a", [0.0, 0.0]), _pt("b", [0.0, 0.0, 1.0])]}],
}


@pytest.mark.parametrize("case", sorted(BAD_PLANS))
def test_bad_plan_markups_raise_input_error_naming_the_file(tmp_path: Path, case: str) -> None:
    f = tmp_path / f"plan_{case}.mrk.json"
    content = BAD_PLANS[case]
    if isinstance(content, list):
        _write_markups(f, content)
    else:
        f.write_text(content if isinstance(content, str) else json.dumps(content))
    with pytest.raises(InputError) as err:
        load_plan(f)
    assert f.name in str(err.value) and "\n" not in str(err.value)
