"""The reached CM's tip fused from the images and the kinematics (``fuse_tip``) and the distance of
the images' own landmarks from a predicted pose (``landmark_gap_mm``): against hand-computed
information-weighted means and projections."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch

from fluoronav.geometry import se3
from fluoronav.geometry.camera import Camera, DetectorSpec
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.registration.cm import CMRegistrationResult
from fluoronav.registration.view_set.cm import landmark_gap_mm
from fluoronav.registration.view_set.fusion import TipFusionConfig, fuse_tip

SPEC = DetectorSpec(rows=256, cols=256, pixel_spacing_mm=0.5, sdd_mm=1000.0)
#: the CM's tip at the isocentre, 600 mm from each source
TIP = np.array([0.0, 0.0, 0.0])


def _camera_looking_along(axis: str) -> Camera:
    """A camera 600 mm from the origin on the −z axis ("z", the beam along +z) or the −x axis ("x",
    the beam along +x)."""
    # "x": camera z = world x, camera x = world −z
    R = np.eye(3) if axis == "z" else np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    return Camera.from_detector(SPEC, se3.make(R, (0.0, 0.0, 600.0)))


def _result(world_from_cm: np.ndarray, tip: np.ndarray, cameras: list[Camera]) -> CMRegistrationResult:
    ab = np.array([[tip - np.array([0.0, 0.0, 20.0]), tip]])
    fields: dict[str, Any] = {
        "workflow": "multi-view",
        "world_from_cm": world_from_cm[None],
        "camera_from_cm": np.stack([c.camera_from_world @ world_from_cm for c in cameras]),
        "control_points_deg": np.zeros(5),
        "joint_angles_deg": np.zeros(27),
        "tip_world": tip[None],
        "landmarks_world": ab,
        "landmarks_px": np.stack([c.project(ab[0]) for c in cameras]),
        "cost": -1.0,
        "converged": True,
        "success": True,
        "reason": "converged",
        "trace": SimpleNamespace(),
        "seconds": 0.0,
        "params": np.zeros(11),
        "view_names": [f"v{k}" for k in range(len(cameras))],
        "roi_images": np.zeros((len(cameras), 4, 4)),
        "roi_drrs": np.zeros((len(cameras), 4, 4)),
        "roi_cameras": cameras,
    }
    return CMRegistrationResult(**fields)


def test_two_orthogonal_views_keep_the_images_tip_up_to_the_weights() -> None:
    cams = [_camera_looking_along("z"), _camera_looking_along("x")]
    tip_img = TIP.copy()
    predicted = np.array([1.0, -1.0, 2.0])
    cfg = TipFusionConfig(inplane_sigma_mm=0.3, depth_sigma_mm=3.0)
    fused, diag = fuse_tip(_result(se3.make(np.eye(3), tip_img), tip_img, cams), cams, predicted, 1.0, cfg)
    # the ray of view 1 is along world z (in-plane x, y), of view 2 along world x (in-plane y, z):
    # information per axis: x 1/0.3² + 1/3², y 2/0.3², z 1/0.3² + 1/3²; the kinematics 1/1² each
    img = np.array([1 / 0.09 + 1 / 9.0, 2 / 0.09, 1 / 0.09 + 1 / 9.0])
    expected = (img * tip_img + 1.0 * predicted) / (img + 1.0)
    np.testing.assert_allclose(fused.tip_world[0], expected, atol=1e-9)
    np.testing.assert_allclose(diag["fusion_shift_mm"], np.linalg.norm(expected - tip_img), atol=1e-9)
    # the whole CM moved with its tip: base, landmarks and their projections
    shift = expected - tip_img
    np.testing.assert_allclose(fused.world_from_cm[0][:3, 3], shift, atol=1e-9)
    np.testing.assert_allclose(
        fused.landmarks_world[0], _result(np.eye(4), TIP, cams).landmarks_world[0] + shift
    )
    for k, c in enumerate(cams):
        np.testing.assert_allclose(fused.landmarks_px[k], c.project(fused.landmarks_world[0]), atol=1e-9)
        np.testing.assert_allclose(fused.camera_from_cm[k], c.camera_from_world @ fused.world_from_cm[0])
    assert diag["image_depth_sigma_mm"] == pytest.approx(1 / np.sqrt(1 / 0.09 + 1 / 9.0))
    # their difference over the combined covariance (per axis 1/img + 1²)
    d = tip_img - predicted
    assert diag["mahalanobis"] == pytest.approx(np.sqrt(np.sum(d**2 / (1 / img + 1.0))))


def test_one_view_takes_its_depth_from_the_kinematics() -> None:
    cam = _camera_looking_along("z")
    predicted = np.array([0.0, 0.0, 4.0])  # 4 mm deeper along the one view's ray, same in-plane
    cfg = TipFusionConfig(inplane_sigma_mm=0.3, depth_sigma_mm=3.0)
    fused, diag = fuse_tip(_result(np.eye(4), TIP, [cam]), [cam], predicted, 0.8, cfg)
    w = (1 / 0.8**2) / (1 / 0.8**2 + 1 / 3.0**2)
    # the ray from the source (0, 0, −600) to the tip is the world z axis: depth is z
    np.testing.assert_allclose(fused.tip_world[0], [0.0, 0.0, 4.0 * w], atol=1e-9)
    assert w > 0.9 and diag["image_depth_sigma_mm"] == pytest.approx(3.0)
    # across the ray the image wins: a prediction 2 mm off in x moves the tip by 2·0.3²/(0.3²+0.8²)
    fused2, _ = fuse_tip(_result(np.eye(4), TIP, [cam]), [cam], np.array([2.0, 0.0, 0.0]), 0.8, cfg)
    np.testing.assert_allclose(fused2.tip_world[0][0], 2.0 * 0.09 / (0.09 + 0.64), atol=1e-9)


def _landmarks_world(world_from_cm: np.ndarray, cp: np.ndarray) -> np.ndarray:
    ab = CMKinematics(CMConfig()).landmarks_cm(torch.as_tensor(cp)).numpy()
    return ab @ world_from_cm[:3, :3].T + world_from_cm[:3, 3]


def test_landmark_gap_with_one_view_is_the_reprojection_distance_at_the_cm() -> None:
    cam = _camera_looking_along("z")
    cp = np.zeros(5)
    W = se3.make(np.eye(3), (0.0, 0.0, 0.0))
    ab = _landmarks_world(W, cp)
    lm = cam.project(ab) + np.array([[3.0, 4.0], [0.0, 0.0]])  # A 5 px off
    views = [SimpleNamespace(camera=cam)]
    depth_a = cam.to_camera(ab)[0, 2]
    expected = 5.0 * depth_a / cam.K[0, 0]
    got = landmark_gap_mm(views, [lm], None, W, CMConfig(), cp)  # type: ignore[arg-type]
    assert got == pytest.approx(expected, rel=1e-9)
    assert landmark_gap_mm(views, [None], None, W, CMConfig(), cp) == np.inf  # type: ignore[arg-type]


def test_landmark_gap_with_two_views_is_the_triangulated_distance() -> None:
    cp = np.zeros(5)
    W = np.eye(4)
    ab = _landmarks_world(W, cp)
    init = SimpleNamespace(landmarks_world=ab + np.array([[0.0, 0.0, 0.0], [1.5, 2.0, 0.0]]))
    got = landmark_gap_mm([], [], init, W, CMConfig(), cp)  # type: ignore[arg-type]
    assert got == pytest.approx(2.5)
