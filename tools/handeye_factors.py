"""One image-based hand-eye calibration with its error sources switched on or off, to tell them apart.

A hand-eye scenario of ``fluoronav study hand-eye`` (phantom, physics images, oracle landmarks
±3 px) is calibrated with ``calibrate_hand_eye_from_images``, and the options remove one error
source at a time: the robot's kinematic errors (``--fk true``: the calibration sees the true FK), the
FBG reading's error (``--exact-shape``), the shape's freedom (``--shape fixed`` holds it at the
initial values; ``--shape-sigma`` sets the prior's walls), the start (``--start truth``), and adds
C-arm positions (``--views K``: each pose also seen from cameras orbited by ±``--orbit`` degrees,
known to the calibration). Prints one JSON line: rotation (tilt of the CM axis, roll about it) and
translation errors of ``ee_from_cm``, the eq. 10 tip error, the fitted shape's error and the levels.

Run (the docs/validation.md tables, ~5 min each on 2 cores)::

    python tools/handeye_factors.py --seed 71 --poses 15                       # the shipped default
    python tools/handeye_factors.py --seed 71 --poses 15 --shape-sigma 1 --tolerance 0   # old prior
    python tools/handeye_factors.py --seed 71 --poses 15 --shape fixed --exact-shape --fk true
    python tools/handeye_factors.py --seed 71 --poses 15 --bend-deg 2.5        # the study's bent CM
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import numpy as np
import torch

from fluoronav.calibration import image_handeye as ih
from fluoronav.calibration.handeye import transform_error
from fluoronav.geometry.carm import orbit_camera
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.registration.cm import CMView
from fluoronav.simulation.articulated import anatomy_and_simulator
from fluoronav.simulation.robot_scene import (
    perturb_transform,
    sample_handeye_scenario,
    simulate_scenario_images,
)
from fluoronav.studies import handeye_trials as ht


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=71)
    ap.add_argument("--poses", type=int, default=15)
    ap.add_argument("--image-size", type=int, default=768)
    ap.add_argument("--spread-deg", type=float, default=25.0)
    ap.add_argument("--fk", choices=("reported", "true"), default="reported")
    ap.add_argument("--start", choices=("perturbed", "truth"), default="perturbed")
    ap.add_argument("--exact-shape", action="store_true", help="initial shape = truth (no FBG error)")
    ap.add_argument("--shape", choices=("free", "fixed"), default="free")
    ap.add_argument("--shape-sigma", type=float, default=0.25, help="prior walls σ, deg")
    ap.add_argument("--tolerance", type=float, default=1.0, help="prior flat bottom ±, deg")
    ap.add_argument("--bend-deg", type=float, default=None, help="calibration C-bend (the study's)")
    ap.add_argument("--views", type=int, default=1)
    ap.add_argument("--orbit", type=float, default=30.0)
    args = ap.parse_args()

    torch.set_num_threads(2)
    size = args.image_size
    volume, sim = anatomy_and_simulator("phantom", 0, size, "cpu")
    rng = np.random.default_rng(args.seed)
    sc = sample_handeye_scenario(
        volume, rng, n_poses=args.poses, rotation_spread_deg=args.spread_deg, bend_deg=args.bend_deg
    )
    kin = CMKinematics()
    ab = kin.landmarks_cm(torch.as_tensor(sc.control_points_deg, dtype=torch.float64)).numpy()
    noise = np.random.default_rng(args.seed + 1)
    cams = [sc.camera] + [
        orbit_camera(
            sc.camera,
            angle_deg=(1.0 if k % 2 else -1.0) * args.orbit * ((k + 1) // 2),
            isocenter_world=sc.world_from_cm[0][:3, 3],
        )
        for k in range(1, args.views)
    ]
    oracle = ht.HandEyeStudyConfig(workflow="hand-eye", trials=1, seed=args.seed, oracle_landmarks=True)
    views = []
    for k, cam in enumerate(cams):
        images = simulate_scenario_images(sc, sim, seed=5 + 50 * k, image_size=size, camera=cam)
        true_full_px = np.stack([cam.project(ab @ T[:3, :3].T + T[:3, 3]) for T in sc.world_from_cm])
        lms, _ = ht._landmarks(images, true_full_px, noise, oracle)  # the study's truth ± 3 px
        views += [
            CMView(s.image, s.camera, landmarks_px=lm, name=f"v{k}p{i}")
            for i, (s, lm) in enumerate(zip(images, lms, strict=True))
        ]
    A1 = sc.rbase_from_ee_reported if args.fk == "reported" else sc.true_robot.rbase_from_ee(sc.q_actual_deg)
    A = np.concatenate([A1] * args.views)
    X0 = sc.ee_from_cm if args.start == "truth" else perturb_transform(sc.ee_from_cm, noise, 10.0, 10.0)
    cp_fbg = sc.control_points_deg + (0.0 if args.exact_shape else noise.uniform(-0.5, 0.5, 5))
    W0 = (
        sc.world_from_rbase
        if args.start == "truth"
        else ih.initial_world_from_rbase_pnp(views[: args.poses], A1, X0, cp_fbg)
    )
    levels = ih.default_handeye_levels()
    if args.shape == "fixed":
        levels = tuple(replace(lv, sigma=tuple(lv.sigma[:12]) + (ih._HELD,) * 5) for lv in levels)
    cfg = ih.ImageHandEyeConfig(
        levels=levels, control_point_sigma_deg=args.shape_sigma, control_point_tolerance_deg=args.tolerance
    )
    t0 = time.perf_counter()
    res = ih.calibrate_hand_eye_from_images(
        views,
        A,
        initial_ee_from_cm=X0,
        initial_control_points_deg=cp_fbg,
        initial_world_from_rbase=W0,
        config=cfg,
        seed=3,
    )
    if not res.ok:
        raise SystemExit(f"calibration failed: {res.reason}")
    assert isinstance(res, ih.ImageHandEyeResult)
    rot, trans = transform_error(res.ee_from_cm, sc.ee_from_cm)
    tip_true = ht.tip_rbase(
        sc.true_robot.rbase_from_ee(sc.q_actual_deg), sc.ee_from_cm, sc.control_points_deg, kin
    )
    tip10 = ht.tip_rbase(sc.rbase_from_ee_reported, res.ee_from_cm, res.control_points_deg, kin)
    out = {
        "args": vars(args),
        "rotation_deg": rot,
        **ht.axis_and_roll_deg(res.ee_from_cm, sc.ee_from_cm),
        "translation_mm": trans,
        "tip_mm": float(np.linalg.norm(tip10 - tip_true, axis=1).mean()),
        "shape_error_deg": np.round(res.control_points_deg - sc.control_points_deg, 3).tolist(),
        "cost": res.cost,
        "reason": res.reason,
        "seconds": time.perf_counter() - t0,
        "levels": [(lv.name, lv.n_iters, round(lv.cost, 4)) for lv in res.trace.levels],
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
