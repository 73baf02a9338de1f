"""Views taken again from an earlier registration's C-arm positions: the check that the anatomy
stayed (``unmoved_ncc``) and the earlier bones handed on (``unmoved_bones``, ``known_bones``)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy import ndimage

from fluoronav.geometry.camera import Camera, DetectorSpec
from fluoronav.registration.bone import BoneView
from fluoronav.registration.view_set import FluoroView, ViewDetection
from fluoronav.registration.view_set.unmoved import unmoved_bones, unmoved_ncc

SPEC = DetectorSpec(rows=256, cols=256, pixel_spacing_mm=0.5, sdd_mm=1000.0)
CAM = Camera.from_detector(SPEC)


def _anatomy(shift_px: float = 0.0, seed: int = 0, noise: float = 0.002) -> np.ndarray:
    """A smooth bony pattern (blurred blobs), shifted by ``shift_px`` columns, with noise."""
    rng = np.random.default_rng(1)
    base = ndimage.gaussian_filter(rng.random((256, 256)), 6.0)
    moved = ndimage.shift(base, (0.0, shift_px), order=3, mode="nearest")
    return moved + np.random.default_rng(seed).normal(0.0, noise, moved.shape)


def test_the_same_scene_agrees_and_a_shifted_one_does_not() -> None:
    same = unmoved_ncc(BoneView(_anatomy(seed=1), CAM), BoneView(_anatomy(seed=2), CAM))
    shifted = unmoved_ncc(BoneView(_anatomy(seed=1), CAM), BoneView(_anatomy(4.0, seed=2), CAM))
    assert same > 0.99 and shifted < same - 0.05


def test_the_instruments_of_both_images_are_left_out() -> None:
    a, b = _anatomy(seed=1), _anatomy(seed=2)
    mask_a, mask_b = np.ones((256, 256), bool), np.ones((256, 256), bool)
    a[40:60, 30:200], b[150:170, 30:200] = 5.0, 5.0  # the CM before and after its move
    mask_a[38:62, 28:202], mask_b[148:172, 28:202] = False, False
    with_masks = unmoved_ncc(BoneView(a, CAM, mask_a), BoneView(b, CAM, mask_b))
    without = unmoved_ncc(BoneView(a, CAM), BoneView(b, CAM))
    assert with_masks > 0.99 and without < 0.9


def test_images_of_other_sizes_are_an_error() -> None:
    small = Camera.from_detector(DetectorSpec(rows=128, cols=128, pixel_spacing_mm=1.0, sdd_mm=1000.0))
    with pytest.raises(ValueError, match="pixels"):
        unmoved_ncc(BoneView(_anatomy(), CAM), BoneView(np.zeros((128, 128)), small))


def _view(name: str, image: np.ndarray) -> FluoroView:
    det = ViewDetection(
        np.array([[10.0, 10.0], [20.0, 20.0]]),
        np.array([[10.0, 10.0], [20.0, 20.0]]),
        np.zeros((256, 256), bool),
        np.ones(2),
        "case",
    )
    return FluoroView(name, image, CAM, det)


def _earlier() -> SimpleNamespace:
    moved = np.eye(4)
    moved[:3, 3] = (1.0, 2.0, 3.0)
    return SimpleNamespace(
        views=(_view("AP", _anatomy(seed=1)), _view("oblique", _anatomy(5.0, seed=3))),
        pelvis=("pelvis AP", "pelvis oblique"),
        cameras_ct=(CAM.with_pose(moved), CAM),
        femur="femur",
    )


def test_unmoved_views_keep_the_earlier_bones() -> None:
    earlier = _earlier()
    later = [_view("AP again", _anatomy(seed=7))]
    bones, ncc = unmoved_bones(later, earlier, [0], min_ncc=0.99)  # type: ignore[arg-type]
    assert bones is not None and set(ncc) == {"AP again"}
    assert bones.pelvis == ("pelvis AP",) and bones.femur == "femur"
    np.testing.assert_array_equal(bones.cameras[0].camera_from_world, earlier.cameras_ct[0].camera_from_world)


def test_a_moved_anatomy_registers_the_bones_again() -> None:
    later = [_view("AP again", _anatomy(3.0, seed=7))]
    bones, ncc = unmoved_bones(later, _earlier(), [0], min_ncc=0.99)  # type: ignore[arg-type]
    assert bones is None and ncc["AP again"] < 0.99
