"""Parameterisations: reference poses, fixed centres, multi-CM and hand-eye composition."""

from __future__ import annotations

import numpy as np
import torch

from fluoronav.geometry.transforms import apply_transform, invert_transform, transform_from_params
from fluoronav.registration.parameterization import (
    CMPoseShape,
    HandEye,
    MultiCMReference,
    RigidAboutPoint,
    RotationAboutPoint,
    delta_transform,
    reference_frame,
)

D = torch.float64


def random_pose(rng: np.random.Generator, t_scale: float = 100.0) -> torch.Tensor:
    p = np.concatenate([rng.uniform(-1, 1, 3), rng.uniform(-t_scale, t_scale, 3)])
    return transform_from_params(torch.tensor(p, dtype=D))


def test_delta_transform_degrees() -> None:
    T = delta_transform(torch.tensor([0.0, 0.0, 90.0, 1.0, 2.0, 3.0], dtype=D))
    torch.testing.assert_close(T[:3, :3], torch.tensor([[0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=D))
    torch.testing.assert_close(T[:3, 3], torch.tensor([1.0, 2.0, 3.0], dtype=D))


def test_cm_pose_shape_zero_and_frame() -> None:
    rng = np.random.default_rng(0)
    T0 = random_pose(rng)
    cp0 = np.array([1.0, -2.0, 3.0, 0.5, 0.0])
    par = CMPoseShape(T0, cp0)
    assert par.dim == 11 and len(par.names) == 11
    x0 = par.initial()
    st = par(np.stack([x0, x0]))
    torch.testing.assert_close(st.camera_from_cm, T0.expand(2, 4, 4), rtol=0, atol=1e-12)
    torch.testing.assert_close(st.control_points_deg[0], torch.tensor(cp0, dtype=D))
    # a pure rotation keeps the CM base origin A fixed; a translation moves it along CM axes
    x = x0.copy()
    x[:3] = [10.0, -20.0, 5.0]
    T = par(x).camera_from_cm[0]
    torch.testing.assert_close(T[:3, 3], T0[:3, 3], rtol=0, atol=1e-12)
    x = x0.copy()
    x[3:6] = [0.0, 0.0, 7.0]
    T = par(x).camera_from_cm[0]
    torch.testing.assert_close(T[:3, 3] - T0[:3, 3], 7.0 * T0[:3, 2], rtol=0, atol=1e-12)


def test_rigid_about_point_keeps_centre_fixed() -> None:
    rng = np.random.default_rng(1)
    T0 = random_pose(rng)
    c = torch.tensor([12.0, -40.0, 85.0], dtype=D)
    params = torch.tensor(np.concatenate([rng.uniform(-30, 30, (5, 3)), np.zeros((5, 3))], axis=1))
    for axes in ("camera", "object"):
        par = RigidAboutPoint(T0, c, axes=axes)
        torch.testing.assert_close(par(np.zeros(6)).camera_from_object[0], T0, rtol=0, atol=1e-12)
        T = par(params).camera_from_object
        c_cam = apply_transform(T, c.expand(5, 1, 3))[:, 0]
        torch.testing.assert_close(c_cam, apply_transform(T0, c[None])[0].expand(5, 3), rtol=0, atol=1e-9)
        # other points move
        assert float((apply_transform(T, torch.zeros(5, 1, 3, dtype=D)) - T0[:3, 3]).norm(dim=-1).min()) > 1.0
    # camera axes: the translation is along camera axes
    par = RigidAboutPoint(T0, c, axes="camera")
    T = par(np.array([0, 0, 0, 1.0, 2.0, 3.0])).camera_from_object[0]
    torch.testing.assert_close(T[:3, 3] - T0[:3, 3], torch.tensor([1.0, 2.0, 3.0], dtype=D))
    # object axes: the rotation vector is expressed in the object frame
    par_o = RigidAboutPoint(T0, c, axes="object")
    To = par_o(np.array([0, 0, 30.0, 0, 0, 0])).camera_from_object[0]
    R_rel = T0[:3, :3].T @ To[:3, :3]  # object_from_object'
    torch.testing.assert_close(R_rel, delta_transform(torch.tensor([0, 0, 30.0, 0, 0, 0], dtype=D))[:3, :3])


def test_rotation_about_point_femur() -> None:
    rng = np.random.default_rng(2)
    T0 = random_pose(rng)
    head = torch.tensor([-80.0, 10.0, 30.0], dtype=D)
    par = RotationAboutPoint(T0, head)
    assert par.dim == 3
    T = par(rng.uniform(-15, 15, (4, 3))).camera_from_object
    torch.testing.assert_close(
        apply_transform(T, head.expand(4, 1, 3))[:, 0],
        apply_transform(T0, head[None]).expand(4, 3),
        rtol=0,
        atol=1e-9,
    )
    ang = torch.rad2deg(
        torch.arccos(((T0[:3, :3].T @ T[:, :3, :3]).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2)
    )
    assert float(ang.min()) > 1.0


def test_multi_cm_reproduces_given_poses() -> None:
    rng = np.random.default_rng(3)
    base_from_cm = torch.stack([random_pose(rng, 10.0) for _ in range(4)])
    camera_from_base = random_pose(rng)
    base_from_ref, _ = reference_frame(base_from_cm)
    torch.testing.assert_close(base_from_ref[:3, :3], torch.eye(3, dtype=D))
    torch.testing.assert_close(base_from_ref[:3, 3], base_from_cm[:, :3, 3].mean(0))
    par = MultiCMReference.from_base_poses(camera_from_base, base_from_cm, np.full(5, 2.0))
    assert par.n_poses == 4
    st = par(np.stack([par.initial()] * 3))
    assert st.camera_from_cm.shape == (3, 4, 4, 4)
    torch.testing.assert_close(st.camera_from_cm[1], camera_from_base @ base_from_cm, rtol=0, atol=1e-10)
    # a reference perturbation moves all poses rigidly together: relative poses unchanged
    x = par.initial()
    x[:6] = [5, -3, 8, 4, -2, 6]
    Tm = par(x).camera_from_cm[0]
    rel = invert_transform(Tm[0])[None] @ Tm
    torch.testing.assert_close(
        rel, invert_transform(base_from_cm[0])[None] @ base_from_cm, rtol=0, atol=1e-10
    )


def test_hand_eye_composition() -> None:
    rng = np.random.default_rng(4)
    base_from_ee = torch.stack([random_pose(rng, 50.0) for _ in range(5)])
    ee_from_cm = random_pose(rng, 30.0)
    camera_from_base = random_pose(rng)
    par = HandEye(camera_from_base, base_from_ee, ee_from_cm, np.zeros(5))
    assert par.dim == 17 and par.n_poses == 5
    st = par(par.initial())
    torch.testing.assert_close(
        st.camera_from_cm[0], camera_from_base @ base_from_ee @ ee_from_cm, rtol=0, atol=1e-10
    )
    # changing the hand-eye block changes the hand-eye matrix by a CM-frame perturbation, not the ref pose
    x = par.initial()
    x[6:12] = [3, 0, -2, 1.0, 0.5, -4.0]
    st = par(x)
    torch.testing.assert_close(
        st.ee_from_cm[0], ee_from_cm @ delta_transform(torch.tensor(x[6:12])), rtol=0, atol=1e-12
    )
    torch.testing.assert_close(st.camera_from_ref[0], par.camera_from_ref0, rtol=0, atol=1e-12)
    torch.testing.assert_close(
        st.camera_from_cm[0], camera_from_base @ base_from_ee @ st.ee_from_cm[0], rtol=0, atol=1e-10
    )
