"""Camera model: projection against hand computation, files, crop/downsample."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from fluoronav.errors import InputError
from fluoronav.geometry import CIOS_FUSION, Camera, DetectorSpec, carm_camera, orbit_camera, project_points
from fluoronav.geometry.carm import carm_camera_from_world


def _rotation(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    t = math.radians(angle_deg)
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K


def test_projection_matches_hand_computed_pinhole() -> None:
    # 1000 mm SDD, 0.5 mm pixels → f = 2000 px; principal point (99.5, 49.5) for 200 cols × 100 rows.
    cam = Camera.from_detector(DetectorSpec(rows=100, cols=200, pixel_spacing_mm=0.5, sdd_mm=1000.0))
    # A point 10 mm right, 5 mm down at 500 mm depth: magnification 2 → 20 mm, 10 mm at the detector
    # → 40 px and 20 px from the principal point.
    uv = cam.project(np.array([10.0, 5.0, 500.0]))
    assert uv == pytest.approx([99.5 + 40.0, 49.5 + 20.0], abs=1e-12)


def test_projection_with_pose_matches_manual_transform() -> None:
    T = np.eye(4)
    T[:3, :3] = _rotation(np.array([1.0, 2.0, 3.0]), 37.0)
    T[:3, 3] = [5.0, -7.0, 600.0]
    cam = Camera(
        rows=64, cols=80, K=np.array([[1500.0, 0, 40.0], [0, 1400.0, 30.0], [0, 0, 1]]), camera_from_world=T
    )
    p = np.array([[3.0, 4.0, 5.0], [-20.0, 10.0, 0.0]])
    cam_pts = p @ T[:3, :3].T + T[:3, 3]
    expected = np.stack(
        [1500 * cam_pts[:, 0] / cam_pts[:, 2] + 40, 1400 * cam_pts[:, 1] / cam_pts[:, 2] + 30], 1
    )
    np.testing.assert_allclose(cam.project(p), expected, atol=1e-10)
    # torch batched version agrees
    uv_t = project_points(torch.as_tensor(cam.K), torch.as_tensor(cam.camera_from_world), torch.as_tensor(p))
    np.testing.assert_allclose(uv_t.numpy(), expected, atol=1e-10)


def test_backproject_inverts_project() -> None:
    cam = carm_camera(lao_rao_deg=30.0, cran_caud_deg=95.0, source_to_isocenter_mm=450.0)
    p = np.array([[10.0, -20.0, 30.0], [0.0, 0.0, 0.0]])
    depth = cam.to_camera(p)[:, 2]
    np.testing.assert_allclose(cam.backproject(cam.project(p), depth), p, atol=1e-9)


def test_rays_pass_through_projected_point() -> None:
    cam = carm_camera(lao_rao_deg=120.0, cran_caud_deg=80.0, source_to_isocenter_mm=420.0)
    p = np.array([12.0, 3.0, -40.0])
    d = cam.ray_directions_world(cam.project(p))
    v = p - cam.source_world
    assert np.allclose(d, v / np.linalg.norm(v), atol=1e-12)


def test_cios_preset_and_ap_view_orientation() -> None:
    assert CIOS_FUSION.K()[0, 0] == pytest.approx(1020.0 / 0.194)
    cam = carm_camera(source_to_isocenter_mm=450.0)
    # AP: source posterior (+y in LPS), looking anterior; isocentre projects to the image centre.
    assert cam.source_world == pytest.approx([0.0, 450.0, 0.0], abs=1e-9)
    assert cam.project(np.zeros(3)) == pytest.approx([767.5, 767.5])
    # the head (+z, superior) is towards the top of the image (smaller v)
    assert cam.project(np.array([0.0, 0.0, 10.0]))[1] < 767.5
    # the camera frame is right-handed and rigid
    R = cam.camera_from_world[:3, :3]
    assert np.linalg.det(R) == pytest.approx(1.0)


def test_carm_angles_place_source_on_sphere() -> None:
    iso = np.array([5.0, -3.0, 20.0])
    for a, b in [(0, 90), (90, 90), (200, 75), (315, 105)]:
        T = carm_camera_from_world(
            lao_rao_deg=a, cran_caud_deg=b, source_to_isocenter_mm=480.0, isocenter_world=iso
        )
        cam = Camera(10, 10, np.eye(3), T)
        assert np.linalg.norm(cam.source_world - iso) == pytest.approx(480.0)
        # the isocentre lies on the optical axis
        c = cam.to_camera(iso[None])[0]
        assert c[:2] == pytest.approx([0, 0], abs=1e-9)
        assert c[2] == pytest.approx(480.0)


def test_orbit_rotation_keeps_isocentre_on_axis() -> None:
    iso = np.array([0.0, 0.0, 0.0])
    cam = carm_camera(source_to_isocenter_mm=450.0)
    cam2 = orbit_camera(cam, angle_deg=20.0, isocenter_world=iso)
    assert cam2.project(iso) == pytest.approx(cam.project(iso))
    d1 = cam.source_world / 450.0
    d2 = cam2.source_world / 450.0
    assert math.degrees(math.acos(np.clip(d1 @ d2, -1, 1))) == pytest.approx(20.0)


def test_crop_and_downsample_are_consistent_with_full_image() -> None:
    cam = carm_camera()
    p = np.array([[3.0, 4.0, 5.0], [30.0, -12.0, 8.0]])
    uv = cam.project(p)
    crop, (r0, c0) = cam.crop_around(uv[0], 500)
    np.testing.assert_allclose(crop.project(p), uv - [c0, r0], atol=1e-9)
    down = crop.downsample(4)
    assert (down.rows, down.cols) == (125, 125)
    # the centre of binned pixel (u', v') lies at 4u' + 1.5 in the crop
    np.testing.assert_allclose(4 * down.project(p) + 1.5, crop.project(p), atol=1e-9)
    assert down.pixel_spacing_mm == pytest.approx(4 * 0.194)
    scaled = cam.scaled_to(384, 384)
    np.testing.assert_allclose((scaled.project(p) + 0.5) * 4 - 0.5, uv, atol=1e-9)


def test_camera_file_round_trip(tmp_path) -> None:
    T = np.eye(4)
    T[:3, :3] = _rotation(np.array([0.3, -1.0, 0.2]), 71.0)
    T[:3, 3] = [1.0, 2.0, 3.0]
    cam = Camera(
        rows=300,
        cols=420,
        K=np.array([[5000.0, 0, 209.5], [0, 5010.0, 149.5], [0, 0, 1]]),
        camera_from_world=T,
        pixel_spacing_mm=0.2,
    )
    f = tmp_path / "cam.json"
    cam.save(f)
    back = Camera.load(f)
    assert (back.rows, back.cols) == (300, 420)
    np.testing.assert_array_equal(back.K, cam.K)
    np.testing.assert_allclose(back.camera_from_world, cam.camera_from_world, atol=0)
    assert back.pixel_spacing_mm == 0.2


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        ("", "empty"),
        ("{not json", "not valid JSON"),
        ("[1, 2]", "JSON object"),
        ('{"rows": 10, "cols": 10, "K": [[1,0,0],[0,1,0],[0,0,1]]}', "missing camera_from_world"),
        (
            '{"rows": 10, "cols": 10, "K": [[1,0,0],[0,1,0]], "camera_from_world": '
            "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}",
            "K must be 3x3",
        ),
        (
            '{"rows": -1, "cols": 10, "K": [[1,0,0],[0,1,0],[0,0,1]], "camera_from_world": '
            "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}",
            "positive",
        ),
        (
            '{"rows": 10, "cols": 10, "K": [[1,0,0],[0,1,0],[0,0,1]], "camera_from_world": '
            "[[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}",
            "not a rigid transform",
        ),
    ],
)
def test_malformed_camera_files_name_the_file(tmp_path, content: str, problem: str) -> None:
    f = tmp_path / "bad.json"
    f.write_text(content)
    with pytest.raises(InputError) as info:
        Camera.load(f)
    assert str(f) in str(info.value)
    assert problem in str(info.value)


def test_missing_camera_file(tmp_path) -> None:
    with pytest.raises(InputError, match="cannot read"):
        Camera.load(tmp_path / "nope.json")


def test_contract_keys_in_file(tmp_path) -> None:
    f = tmp_path / "c.json"
    carm_camera().save(f)
    d = json.loads(f.read_text())
    assert {"rows", "cols", "K", "camera_from_world"} <= set(d)


def test_triangulate_points_recovers_world_points() -> None:
    from fluoronav.geometry import carm_camera, orbit_camera, triangulate_points

    rng = np.random.default_rng(5)
    iso = np.array([10.0, -20.0, 30.0])
    ap = carm_camera(source_to_isocenter_mm=450.0, isocenter_world=iso)
    cams = [
        ap,
        orbit_camera(ap, angle_deg=20.0, isocenter_world=iso),
        orbit_camera(ap, angle_deg=-15.0, isocenter_world=iso),
    ]
    pts = iso + rng.uniform(-30, 30, (4, 3))
    uv = np.stack([c.project(pts) for c in cams])
    np.testing.assert_allclose(triangulate_points(cams, uv), pts, atol=1e-7)
    # 0.5 px noise in 3 views ~20° apart at 0.194 mm pixels: sub-millimetre
    noisy = uv + rng.uniform(-0.5, 0.5, uv.shape)
    assert np.max(np.linalg.norm(triangulate_points(cams, noisy) - pts, axis=1)) < 1.0
    with pytest.raises(ValueError):
        triangulate_points(cams[:1], uv[:1])


def test_robust_triangulation_drops_the_view_with_a_wrong_detection() -> None:
    from fluoronav.geometry import carm_camera, orbit_camera, triangulate_points, triangulate_points_robust

    rng = np.random.default_rng(6)
    iso = np.array([0.0, 10.0, -5.0])
    ap = carm_camera(source_to_isocenter_mm=450.0, isocenter_world=iso)
    cams = [ap, orbit_camera(ap, angle_deg=20.0, isocenter_world=iso)]
    cams.append(orbit_camera(ap, angle_deg=-15.0, isocenter_world=iso))
    pts = iso + rng.uniform(-30, 30, (2, 3))
    uv = np.stack([c.project(pts) for c in cams]) + rng.uniform(-1.0, 1.0, (3, 2, 2))
    uv_bad = uv.copy()
    uv_bad[0, 1] += [-150.0, -120.0]  # point 1 detected far off in view 0
    plain = triangulate_points(cams, uv_bad)
    assert np.linalg.norm(plain[1] - pts[1]) > 5.0  # the plain DLT is pulled off
    X, inl, res = triangulate_points_robust(cams, uv_bad, max_residual_px=20.0)
    np.testing.assert_array_equal(inl, [[True, False], [True, True], [True, True]])
    assert np.max(np.linalg.norm(X - pts, axis=1)) < 1.0
    assert res[0, 1] > 100.0 and np.all(res[1:] < 5.0)
    # agreeing views: all kept, same answer as the plain DLT
    X2, inl2, _ = triangulate_points_robust(cams, uv, max_residual_px=20.0)
    assert inl2.all()
    np.testing.assert_allclose(X2, triangulate_points(cams, uv))
    # two views: nothing to tell apart, both kept
    _, inl3, _ = triangulate_points_robust(cams[:2], uv_bad[:2], max_residual_px=20.0)
    assert inl3.all()
