"""Rigid transforms and rotation parameterisations, per dtype."""

from __future__ import annotations

import math

import pytest
import torch

from fluoronav.geometry.rotations import (
    angle_between_rotations_deg,
    euler_to_matrix,
    matrix_to_quat,
    matrix_to_rotvec,
    quat_to_matrix,
    random_rotation_about_random_axis,
    rotvec_to_matrix,
    rotx,
    roty,
    rotz,
)
from fluoronav.geometry.transforms import (
    apply_transform,
    compose,
    invert_transform,
    make_transform,
    params_from_transform,
    rotation_about_point,
    transform_from_params,
)

TOL = {torch.float32: 1e-5, torch.float64: 1e-12}


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_invert_and_compose(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(0)
    p = torch.randn(7, 6, generator=g, dtype=dtype)
    T = transform_from_params(p)
    eye = torch.eye(4, dtype=dtype).expand(7, 4, 4)
    torch.testing.assert_close(compose(T, invert_transform(T)), eye, atol=TOL[dtype] * 10, rtol=0)
    pts = torch.randn(7, 5, 3, generator=g, dtype=dtype)
    back = apply_transform(invert_transform(T), apply_transform(T, pts))
    torch.testing.assert_close(back, pts, atol=TOL[dtype] * 100, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_params_round_trip(dtype: torch.dtype) -> None:
    g = torch.Generator().manual_seed(1)
    p = torch.randn(10, 6, generator=g, dtype=dtype)
    p[:, :3] = (
        p[:, :3] / p[:, :3].norm(dim=-1, keepdim=True) * torch.rand(10, 1, generator=g, dtype=dtype) * 3
    )
    torch.testing.assert_close(
        params_from_transform(transform_from_params(p)), p, atol=TOL[dtype] * 100, rtol=0
    )


def test_elementary_rotations_match_hand_values() -> None:
    a = torch.tensor(math.pi / 2, dtype=torch.float64)
    e = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    torch.testing.assert_close(rotz(a) @ e, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(roty(a) @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), e)
    torch.testing.assert_close(
        rotx(a) @ torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64),
        torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
    )
    torch.testing.assert_close(
        rotvec_to_matrix(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64)), rotz(a)
    )


def test_quaternion_and_euler_consistency() -> None:
    g = torch.Generator().manual_seed(2)
    R = random_rotation_about_random_axis(g, 20, max_angle_deg=170.0)
    torch.testing.assert_close(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-12, rtol=0)
    torch.testing.assert_close(rotvec_to_matrix(matrix_to_rotvec(R)), R, atol=1e-12, rtol=0)
    ang = torch.tensor([[10.0, 20.0, 30.0]], dtype=torch.float64)
    Rz = euler_to_matrix("ZYX", ang)[0]
    manual = rotz(torch.deg2rad(ang[0, 0])) @ roty(torch.deg2rad(ang[0, 1])) @ rotx(torch.deg2rad(ang[0, 2]))
    torch.testing.assert_close(Rz, manual, atol=1e-12, rtol=0)


def test_random_axis_rotation_angles_within_bound() -> None:
    g = torch.Generator().manual_seed(3)
    R = random_rotation_about_random_axis(g, 500, max_angle_deg=30.0)
    ang = angle_between_rotations_deg(R, torch.eye(3, dtype=torch.float64).expand_as(R))
    assert float(ang.max()) <= 30.0 + 1e-9
    assert float(ang.max()) > 25.0  # the range is actually used


def test_rotation_about_point_fixes_the_point() -> None:
    c = torch.tensor([10.0, -5.0, 3.0], dtype=torch.float64)
    R = rotvec_to_matrix(torch.tensor([0.2, 0.5, -0.1], dtype=torch.float64))
    T = rotation_about_point(R, c)
    torch.testing.assert_close(apply_transform(T, c[None])[0], c)
    torch.testing.assert_close(make_transform(R, torch.zeros(3, dtype=torch.float64))[:3, :3], R)
