"""The kinematic prediction's stated uncertainty after a move (``prediction_sigma_mm``), against
hand-computed terms; and which verification images a simulated case keeps."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fluoronav.geometry import se3
from fluoronav.navigation.kinematic_prior import KinematicUncertainty, prediction_sigma_mm
from fluoronav.simulation.navigation.scenario import verification_view_indices


class _Robot:
    """A robot whose flange pose is a table of given joint vectors (the motion is what matters)."""

    def __init__(self, poses: dict[float, np.ndarray]) -> None:
        self.poses = poses

    def rbase_from_ee(self, q: np.ndarray) -> np.ndarray:
        return self.poses[float(q[0])]


U = KinematicUncertainty(registration_mm=0.5, robot_mm=0.3, handeye_deg=0.4, handeye_mm=0.5)


def _rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _sigma(before: np.ndarray, after: np.ndarray, ee_from_cm: np.ndarray) -> float:
    robot = _Robot({0.0: before, 1.0: after})
    return prediction_sigma_mm(
        robot,  # type: ignore[arg-type]
        np.zeros(6),
        np.array([1.0, 0, 0, 0, 0, 0]),
        ee_from_cm=ee_from_cm,
        uncertainty=U,
    )


def test_no_motion_leaves_the_registration_and_the_robot() -> None:
    T = se3.make(_rot_z(30.0), (100.0, 0.0, 400.0))
    assert _sigma(T, T, np.eye(4)) == pytest.approx(math.hypot(0.5, 0.3))


def test_a_translation_adds_the_hand_eye_rotation_times_its_length() -> None:
    before = se3.make(np.eye(3), (0.0, 0.0, 400.0))
    after = se3.make(np.eye(3), (0.0, 100.0, 400.0))
    expected = math.sqrt(0.5**2 + 0.3**2 + (100.0 * math.radians(0.4)) ** 2)
    # the hand-eye matrix turns the CM frame but not the translation's length
    assert _sigma(before, after, se3.make(_rot_z(50.0), (5.0, 0.0, 80.0))) == pytest.approx(expected)


def test_a_rotation_about_the_cm_adds_the_hand_eye_translation_chord() -> None:
    ee_from_cm = se3.make(np.eye(3), (0.0, 0.0, 80.0))
    # the flange turns 60° about the CM's origin: the CM does not translate
    cm_motion = se3.make(_rot_z(60.0), (0.0, 0.0, 0.0))
    before = np.eye(4)
    after = before @ ee_from_cm @ cm_motion @ se3.inv(ee_from_cm)
    expected = math.sqrt(0.5**2 + 0.3**2 + (2.0 * math.sin(math.radians(30.0)) * 0.5) ** 2)
    assert _sigma(before, after, ee_from_cm) == pytest.approx(expected)


@pytest.mark.parametrize(("k", "expected"), [(1, [0]), (2, [1, 2]), (3, [0, 1, 2]), (5, [0, 1, 2])])
def test_verification_views_kept(k: int, expected: list[int]) -> None:
    assert verification_view_indices(3, k) == expected


def test_no_verification_view_is_an_error() -> None:
    with pytest.raises(ValueError, match="at least 1"):
        verification_view_indices(3, 0)
