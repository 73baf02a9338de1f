"""CM kinematics against closed forms: straight CM, constant curvature, spline interpolation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fluoronav.manipulator import CMConfig, CMKinematics


@pytest.fixture(scope="module")
def kin() -> CMKinematics:
    return CMKinematics(CMConfig())


def test_zero_control_points_give_a_straight_cm(kin: CMKinematics) -> None:
    c = kin.config
    cp = torch.zeros(c.n_control_points, dtype=torch.float64)
    A, B = kin.landmarks_cm(cp)
    np.testing.assert_allclose(A.numpy(), [0.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(B.numpy(), [0.0, 0.0, c.distal_notch_plane_mm], atol=1e-12)
    np.testing.assert_allclose(kin.tip_cm(cp).numpy(), [0.0, 0.0, c.tip_z_mm], atol=1e-12)
    T = kin.link_transforms(cp).numpy()
    np.testing.assert_allclose(T, np.broadcast_to(np.eye(4), T.shape), atol=1e-12)


def _constant_curvature_tip(c: CMConfig, phi: float) -> np.ndarray:
    """Tip after N equal joints of angle φ about centres spaced by the pitch (geometric sums).

    Joint 0 sits at z_0; after joint j the axis points along R_x((j+1)φ)·ẑ = (0, −sin, cos), so
    joint n−1 is at z_0·ẑ + p·Σ_{k=1}^{N−1} (0, −sin kφ, cos kφ) and the tip lies
    (tip_z − z_{N−1}) further along R_x(Nφ)·ẑ. Σ_{k=1}^{n} sin kφ = sin(nφ/2) sin((n+1)φ/2)/sin(φ/2)
    and likewise with cos.
    """
    N, p = c.n_notches, c.notch_pitch_mm
    n = N - 1
    ratio = math.sin(n * phi / 2) / math.sin(phi / 2)
    sum_sin = ratio * math.sin((n + 1) * phi / 2)
    sum_cos = ratio * math.cos((n + 1) * phi / 2)
    last = c.tip_z_mm - c.notch_z_mm(N - 1)
    y = -p * sum_sin - last * math.sin(N * phi)
    z = c.notch_z_mm(0) + p * sum_cos + last * math.cos(N * phi)
    return np.array([0.0, y, z])


@pytest.mark.parametrize("angle_deg", [-7.9, -2.5, 0.3, 4.0, 7.9])
def test_equal_control_points_give_constant_curvature(kin: CMKinematics, angle_deg: float) -> None:
    c = kin.config
    cp = torch.full((c.n_control_points,), angle_deg, dtype=torch.float64)
    np.testing.assert_allclose(kin.joint_angles_deg(cp).numpy(), angle_deg, atol=1e-12)
    tip = kin.tip_cm(cp).numpy()
    np.testing.assert_allclose(tip, _constant_curvature_tip(c, math.radians(angle_deg)), rtol=0, atol=1e-9)


def test_spline_reproduces_control_points_at_knots(kin: CMKinematics) -> None:
    """Between (and beyond) knots the joint angles are one cubic; refit it from the integer samples."""
    c = kin.config
    rng = np.random.default_rng(3)
    cp = rng.uniform(*c.control_point_range_deg, size=c.n_control_points)
    phi = kin.joint_angles_deg(torch.tensor(cp)).numpy()
    j = np.arange(c.n_notches, dtype=float)
    knots = np.asarray(c.knot_positions())
    edges = np.concatenate([[-np.inf], knots, [np.inf]])
    for piece in range(len(edges) - 1):
        lo, hi = edges[piece], edges[piece + 1]
        if piece == 0:  # left end piece: also used on [knot_0, knot_1]
            hi = knots[1]
        if piece == len(edges) - 2:
            lo = knots[-2]
        sel = (j >= lo) & (j <= hi)
        assert sel.sum() >= 4
        coeff = np.polyfit(j[sel], phi[sel], 3)
        for i, k in enumerate(knots):
            if lo <= k <= hi:
                assert np.polyval(coeff, k) == pytest.approx(cp[i], abs=1e-9)


def test_link_transforms_are_rigid_and_batched(kin: CMKinematics) -> None:
    rng = np.random.default_rng(0)
    cp = torch.tensor(rng.uniform(-7.9, 7.9, size=(3, 5)))
    T = kin.link_transforms(cp)
    assert T.shape == (3, kin.n_links, 4, 4)
    R = T[..., :3, :3]
    eye = torch.eye(3, dtype=T.dtype).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(T[1], kin.link_transforms(cp[1]), atol=1e-12, rtol=0)
