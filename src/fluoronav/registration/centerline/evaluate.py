"""Synthetic scenes for the centreline initialisation and its accuracy on them.

The scenes follow the paper's CM simulation protocol (Gao et al., IEEE TBME 69(1), 2022, sec. III-B)
but are made from the CM model itself (projected landmarks and centreline plus noise), not from
physics-simulated images.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fluoronav.detection.centerline import resample_polyline
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.carm import carm_camera
from fluoronav.manipulator import CMConfig, CMKinematics
from fluoronav.registration.centerline.geometry import roll_about_axis_deg
from fluoronav.registration.centerline.single import (
    CenterlineInitConfig,
    centerline_initialize,
    depth_range_about,
)

__all__ = [
    "LANDMARK_BLEND_FRACTION",
    "CenterlineScene",
    "evaluate_centerline_init",
    "synthetic_centerline_scene",
]

#: a synthetic centreline is bent over this fraction of its arc length at each end to start and end
#: at the noisy landmarks (as a path traced between detected landmarks does)
LANDMARK_BLEND_FRACTION = 0.1


@dataclass(frozen=True)
class CenterlineScene:
    """A synthetic initialisation problem (ground truth and the noisy observations)."""

    camera: Camera
    camera_from_cm: np.ndarray  # (4, 4) ground truth
    control_points_deg: np.ndarray  # (5,) ground truth
    fbg_control_points_deg: np.ndarray  # (5,) with FBG noise
    landmarks_px: np.ndarray  # (2, 2) with detection noise
    centerline_px: np.ndarray  # (P, 2)


def synthetic_centerline_scene(
    rng: np.random.Generator,
    *,
    config: CMConfig | None = None,
    source_to_isocenter_mm: tuple[float, float] = (400.0, 500.0),
    translation_mm: float = 30.0,
    rotation_deg: float = 30.0,
    roll_deg: float | None = None,
    fbg_noise_deg: float = 0.5,
    landmark_noise_px: float = 3.0,
    n_centerline_points: int = 100,
) -> CenterlineScene:
    """A random AP-view scene made from the model: projected landmarks and centreline plus noise.

    Follows the paper's CM simulation protocol (sec. III-B): AP view (CIOS Fusion) with the isocentre
    U(``source_to_isocenter_mm``) from the source; the CM nominally lies across the view (its axis in
    the image plane at a uniform in-plane angle, A at the isocentre; roll ``roll_deg``, uniform when
    None, 90° = bending plane parallel to the image plane), then is perturbed
    by a rotation of U(±``rotation_deg``) about a uniformly random axis in the CM base frame and a
    translation of U(±``translation_mm``) per axis; control points U(range of the config).
    Noise: U(±fbg_noise_deg) on the control points, U(±landmark_noise_px) per landmark coordinate;
    the centreline is the true projection from A to B, bent over the first and last
    :data:`LANDMARK_BLEND_FRACTION` of its arc length to start and end at the noisy landmarks.
    """
    cfg = config or CMConfig()
    kin = CMKinematics(cfg)
    sid = rng.uniform(*source_to_isocenter_mm)
    camera = carm_camera(source_to_isocenter_mm=sid)
    phi, roll = rng.uniform(0.0, 2.0 * math.pi, 2)
    if roll_deg is not None:
        roll = math.radians(roll_deg)
    z_axis = np.array([math.cos(phi), math.sin(phi), 0.0])
    x0 = np.array([-math.sin(phi), math.cos(phi), 0.0])
    x_axis = math.cos(roll) * x0 + math.sin(roll) * np.cross(z_axis, x0)
    nominal = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis], axis=1)  # camera_from_cm rotation
    axis = rng.normal(size=3)
    perturb = _axis_angle(axis / np.linalg.norm(axis), math.radians(rng.uniform(-rotation_deg, rotation_deg)))
    T = np.eye(4)
    T[:3, :3] = nominal @ perturb
    T[:3, 3] = np.array([0.0, 0.0, sid]) + rng.uniform(-translation_mm, translation_mm, 3)
    lo_cp, hi_cp = cfg.control_point_range_deg
    cp = rng.uniform(lo_cp, hi_cp, cfg.n_control_points)
    fbg = cp + rng.uniform(-fbg_noise_deg, fbg_noise_deg, cp.shape)
    cp_t = torch.as_tensor(cp, dtype=torch.float64)
    lm_cm = kin.landmarks_cm(cp_t).numpy()
    cl_cm = kin.centerline_cm(cp_t, n_points=4 * n_centerline_points).numpy()
    cam_pose = camera.with_pose(T)  # points in the CM frame projected with camera_from_cm
    lm_true = cam_pose.project(lm_cm)
    lm_noisy = lm_true + rng.uniform(-landmark_noise_px, landmark_noise_px, (2, 2))
    cl = cam_pose.project(cl_cm)
    s = np.linspace(0.0, 1.0, cl.shape[0])[:, None]
    f = LANDMARK_BLEND_FRACTION
    w_a, w_b = np.clip(1.0 - s / f, 0.0, 1.0), np.clip((s - (1.0 - f)) / f, 0.0, 1.0)
    cl = cl + w_a * (lm_noisy[0] - lm_true[0]) + w_b * (lm_noisy[1] - lm_true[1])
    return CenterlineScene(
        camera=camera,
        camera_from_cm=T,
        control_points_deg=cp,
        fbg_control_points_deg=fbg,
        landmarks_px=lm_noisy,
        centerline_px=resample_polyline(cl, n_centerline_points),
    )


def _axis_angle(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    Kx = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle_rad) * Kx + (1.0 - math.cos(angle_rad)) * Kx @ Kx


def evaluate_centerline_init(
    n: int = 20,
    seed: int = 0,
    *,
    fbg_noise_deg: float = 0.5,
    landmark_noise_px: float = 3.0,
    config: CenterlineInitConfig | None = None,
    scene_options: dict[str, Any] | None = None,
    depth_window_mm: float | None = None,
) -> dict[str, float]:
    """Run the initialiser on ``n`` random synthetic scenes and summarise its errors.

    ``scene_options`` go to :func:`synthetic_centerline_scene`, ``config`` to
    :func:`~fluoronav.registration.centerline.single.centerline_initialize`. ``depth_window_mm``:
    search the depth within this distance of the isocentre (the scenes' nominal CM position, as the
    femoral head in the studies).

    Returns:
        mean/std of the depth error (mm, |z_A est − z_A true|) and of the θ error (degrees, roll about
        the true chord, in [0, 180]), mean final cost (px) and mean run time per initialisation (s).
    """
    rng = np.random.default_rng(seed)
    kin = CMKinematics()
    depth_err, theta_err, costs, times = [], [], [], []
    for _ in range(n):
        sc = synthetic_centerline_scene(
            rng, fbg_noise_deg=fbg_noise_deg, landmark_noise_px=landmark_noise_px, **(scene_options or {})
        )
        t0 = time.perf_counter()
        depth_range = (
            None
            if depth_window_mm is None
            else depth_range_about(sc.camera, np.zeros(3), window_mm=depth_window_mm)
        )
        res = centerline_initialize(
            sc.camera, sc.landmarks_px, sc.centerline_px, sc.fbg_control_points_deg,
            config=config, depth_range_mm=depth_range, seed=int(rng.integers(2**31)),
        )  # fmt: skip
        times.append(time.perf_counter() - t0)
        chord = kin.landmarks_cm(torch.as_tensor(sc.control_points_deg)).numpy()
        a_true = sc.camera_from_cm[:3, :3] @ chord[0] + sc.camera_from_cm[:3, 3]
        depth_err.append(abs(res.depth_mm - a_true[2]))
        theta_err.append(
            float(roll_about_axis_deg(res.camera_from_cm, sc.camera_from_cm, chord[1] - chord[0]))
        )
        costs.append(res.cost_px)
    return {
        "depth_error_mm_mean": float(np.mean(depth_err)),
        "depth_error_mm_std": float(np.std(depth_err)),
        "theta_error_deg_mean": float(np.mean(theta_err)),
        "theta_error_deg_std": float(np.std(theta_err)),
        "cost_px_mean": float(np.mean(costs)),
        "seconds_per_init": float(np.mean(times)),
    }
