"""Navigation case files: round trip, DICOM cameras, malformed cases, DH robot files."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import SimpleITK as sitk  # noqa: N813

from fluoronav.anatomy.landmarks import write_landmarks_json
from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError
from fluoronav.geometry.camera import Camera, DetectorSpec
from fluoronav.geometry.carm import carm_camera_from_world
from fluoronav.geometry.dicom import camera_from_dicom
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.robot import UR10, DHRow, SerialRobot, load_robot, robot_to_dict
from fluoronav.navigation.case.model import (
    CaseView,
    NavigationCase,
    VerificationViews,
    load_navigation_case,
    write_navigation_case,
)
from fluoronav.navigation.case.schema import (
    CaseFile,
    InlineCamera,
    MovedFrom,
    RobotEntry,
    Verification,
    ViewEntry,
)
from fluoronav.navigation.planning import Plan

HEAD_LEFT = np.array([14.0, 2.0, -6.0])


def _volume() -> Volume:
    """40³ voxels at 2 mm, centred on the origin: a pelvis block and a left femur ball."""
    n, h = 40, 2.0
    origin = -0.5 * h * (n - 1)
    z, y, x = (origin + h * np.arange(n) for _ in range(3))
    Z, Y, X = np.meshgrid(z, y, x, indexing="ij")
    rng = np.random.default_rng(0)
    data = (-100.0 + 20.0 * rng.standard_normal((n, n, n))).astype(np.float32)
    labels = np.zeros((n, n, n), np.uint8)
    labels[(np.abs(X) < 10) & (np.abs(Y) < 12) & (Z > 10)] = 1
    labels[(X - HEAD_LEFT[0]) ** 2 + (Y - HEAD_LEFT[1]) ** 2 + (Z - HEAD_LEFT[2]) ** 2 < 64] = 2
    data[labels > 0] += 700.0
    return Volume(
        data=data,
        spacing_mm=(h, h, h),
        origin_mm=(origin, origin, origin),
        labels=labels,
        label_names={1: "pelvis", 2: "femur_left"},
        landmarks_world={"femoral_head_left": HEAD_LEFT.copy(), "pelvis_center": np.array([0.0, 0.0, 20.0])},
        name="synthetic",
    )


def _camera(angle_deg: float, *, rows: int = 32, cols: int = 40, spacing: float | None = 0.8) -> Camera:
    T = carm_camera_from_world(
        lao_rao_deg=angle_deg, cran_caud_deg=90.0, source_to_isocenter_mm=450.0, isocenter_world=HEAD_LEFT
    )
    spec = DetectorSpec(rows=rows, cols=cols, pixel_spacing_mm=spacing or 1.0, sdd_mm=1000.0)
    cam = Camera.from_detector(spec, T)
    return cam if spacing is not None else Camera(rows, cols, cam.K, T, None)


def _view(name: str, seed: int, *, with_mask: bool = False, spacing: float | None = 0.8) -> CaseView:
    rng = np.random.default_rng(seed)
    cam = _camera(10.0 * seed, spacing=spacing)
    image = rng.random((cam.rows, cam.cols)).astype(np.float32)
    lm = np.array([[10.5, 12.0], [25.0, 20.25]]) if with_mask else None
    mask = None
    if with_mask:
        mask = np.zeros((cam.rows, cam.cols), bool)
        mask[10:22, 8:30] = True
    return CaseView(name=name, image=image, camera=cam, landmarks_px=lm, mask=mask)


def _robot_other() -> SerialRobot:
    rows = tuple(
        DHRow(r.a_mm + 0.1 * i, r.alpha_deg + 0.01, r.d_mm - 0.05, r.theta_offset_deg + 0.02 * i)
        for i, r in enumerate(UR10.dh)
    )
    return SerialRobot(dh=rows, name="UR10 calibrated", joint_limits_deg=tuple((-350.0, 355.0) for _ in rows))


def _case(*, robot: SerialRobot = UR10) -> NavigationCase:
    ee = np.eye(4)
    ee[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    ee[:3, 3] = [1.5, -2.0, 180.0]
    return NavigationCase(
        volume=_volume(),
        plan=Plan(
            target_name="entry",
            entry_point_world_mm=np.array([30.0, 4.0, -20.0]),
            direction_world=np.array([-0.6, 0.0, 0.8]),
            insertion_depth_mm=2.5,
            control_points_deg=np.array([1.0, 0.5, 0.0, -0.5, -1.0]),
        ),
        side="left",
        cm_config=CMConfig(notch_width_mm=0.6),
        fbg_control_points_deg=np.array([0.5, 1.0, -1.5, 2.0, 0.25]),
        fbg_sigma_deg=0.1,
        robot=robot,
        joints_deg=np.array([10.0, -80.0, 95.0, -100.0, -90.0, 5.0]),
        ee_from_cm=ee,
        views=(_view("ap", 0), _view("oblique", 1, with_mask=True), _view("lateral", 2, spacing=None)),
        verification=VerificationViews(
            joints_deg=np.array([12.0, -78.0, 93.0, -101.0, -90.0, 6.0]),
            views=(
                replace(_view("ap after", 3), moved_from="ap", carm_motion=CARM_SLIDE),
                replace(_view("oblique again", 4), moved_from="oblique", carm_motion=np.eye(4)),
                _view("free", 5),
            ),
        ),
    )


#: the C-arm slid 40 mm along its x axis and 15 mm up between a first view and its verification view
CARM_SLIDE = np.array([[1.0, 0.0, 0.0, -40.0], [0.0, 1.0, 0.0, 15.0], [0.0, 0.0, 1.0, 0.0], [0, 0, 0, 1.0]])


def _assert_views_equal(a: tuple[CaseView, ...], b: tuple[CaseView, ...]) -> None:
    assert [v.name for v in a] == [v.name for v in b]
    for u, v in zip(a, b, strict=True):
        np.testing.assert_array_equal(u.image, v.image)
        assert v.image.dtype == np.float32
        assert (u.camera.rows, u.camera.cols) == (v.camera.rows, v.camera.cols)
        np.testing.assert_allclose(u.camera.K, v.camera.K, rtol=0, atol=1e-12)
        np.testing.assert_allclose(u.camera.camera_from_world, v.camera.camera_from_world, atol=1e-12)
        assert u.camera.pixel_spacing_mm == v.camera.pixel_spacing_mm
        assert u.moved_from == v.moved_from
        for x, y in ((u.landmarks_px, v.landmarks_px), (u.mask, v.mask), (u.carm_motion, v.carm_motion)):
            assert (x is None) == (y is None)
            if x is not None:
                np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("robot", [UR10, _robot_other()], ids=["UR10", "dh-file"])
def test_written_case_loads_back_equal(tmp_path: Path, robot: SerialRobot) -> None:
    case = _case(robot=robot)
    path = write_navigation_case(case, tmp_path / "case", extra={"notes": "simulated", "_truth": [1, 2]})
    assert path == tmp_path / "case" / "navigation.json"
    d = json.loads(path.read_text())
    assert d["robot"]["model"] == ("UR10" if robot == UR10 else "robot_dh.json")
    assert d["notes"] == "simulated"
    back = load_navigation_case(path)

    v0, v1 = case.volume, back.volume
    np.testing.assert_array_equal(v0.data, v1.data)
    assert v1.labels is not None and v0.labels is not None
    np.testing.assert_array_equal(v0.labels, v1.labels)
    assert v1.label_names == v0.label_names
    np.testing.assert_allclose(v1.spacing_mm, v0.spacing_mm, rtol=1e-6)
    np.testing.assert_allclose(v1.origin_mm, v0.origin_mm, rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(v1.direction, v0.direction, atol=1e-7)
    assert v1.landmarks_world.keys() == v0.landmarks_world.keys()
    for k in v0.landmarks_world:
        np.testing.assert_allclose(v1.landmarks_world[k], v0.landmarks_world[k], atol=1e-9)

    p0, p1 = case.plan, back.plan
    assert p1.target_name == p0.target_name and p1.insertion_depth_mm == p0.insertion_depth_mm
    np.testing.assert_allclose(p1.entry_point_world_mm, p0.entry_point_world_mm)
    np.testing.assert_allclose(p1.direction_world, p0.direction_world, atol=1e-12)
    assert p1.control_points_deg is not None and p0.control_points_deg is not None
    np.testing.assert_array_equal(p1.control_points_deg, p0.control_points_deg)

    assert back.side == "left"
    assert back.cm_config == case.cm_config
    assert back.fbg_control_points_deg is not None and case.fbg_control_points_deg is not None
    np.testing.assert_array_equal(back.fbg_control_points_deg, case.fbg_control_points_deg)
    assert back.fbg_sigma_deg == 0.1
    assert back.robot == robot
    np.testing.assert_array_equal(back.joints_deg, case.joints_deg)
    np.testing.assert_array_equal(back.ee_from_cm, case.ee_from_cm)
    _assert_views_equal(case.views, back.views)
    assert back.verification is not None and case.verification is not None
    np.testing.assert_array_equal(back.verification.joints_deg, case.verification.joints_deg)
    _assert_views_equal(case.verification.views, back.verification.views)
    entries = d["verification"]["views"]
    assert entries[0]["moved_from"]["view"] == "ap" and entries[1]["same_camera_as"] == "oblique"
    assert "moved_from" not in entries[2] and "same_camera_as" not in entries[2]
    assert back.source == path


DATA = Path(__file__).parent / "data"


def _case_with_a_masked_verification_view() -> NavigationCase:
    """:func:`_case` with a DH robot and a verification view holding landmarks, a mask and
    ``same_camera_as`` (the order of a view's keys)."""
    case = _case(robot=_robot_other())
    assert case.verification is not None
    views = list(case.verification.views)
    views[1] = replace(_view("oblique again", 4, with_mask=True), moved_from="oblique", carm_motion=np.eye(4))
    return replace(case, verification=replace(case.verification, views=tuple(views)))


@pytest.mark.parametrize(
    ("make", "kwargs", "expected"),
    [
        (_case, {"extra": {"notes": "simulated", "_truth": [1, 2]}}, "written_case.json"),
        (
            _case_with_a_masked_verification_view,
            {
                "ct_path": "phantom",
                "extra": {"description": "a DH robot", "phantom_seed": 3, "isocenter_ct_mm": [1.0, 2.0, 3.5]},
            },
            "written_case_dh_robot.json",
        ),
    ],
    ids=["UR10", "dh-robot-phantom"],
)
def test_written_case_file_keeps_its_bytes(
    tmp_path: Path, make: Callable[[], NavigationCase], kwargs: dict[str, Any], expected: str
) -> None:
    """``navigation.json`` byte for byte as the writer wrote it before the schema models (data/):
    the demo reads back the case it writes, so its results hang on these bytes."""
    path = write_navigation_case(make(), tmp_path, **kwargs)
    assert path.read_text(encoding="utf-8") == (DATA / expected).read_text(encoding="utf-8")


def test_an_inline_camera_and_plan_read_as_their_files(tmp_path: Path) -> None:
    path = write_navigation_case(replace(_case(), verification=None), tmp_path)
    back = load_navigation_case(path)
    d = json.loads(path.read_text())
    d["views"][2]["camera"] = json.loads((tmp_path / d["views"][2]["camera"]).read_text())
    d["plan"] = json.loads((tmp_path / d["plan"]).read_text())
    path.write_text(json.dumps(d))
    inline = load_navigation_case(path)
    _assert_views_equal(back.views, inline.views)
    assert repr(inline.plan) == repr(back.plan)


def test_side_defaults_to_the_head_nearest_the_entry_and_ct_path_is_kept(tmp_path: Path) -> None:
    case = _case()
    first = write_navigation_case(case, tmp_path / "a")
    d = json.loads(first.read_text())
    out = write_navigation_case(
        replace(case, verification=None), tmp_path / "b", ct_path=str(tmp_path / "a" / d["ct"])
    )
    d = json.loads(out.read_text())
    assert d["ct"] == "../a/ct.nii.gz" and "labels" not in d and not (tmp_path / "b" / "ct.nii.gz").exists()
    del d["side"]
    out.write_text(json.dumps(d))
    back = load_navigation_case(out)
    assert back.side == "left" and back.verification is None
    np.testing.assert_array_equal(back.volume.data, case.volume.data)  # siblings found next to the CT
    assert back.volume.label_names == case.volume.label_names


def test_ee_from_cm_from_a_calibrate_output(tmp_path: Path) -> None:
    case = _case()
    path = write_navigation_case(case, tmp_path)
    handeye = {"case": "c.json", "seed": 0, "ok": True, "ee_from_cm": case.ee_from_cm.tolist(), "cost": 1.0}
    (tmp_path / "handeye.json").write_text(json.dumps(handeye))
    d = json.loads(path.read_text())
    d["robot"]["ee_from_cm"] = "handeye.json"
    path.write_text(json.dumps(d))
    np.testing.assert_array_equal(load_navigation_case(path).ee_from_cm, case.ee_from_cm)
    (tmp_path / "handeye.json").write_text(json.dumps({"ok": False, "reason": "did not converge"}))
    with pytest.raises(InputError, match=r"robot\.ee_from_cm.*handeye\.json.*did not converge"):
        load_navigation_case(path)


def _write_dicom(path: Path, rows: int, cols: int) -> dict[str, str]:
    tags = {
        "0018|1164": "0.8\\0.8",
        "0018|1110": "1000",
        "0018|1111": "450",
        "0018|1510": "20",
        "0018|1511": "-5",
    }
    pixels = (np.arange(rows * cols, dtype=np.uint16).reshape(rows, cols) * 7) % 4000
    img = sitk.GetImageFromArray(pixels)
    for k, v in tags.items():
        img.SetMetaData(k, v)
    sitk.WriteImage(img, str(path))
    return tags


@pytest.mark.parametrize("iso", [[10.0, -5.0, 3.0], None], ids=["given", "femoral-head"])
def test_dicom_camera_places_the_isocentre_point_on_the_principal_point(
    tmp_path: Path, iso: list[float] | None
) -> None:
    path = write_navigation_case(replace(_case(), verification=None), tmp_path)
    _write_dicom(tmp_path / "frame.dcm", rows=48, cols=64)
    d = json.loads(path.read_text())
    d["views"][1] = {"name": "dcm", "image": "frame.dcm", "camera": "dicom"}
    if iso is not None:
        d["isocenter_ct_mm"] = iso
    path.write_text(json.dumps(d))
    cam = load_navigation_case(path).views[1].camera
    iso_ct = np.asarray(iso if iso is not None else HEAD_LEFT)
    ref = camera_from_dicom(tmp_path / "frame.dcm")
    shift = np.eye(4)
    shift[:3, 3] = -iso_ct
    np.testing.assert_allclose(cam.camera_from_world, ref.camera_from_world @ shift, atol=1e-12)
    np.testing.assert_allclose(cam.K, ref.K)
    assert (cam.rows, cam.cols) == (48, 64) and cam.pixel_spacing_mm == pytest.approx(0.8)
    np.testing.assert_allclose(cam.project(iso_ct[None])[0], [31.5, 23.5], atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(cam.source_world - iso_ct), 450.0)


def test_a_view_may_give_its_own_isocentre(tmp_path: Path) -> None:
    """Views taken with the C-arm moved between shots: each view's ``isocenter_ct_mm`` wins over the
    case's."""
    path = write_navigation_case(replace(_case(), verification=None), tmp_path)
    _write_dicom(tmp_path / "frame.dcm", rows=48, cols=64)
    d = json.loads(path.read_text())
    d["isocenter_ct_mm"] = [1.0, 2.0, 3.0]
    own = [10.0, -20.0, 5.0]
    d["views"][1] = {"name": "dcm", "image": "frame.dcm", "camera": "dicom", "isocenter_ct_mm": own}
    d["views"][2] = {"name": "dcm2", "image": "frame.dcm", "camera": "dicom"}
    path.write_text(json.dumps(d))
    views = load_navigation_case(path).views
    np.testing.assert_allclose(views[1].camera.project(np.array([own]))[0], [31.5, 23.5], atol=1e-9)
    np.testing.assert_allclose(
        views[2].camera.project(np.array([[1.0, 2.0, 3.0]]))[0], [31.5, 23.5], atol=1e-9
    )
    d["views"][1]["isocenter_ct_mm"] = [1.0, 2.0]
    path.write_text(json.dumps(d))
    with pytest.raises(InputError, match=r"views\[1\]\.isocenter_ct_mm"):
        load_navigation_case(path)


# ----- malformed cases ---------------------------------------------------------------------------
Edit = Callable[[dict[str, Any], Path], None]


def _set(*keys: Any, value: Any) -> Edit:
    def edit(d: dict[str, Any], _: Path) -> None:
        node = d
        for k in keys[:-1]:
            node = node[k]
        node[keys[-1]] = value

    return edit


def _delete(*keys: Any) -> Edit:
    def edit(d: dict[str, Any], _: Path) -> None:
        node = d
        for k in keys[:-1]:
            node = node[k]
        del node[keys[-1]]

    return edit


def _bad_plan(d: dict[str, Any], root: Path) -> None:
    (root / "bad_plan.json").write_text("{not json")
    d["plan"] = "bad_plan.json"


def _no_head(d: dict[str, Any], root: Path) -> None:
    write_landmarks_json(root / "other.json", {"pelvis_center": np.zeros(3)})
    d["landmarks"] = "other.json"


def _wrong_size_camera(d: dict[str, Any], root: Path) -> None:
    d["views"][0]["camera"] = _camera(0.0, rows=40, cols=40).to_dict()


def _dup_names(d: dict[str, Any], root: Path) -> None:
    d["views"][2]["name"] = d["views"][0]["name"]


def _inline_camera(**change: Any) -> Edit:
    """views[0]'s camera inline (its own, so only ``change`` is wrong)."""

    def edit(d: dict[str, Any], _: Path) -> None:
        d["views"][0]["camera"] = {**Camera.load(d["views"][0]["camera"]).to_dict(), **change}

    return edit


NOT_RIGID = (np.diag([2.0, 1.0, 1.0, 1.0])).tolist()
MALFORMED: dict[str, tuple[Edit, str]] = {
    "missing-ct": (_delete("ct"), "'ct': missing"),
    "ct-not-found": (_set("ct", value="nope.nii.gz"), "'ct' file not found: nope.nii.gz"),
    "view-without-camera": (_delete("views", 1, "camera"), "views[1].camera: missing (give a camera file"),
    "joints-length": (
        _set("robot", "joints_deg", value=[0.0] * 5),
        "robot.joints_deg has 5 values, the UR10 has 6 joints",
    ),
    "plan-not-json": (_bad_plan, "'plan': "),
    "plan-not-found": (_set("plan", value="gone.json"), "'plan' file not found: gone.json"),
    "ee-not-rigid": (
        _set("robot", "ee_from_cm", value=NOT_RIGID),
        "robot.ee_from_cm: expected a 4x4 rigid matrix (the rotation part is not orthonormal)",
    ),
    "ee-shape": (
        _set("robot", "ee_from_cm", value=NOT_RIGID[:3]),
        "robot.ee_from_cm: expected a 4x4 rigid matrix, got shape (3, 4)",
    ),
    "ee-not-numbers": (_set("robot", "ee_from_cm", value=5), "robot.ee_from_cm: expected a 4x4 rigid matrix"),
    "image-camera-size": (_wrong_size_camera, "views[0]: the image is 32x40"),
    "duplicate-names": (_dup_names, "views[2].name 'ap' is used twice"),
    "unknown-key": (_set("veiws", value=[]), "unknown key(s) ['veiws']; allowed:"),
    "no-femoral-head": (_no_head, "landmark 'femoral_head_left'"),
    "fbg-length": (_set("fbg_control_points_deg", value=[0.0] * 4), "fbg_control_points_deg has 4 values"),
    "fbg-sigma-zero": (_set("fbg_sigma_deg", value=0), "'fbg_sigma_deg': input should be greater than 0"),
    "fbg-sigma-text": (_set("fbg_sigma_deg", value="0.1"), "'fbg_sigma_deg': input should be a valid number"),
    "fbg-sigma-alone": (_delete("fbg_control_points_deg"), "'fbg_sigma_deg' is given without"),
    "verification-joints": (
        _set("verification", "joints_deg", value=[0.0] * 7),
        "verification.joints_deg has 7 values, the UR10 has 6 joints",
    ),
    "joint-outside-limits": (_set("robot", "joints_deg", 2, value=400.0), "robot.joints_deg[2] = 400"),
    "mask-without-landmarks": (
        _delete("views", 1, "landmarks_px"),
        "views[1].mask: given without landmarks_px",
    ),
    "bad-robot-model": (_set("robot", "model", value="UR-10"), "robot.model 'UR-10' is neither"),
    "moved-from-unknown-view": (
        _set("verification", "views", 1, "same_camera_as", value="lateral view"),
        "verification.views[1] names view 'lateral view', which is not among the views",
    ),
    "moved-from-and-same-camera": (
        _set("verification", "views", 0, "same_camera_as", value="ap"),
        "verification.views[0]: give same_camera_as or moved_from, not both",
    ),
    "carm-motion-not-rigid": (
        _set("verification", "views", 0, "moved_from", "carm_after_from_carm_before", value=NOT_RIGID),
        "verification.views[0].moved_from.carm_after_from_carm_before: expected a 4x4 rigid matrix",
    ),
    "moved-from-malformed": (
        _set("verification", "views", 0, "moved_from", value="ap"),
        "verification.views[0].moved_from: expected an object with keys ['view', 'carm_after_from",
    ),
    "missing-robot-key": (
        _delete("robot", "joints_deg"),
        "robot.joints_deg: missing (give the joint readings",
    ),
    "joint-not-a-number": (
        _set("robot", "joints_deg", 1, value=True),
        "robot.joints_deg[1]: input should be",
    ),
    "unknown-view-key": (
        _set("views", 0, "camrea", value="x"),
        "views[0]: unknown key(s) ['camrea']; allowed:",
    ),
    "side-not-an-enum": (_set("side", value="both"), "'side': input should be 'left' or 'right'"),
    "no-views": (_set("views", value=[]), "'views': list should have at least 1 item"),
    "plan-a-number": (_set("plan", value=3), "'plan': expected a plan file or an inline plan object"),
    "isocentre-length": (_set("isocenter_ct_mm", value=[1.0, 2.0]), "'isocenter_ct_mm': expected 3 numbers"),
    "landmarks-not-finite": (
        _set("views", 1, "landmarks_px", 0, value=[float("nan"), 1.0]),
        "views[1].landmarks_px: expected [[uA, vA], [uB, vB]] (pixels) of finite numbers",
    ),
    "inline-camera-spacing": (
        _inline_camera(pixel_spacing_mm=-0.5),
        "views[0].camera.pixel_spacing_mm: input should be greater than 0",
    ),
    "inline-camera-not-rigid": (
        _inline_camera(camera_from_world=NOT_RIGID),
        "views[0].camera.camera_from_world: expected a 4x4 rigid matrix",
    ),
    "inline-camera-unknown-key": (_inline_camera(pixel_spacing=0.8), "views[0].camera: unknown key(s)"),
    "phantom-with-labels": (_set("ct", value="phantom"), "['labels', 'landmarks'] cannot be given with 'ct'"),
    "seed-without-phantom": (_set("phantom_seed", value=1), "'phantom_seed' is only for 'ct': \"phantom\""),
}


@pytest.fixture(scope="module")
def written_case(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_navigation_case(_case(), tmp_path_factory.mktemp("case"))


@pytest.mark.parametrize("name", list(MALFORMED))
def test_malformed_case_names_the_file_and_the_key(written_case: Path, tmp_path: Path, name: str) -> None:
    edit, expected = MALFORMED[name]
    d = json.loads(written_case.read_text())
    for k in ("ct", "labels", "landmarks", "plan"):  # the files stay where they were written
        d[k] = str(written_case.parent / d[k])
    for entry in (*d["views"], *d["verification"]["views"]):
        for k in ("image", "camera", "mask"):
            if k in entry:
                entry[k] = str(written_case.parent / entry[k])
    edit(d, tmp_path)
    path = tmp_path / "case.json"
    path.write_text(json.dumps(d))
    with pytest.raises(InputError) as info:
        load_navigation_case(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "\n" not in message
    assert expected in message
    if name == "plan-not-json":
        assert "bad_plan.json" in message and "not valid JSON" in message


def test_every_required_key_says_what_to_give() -> None:
    """A missing key's message is ``<key>: missing (give <its description>)``."""
    for model in (CaseFile, RobotEntry, ViewEntry, MovedFrom, Verification, InlineCamera):
        for key, field in model.model_fields.items():
            assert not field.is_required() or field.description, f"{model.__name__}.{key}"


def test_writer_rejects_extra_keys_that_would_not_load(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="would not load"):
        write_navigation_case(_case(), tmp_path, extra={"truth": 1})
    with pytest.raises(ValueError, match="written from the case"):
        write_navigation_case(_case(), tmp_path, extra={"views": []})


# ----- DH robot files ------------------------------------------------------------------------------
def test_dh_file_of_the_ur10_table_gives_the_ur10_kinematics(tmp_path: Path) -> None:
    path = tmp_path / "ur10.json"
    path.write_text(json.dumps(robot_to_dict(UR10)))
    robot = load_robot(path)
    assert robot == UR10 and load_robot("ur10") is UR10
    q = np.random.default_rng(1).uniform(-180.0, 180.0, (20, 6))
    np.testing.assert_allclose(robot.rbase_from_ee(q), UR10.rbase_from_ee(q), atol=1e-9)
    minimal = {
        "dh": [{k: v for k, v in r.items() if k != "theta_offset_deg"} for r in robot_to_dict(UR10)["dh"]]
    }
    path.write_text(json.dumps(minimal))
    robot = load_robot(path)
    assert robot.name == "ur10" and robot.joint_limits_deg == UR10.joint_limits_deg
    np.testing.assert_allclose(robot.rbase_from_ee(q), UR10.rbase_from_ee(q), atol=1e-9)


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        ("{oops", "not valid JSON"),
        ('{"dh": []}', "'dh' must be a non-empty list"),
        ('{"dh": [{"a_mm": 0, "alpha_deg": 90}]}', "dh[0]: missing 'd_mm'"),
        ('{"dh": [{"a_mm": "x", "alpha_deg": 90, "d_mm": 1}]}', "dh[0].a_mm must be a finite number"),
        ('{"dh": [{"a_mm": 0, "alpha_deg": 90, "d_mm": 1, "b": 2}]}', "dh[0]: unknown key(s) ['b']"),
        ('{"dh": [{"a_mm": 0, "alpha_deg": 90, "d_mm": 1}], "joint_limits_deg": [[5, -5]]}', "lower 5.0"),
        ('{"dh": [{"a_mm": 0, "alpha_deg": 90, "d_mm": 1}], "joint_limits_deg": []}', "one [lo, hi] pair"),
        ('{"links": []}', "unknown key(s) ['links']"),
    ],
)
def test_malformed_dh_file_is_an_input_error(tmp_path: Path, content: str, expected: str) -> None:
    path = tmp_path / "robot.json"
    path.write_text(content)
    with pytest.raises(InputError) as info:
        load_robot(path)
    assert str(info.value).startswith(str(path)) and expected in str(info.value)
    with pytest.raises(InputError, match="neither"):
        load_robot(tmp_path / "missing.json", source="case.json")
