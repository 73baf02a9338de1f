"""Level presets (the authors' numbers), ROI cameras and trace serialisation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fluoronav.geometry.camera import Camera
from fluoronav.registration.levels import CM_SIGMA, LevelConfig, cm_levels, patch_radius_for, pelvis_levels
from fluoronav.registration.optimizer import IterationRecord
from fluoronav.registration.roi import (
    CropBox,
    area_downsample,
    crop_and_downsample_image,
    full_to_roi_px,
    roi_camera_from_landmarks,
    roi_to_full_px,
)
from fluoronav.registration.trace import LevelTrace, RegistrationTrace


def test_patch_radius_rule() -> None:
    # the authors: round(41 × downsampling factor) with xReg's factor = scale = 1/downsample
    assert patch_radius_for(1) == 41
    assert patch_radius_for(4) == 10  # 10.25
    assert patch_radius_for(2) == 21  # 20.5 rounds half away from zero, as C++
    assert patch_radius_for(8) == 5
    lv = cm_levels()[0]
    assert (lv.downsample, lv.radius, lv.stride, lv.popsize, lv.tolx, lv.tolfun) == (4, 10, 5, 50, 0.01, 0.01)
    assert lv.sigma == CM_SIGMA and lv.landmark_sigma_px == 25.0 and lv.landmark_sigma_full_px == 100.0
    assert lv.with_(downsample=2).radius == 21
    assert LevelConfig(sigma=(1.0,), downsample=2, patch_radius=3).radius == 3
    p = pelvis_levels()
    assert p[0].sigma == (30.0, 30.0, 30.0, 50.0, 50.0, 100.0) and p[0].stride == 1
    with pytest.raises(ValueError):
        LevelConfig(sigma=(1.0,), downsample=0)
    with pytest.raises(ValueError):
        LevelConfig(sigma=(0.0,))


def test_roi_camera_matches_crop_and_downsample() -> None:
    K = np.array([[5257.7, 0, 767.5], [0, 5257.7, 767.5], [0, 0, 1]])
    cam = Camera(1536, 1536, K, np.eye(4), 0.194)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-20, 20, 20), rng.uniform(-20, 20, 20), rng.uniform(400, 600, 20)])
    landmarks = np.array([[700.3, 820.9], [905.1, 760.2]])
    roi, box = roi_camera_from_landmarks(cam, landmarks, size=500, downsample=4)
    assert (roi.rows, roi.cols) == (125, 125) and (box.rows, box.cols) == (500, 500)
    assert math.isclose(roi.pixel_spacing_mm, 0.194 * 4)
    # the crop is centred on the landmarks' midpoint
    mid = landmarks.mean(0)
    assert abs(box.col0 + 249.5 - mid[0]) <= 0.5 and abs(box.row0 + 249.5 - mid[1]) <= 0.5
    full = cam.project(pts)
    np.testing.assert_allclose(roi.project(pts), full_to_roi_px(full, box, 4), atol=1e-9)
    np.testing.assert_allclose(roi_to_full_px(roi.project(pts), box, 4), full, atol=1e-9)


def test_crop_and_downsample_image_is_consistent_with_camera() -> None:
    # an image whose pixel (r, c) holds u = c: after crop and 4× binning it must hold the full-image
    # u of each ROI pixel centre, i.e. roi_to_full_px
    H, W = 64, 80
    u = np.tile(np.arange(W, dtype=np.float64), (H, 1))
    v = np.tile(np.arange(H, dtype=np.float64)[:, None], (1, W))
    box = CropBox(row0=6, col0=10, rows=40, cols=48)
    ru = crop_and_downsample_image(u, box, 4)
    rv = crop_and_downsample_image(v, box, 4)
    assert isinstance(ru, np.ndarray) and ru.shape == (10, 12)
    vv, uu = np.mgrid[0:10, 0:12]
    back = roi_to_full_px(np.stack([uu, vv], -1).astype(np.float64), box, 4)
    np.testing.assert_allclose(ru, back[..., 0], atol=1e-12)
    np.testing.assert_allclose(rv, back[..., 1], atol=1e-12)
    # a box past the edge replicates the border
    edge = crop_and_downsample_image(torch.from_numpy(u), CropBox(-4, 72, 8, 16), 4)
    assert isinstance(edge, torch.Tensor) and edge.shape == (2, 4)
    np.testing.assert_allclose(edge[0].numpy(), [73.5, 77.5, 79.0, 79.0])
    x = torch.arange(2 * 6 * 7, dtype=torch.float64).reshape(2, 6, 7)
    torch.testing.assert_close(area_downsample(x, 3)[1, 1, 0], x[1, 3:6, 0:3].mean())


def test_trace_json_round_trip() -> None:
    rec = IterationRecord(
        iteration=1,
        best_cost=0.5,
        mean_cost=float("nan"),
        sigma=1.0,
        best_params=(1.0, 2.0),
        n_evals=10,
        elapsed_s=0.1,
    )
    tr = RegistrationTrace(
        parameter_names=["a", "b"],
        levels=[
            LevelTrace(
                index=0,
                name="l0",
                config={"sigma": (1.0, 2.0)},
                x_start=[0.0, 0.0],
                x=[1.0, 2.0],
                cost=0.5,
                n_evals=10,
                n_iters=1,
                converged=True,
                stop_reason="tolx",
                iterations=[rec],
            )
        ],
    )
    text = tr.to_json()
    assert "NaN" not in text
    back = RegistrationTrace.from_json(text)
    assert back.levels[0].iterations[0].best_params == (1.0, 2.0)
    assert math.isnan(back.levels[0].iterations[0].mean_cost)
    assert back.n_evals == 10 and back.levels[0].converged
