"""The whole navigation pipeline on the built-in phantom, in simulation (``fluoronav demo``).

Stages (each timed; every estimate is compared with the simulated truth at the end):

1. ``anatomy``: the seeded hip phantom (CT in HU, labels, landmarks) and the physics simulator.
2. ``scene``: a UR-10 with joint and calibration errors holding the CM above the left femoral head
   (the navigation protocol of :mod:`fluoronav.studies.handeye_study`), the pelvis and femur moved as
   the paper's protocol, and three C-arm views: AP and two orbits about the patient's long axis.
3. ``simulate``: physics X-rays of the three views (polychromatic, Poisson noise, scatter; the CM
   voxelised at 0.1 mm; never the registration's renderer).
4. ``detect``: the shipped detector: CM mask, landmarks A and B, centreline, per view.
5. ``pelvis``: the pelvis registered to each view; the views' relative geometry follows (§II-C).
6. ``femur``: the femur registered to all views (rotation about the femoral head).
7. ``cm``: the landmarks triangulated from the views and a scan of the roll about them scored by
   the centrelines of all views (multi-view centreline initialisation), then multi-view CM
   registration (pose + shape) in the CT frame from the best one or two roll minima.
8. ``plan``: the CM tip on the femur's entry point, its axis along the neck towards the head.
9. ``robot``: eqs. 7–8 and inverse kinematics with the nominal robot model and a hand-eye matrix
   of documented error (``handeye_error_deg`` / ``_mm``).
10. ``move``: the true robot (with its errors) moves; the true tip's distance to the plan is the
    repositioning error.
11. ``verify``: the C-arm slid to centre the femoral head and the planned CM, new images at the
    reached pose, detection, the pelvis (per view), the femur and the CM registered anew (the CM
    from the plan); the distance of the registered tip from the plan is what the surgeon would be
    shown.
12. ``correct``: one corrective command from that registration (eqs. 7–8 again, from the reached
    joints) and its move: the closed loop that a single open-loop move lacks. A rotation error of the
    first registration is multiplied by the length of the first move; the correction is short.

Frames: ``world`` is the simulation's world (the CT frame before the patient moved); ``ct`` is the
CT frame, in which the registration works after the pelvis registration; errors of CM and femur are
measured in the C-arm frame of the AP view, repositioning in the world frame.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fluoronav.errors import FluoronavError

log = logging.getLogger(__name__)

__all__ = ["STAGES", "DemoConfig", "DemoResult", "run_demo"]

STAGES = (
    "anatomy",
    "scene",
    "simulate",
    "detect",
    "pelvis",
    "femur",
    "cm",
    "plan",
    "robot",
    "move",
    "verify",
    "correct",
)


@dataclass(frozen=True)
class DemoConfig:
    """Settings of the demo (recorded in ``results.json``).

    Attributes:
        seed: everything random derives from it (phantom, scene, noise, optimisers).
        image_size: simulated image rows = cols (the 1536² CIOS Fusion detector binned).
        orbit_deg: C-arm orbit angles of the extra views about the patient's long axis through the CM.
        handeye_error_deg, handeye_error_mm: the hand-eye matrix the robot uses is the truth moved by
            exactly these (the measured accuracy of the image-based calibration).
        device: torch device of the detector, renderers and similarities.
        oracle_landmarks: use the true landmarks + U(−3, 3) full-detector px instead of the detector.
    """

    seed: int = 0
    image_size: int = 768
    orbit_deg: tuple[float, ...] = (20.0, -15.0)
    handeye_error_deg: float = 0.4
    handeye_error_mm: float = 0.5
    device: str = "cpu"
    oracle_landmarks: bool = False


@dataclass
class DemoResult:
    """What the demo measured and the pictures' raw material.

    ``errors`` and ``timings_s`` are flat dicts of floats; ``details`` holds poses and per-view
    numbers (JSON-ready); ``artifacts`` holds arrays and traces for the report (not serialised).
    """

    config: DemoConfig
    errors: dict[str, float] = dataclasses.field(default_factory=dict)
    timings_s: dict[str, float] = dataclasses.field(default_factory=dict)
    details: dict[str, Any] = dataclasses.field(default_factory=dict)
    status: str = "ok"
    reason: str = ""
    artifacts: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        from fluoronav import __version__

        return {
            "version": __version__,
            "status": self.status,
            "reason": self.reason,
            "config": dataclasses.asdict(self.config),
            "errors": self.errors,
            "timings_s": self.timings_s,
            "details": self.details,
        }


class _Stages:
    """Times stages and reports them to a callback (the CLI's progress display)."""

    def __init__(self, result: DemoResult, on_stage: Callable[[str, str], None] | None) -> None:
        self.result = result
        self.on_stage = on_stage

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        if self.on_stage is not None:
            self.on_stage(name, "start")
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.result.timings_s[name] = time.perf_counter() - t0
            if self.on_stage is not None:
                self.on_stage(name, "done")


def _rotation_deg(R: np.ndarray) -> float:
    c = (np.trace(R[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def _h(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to (..., 3) points."""
    p = np.asarray(p, dtype=np.float64)
    return p @ T[:3, :3].T + T[:3, 3]


def _landmarks(
    images: list[Any], cfg: DemoConfig, rng: np.random.Generator, names: list[str] | None = None
) -> list[dict[str, Any] | None]:
    """Per view: landmarks (2, 2), centreline (P, 2), mask, confidence (detector or oracle); None
    where the detector found no CM or one cut by the image border."""
    from fluoronav.detection.centerline import extract_centerline

    out: list[dict[str, Any] | None] = []
    for i, sim in enumerate(images):
        binning = max(1, round(1536 / sim.camera.cols))
        if cfg.oracle_landmarks:
            lm = sim.landmarks_px + rng.uniform(-3.0, 3.0, (2, 2)) / binning
            mask = sim.mask.astype(bool)
            out.append(
                {
                    "landmarks_px": lm,
                    "centerline_px": extract_centerline(mask, lm[0], lm[1]),
                    "mask": mask,
                    "confidence": np.ones(2),
                }
            )
            continue
        from fluoronav.studies.pipeline import _detector

        det = _detector(cfg.device).detect(sim.image, pixel_spacing_mm=sim.camera.pixel_spacing_mm)
        if not det.usable or det.centerline_px is None:
            # a CM cut by the image border has a landmark at the cut: the registration then starts
            # from its initial pose in this view, as with no detection
            why = det.unusable_reason or "no centreline"
            log.warning("detector: %s in the %s image; not used", why, names[i] if names else f"#{i}")
            out.append(None)
            continue
        out.append(
            {
                "landmarks_px": det.landmarks_px,
                "centerline_px": det.centerline_px,
                "mask": det.mask,
                "confidence": det.landmark_confidence,
            }
        )
    return out


def run_demo(
    config: DemoConfig | None = None, *, on_stage: Callable[[str, str], None] | None = None
) -> DemoResult:
    """Run the simulated navigation pipeline (module docstring) and measure it against the truth.

    Args:
        config: settings (default :class:`DemoConfig`).
        on_stage: called with (stage name, "start" | "done") for progress displays.

    Returns:
        :class:`DemoResult`; a stage that fails sets ``status = "failed"`` and ``reason`` and the
        stages before it keep their results.
    """
    cfg = config or DemoConfig()
    res = DemoResult(config=cfg)
    try:
        _run(cfg, res, _Stages(res, on_stage))
    except (FluoronavError, ValueError, RuntimeError) as exc:
        log.exception("demo stage failed")
        res.status, res.reason = "failed", f"{exc.__class__.__name__}: {exc}"
    return res


def _run(cfg: DemoConfig, res: DemoResult, stage: _Stages) -> None:
    from fluoronav.calibration.robot import wrap_deg
    from fluoronav.detection.instrument import instrument_masks
    from fluoronav.geometry import orbit_camera
    from fluoronav.manipulator.kinematics import CMKinematics
    from fluoronav.navigation.navigate import femur_from_cm_registered, tip_correction_target
    from fluoronav.navigation.planning import neck_entry_plan, planned_femur_from_cm
    from fluoronav.registration.bone import (
        register_femur,
        register_pelvis_per_view,
        views_from_images,
        views_in_ct_frame,
    )
    from fluoronav.registration.centerline_init import centerline_initialize_multiview
    from fluoronav.registration.cm import CMRegistrationConfig, CMView, register_cm, register_cm_multistart
    from fluoronav.studies.handeye_study import (
        _perturb,
        centre_on,
        sample_handeye_scenario,
        verification_view_centre,
        working_view_centre,
    )
    from fluoronav.studies.metrics import axis_error_deg, cm_errors
    from fluoronav.studies.pipeline import _anatomy, multiview_start_poses

    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    E, D, A = res.errors, res.details, res.artifacts
    seeds = rng.integers(2**31, size=16)

    with stage("anatomy"):
        volume, simulator = _anatomy("phantom", cfg.seed, cfg.image_size, cfg.device)
    A["volume"] = volume

    with stage("scene"):
        sc = sample_handeye_scenario(volume, np.random.default_rng(seeds[0]), n_poses=0)
        tr = sc.trial
        kin = CMKinematics(sc.cm_config)
        cp_true = sc.control_points_deg
        cpt = torch.as_tensor(cp_true, dtype=torch.float64)
        pts_cm = np.concatenate([kin.landmarks_cm(cpt).numpy(), kin.tip_cm(cpt).numpy()[None]])
        q_regi = sc.q_work_deg
        q_regi_actual = sc.error_model.actual_joints_deg(q_regi, rng=rng)
        W_regi = sc.true_world_from_cm(q_regi_actual)
        # the CM, the neck and the acetabulum in view (the field of view is ~130 mm at the
        # isocentre); the CM at the plan is imaged from a C-arm slid towards it (stage verify)
        iso = working_view_centre(tr)
        ap = centre_on(sc.camera, iso)
        cams_full = [ap] + [orbit_camera(ap, angle_deg=a, isocenter_world=iso) for a in cfg.orbit_deg]
        names = ["AP"] + [f"orbit {a:+g}°" for a in cfg.orbit_deg]
    D["views"] = names
    D["true"] = {
        "world_from_cm": W_regi.tolist(),
        "control_points_deg": cp_true.tolist(),
        "world_from_femur": tr.world_from_femur.tolist(),
        "world_from_patient": tr.world_from_patient.tolist(),
        "ee_from_cm": sc.ee_from_cm.tolist(),
        "world_from_rbase": sc.world_from_rbase.tolist(),
        "q_registration_deg": q_regi.tolist(),
    }
    A.update(scene=sc, cams_full=cams_full, names=names, W_regi=W_regi, kin=kin, q_regi_actual=q_regi_actual)

    def simulate_views(world_from_cm: np.ndarray, seed: int, cams: list[Any]) -> list[Any]:
        """Physics X-rays of ``cams``' views with the CM at ``world_from_cm`` (noise seed + view)."""
        return [
            simulator.simulate(
                cam,
                world_from_patient=tr.world_from_patient,
                world_from_femur=tr.world_from_femur,
                cm=(world_from_cm, cp_true),
                seed=seed + k,
                image_size=cfg.image_size,
                cm_config=sc.cm_config,
            )
            for k, cam in enumerate(cams)
        ]

    with stage("simulate"):
        images = simulate_views(W_regi, int(seeds[1]), cams_full)
    A["images"] = images

    with stage("detect"):
        found = _landmarks(images, cfg, rng, names)
    A["detections"] = found
    seen = [k for k, f in enumerate(found) if f is not None]
    D["views_detected"] = len(seen)
    if len(seen) < 2:
        raise FluoronavError(f"the CM was detected in {len(seen)} of {len(found)} views; two are needed")
    det_err = [
        np.linalg.norm(found[k]["landmarks_px"] - images[k].landmarks_px, axis=1)  # type: ignore[index]
        for k in seen
    ]
    ps = images[0].camera.pixel_spacing_mm or float("nan")
    E["landmark_px"] = float(np.mean(det_err))
    E["landmark_mm_at_detector"] = float(np.mean(det_err) * ps)
    D["landmarks_px"] = [None if f is None else f["landmarks_px"].tolist() for f in found]

    # ----- bones: pelvis per view → view geometry in the CT frame; femur in all views -------------
    # the CM and its shaft are left out of the bone similarity
    def bone_views(images: list[Any], found: list[dict[str, Any] | None]) -> list[Any]:
        return views_from_images(
            images,
            instrument_masks(
                [None if f is None else f["mask"] for f in found],
                [None if f is None else f["centerline_px"] for f in found],
                [im.image for im in images],
            ),
        )

    views = bone_views(images, found)
    with stage("pelvis"):
        pelvis = register_pelvis_per_view(
            views, volume, initial_world_from_patient=tr.initial_world_from_patient, seed=int(seeds[2])
        )
    views_ct = views_in_ct_frame(views, pelvis)
    cams_ct = [v.camera for v in views_ct]
    A["pelvis"] = pelvis
    A["cams_ct"] = cams_ct
    # pelvis error: the estimated camera_from_ct against the truth camera_from_world @ world_from_patient
    pel_rot, pel_tr = [], []
    for cam_est, s in zip(cams_ct, images, strict=True):
        true = s.camera.camera_from_world @ tr.world_from_patient
        delta = np.linalg.inv(true) @ cam_est.camera_from_world
        pel_rot.append(_rotation_deg(delta))
        pel_tr.append(float(np.linalg.norm(_h(delta, tr.pelvis_center_ct) - tr.pelvis_center_ct)))
    E["pelvis_rotation_deg"] = float(np.mean(pel_rot))
    E["pelvis_center_mm"] = float(np.mean(pel_tr))

    with stage("femur"):
        femur = register_femur(
            views_ct,
            volume,
            side=tr.side,
            world_from_patient=np.eye(4),
            seed=int(seeds[3]),
        )
    ct_from_femur = femur.world_from_bone
    A["femur"] = femur
    carm = images[0].camera.camera_from_world  # the true AP C-arm frame
    carm_est_from_ct = cams_ct[0].camera_from_world  # the same frame, as estimated
    entry_est_c = _h(carm_est_from_ct @ ct_from_femur, tr.entry_ct)
    entry_true_c = _h(carm @ tr.world_from_femur, tr.entry_ct)
    E["femur_entry_mm"] = float(np.linalg.norm(entry_est_c - entry_true_c))
    E["femur_rotation_deg"] = _rotation_deg(
        np.linalg.inv(carm @ tr.world_from_femur) @ (carm_est_from_ct @ ct_from_femur)
    )

    # ----- CM: triangulated depth + centreline init, multi-start multi-view registration ---------
    with stage("cm"):
        cp0 = tr.initial_control_points_deg  # FBG reading
        init = centerline_initialize_multiview(
            [cams_ct[k] for k in seen],
            np.stack([found[k]["landmarks_px"] for k in seen]),  # type: ignore[index]
            [found[k]["centerline_px"] for k in seen],  # type: ignore[index]
            cp0,
            config=sc.cm_config,
            landmark_confidence=np.stack([found[k]["confidence"] for k in seen]),  # type: ignore[index]
        )
        # landmarks that disagreed with the other views are replaced by the triangulated consensus
        lm_views: list[np.ndarray | None] = [None if f is None else f["landmarks_px"] for f in found]
        for i, k in enumerate(seen):
            lm_views[k] = init.landmarks_px[i]
        cm_views = [  # a view without a detection still counts (ROI at the initial pose)
            CMView(s.image, c, landmarks_px=lm, name=n)
            for s, c, lm, n in zip(images, cams_ct, lm_views, names, strict=True)
        ]
        reg = register_cm_multistart(
            cm_views,
            multiview_start_poses(init),
            initial_control_points_deg=cp0,
            config=CMRegistrationConfig(device=cfg.device),
            seed=int(seeds[5]),
        )
    A["cm"] = reg
    A["cm_init"] = init
    ct_from_cm = reg.world_from_cm[0]
    errs = cm_errors(
        carm_from_cm_est=carm_est_from_ct @ ct_from_cm,
        carm_from_cm_true=carm @ W_regi,
        control_points_est_deg=reg.control_points_deg,
        control_points_true_deg=cp_true,
        config=sc.cm_config,
    )
    E.update({f"cm_{k}": float(v) for k, v in errs.items() if isinstance(v, (int, float))})
    E["cm_init_tip_mm"] = float(
        np.linalg.norm(_h(carm_est_from_ct @ init.world_from_cm, pts_cm[2]) - _h(carm @ W_regi, pts_cm[2]))
    )
    D["cm"] = reg.to_dict()

    # ----- plan, robot command, move -----------------------------------------------------------
    with stage("plan"):
        plan = neck_entry_plan(tr.entry_ct, tr.femoral_head_ct, reg.control_points_deg)
        femur_from_cm_target = planned_femur_from_cm(plan, kinematics=kin)
    D["plan"] = plan.to_dict()

    with stage("robot"):  # eqs. 7-8 + IK on the nominal model; the true robot (with its errors) moves
        ee_from_cm_used = _perturb(sc.ee_from_cm, rng, cfg.handeye_error_deg, cfg.handeye_error_mm)
        q_target, W_after = sc.move_to_plan(
            q_regi,
            ee_from_cm=ee_from_cm_used,
            carm_from_femur=carm_est_from_ct @ ct_from_femur,
            carm_from_cm=carm_est_from_ct @ ct_from_cm,
            femur_from_cm_target=femur_from_cm_target,
            rng=rng,
        )
    D["q_target_deg"] = q_target.tolist()
    E["joint_motion_deg"] = float(np.max(np.abs(wrap_deg(q_target - q_regi))))

    with stage("move"):
        tip_after = _h(W_after, pts_cm[2])
        planned_tip_true = _h(tr.world_from_femur, plan.tip_target_world_mm)
    E["reposition_tip_mm"] = float(np.linalg.norm(tip_after - planned_tip_true))
    W_plan_true = tr.world_from_femur @ femur_from_cm_target
    E["reposition_axis_deg"] = axis_error_deg(W_after[:3, 2], W_plan_true[:3, 2])
    A.update(W_after=W_after, W_plan_true=W_plan_true, ct_from_femur=ct_from_femur)
    D["true"]["world_from_cm_after"] = W_after.tolist()

    with stage("verify"):
        # the C-arm slid (no rotation) to centre the femoral head and the planned CM as the
        # registrations placed them, so that the CM where the robot took it, the neck and the
        # acetabulum are in view. The slide is not known to the software: pelvis (per view), femur
        # and CM are registered anew, the CM from the plan on the new femur. Several views: one
        # cannot tell the CM's depth, and a correction that acts on a single-view depth error can
        # make the tip worse.
        centre_femur = verification_view_centre(femur_from_cm_target, tr.femoral_head_ct)
        # where the person aims the C-arm (seen in the estimated C-arm frame), in the world
        centre2 = _h(np.linalg.inv(carm) @ carm_est_from_ct @ ct_from_femur, centre_femur)
        ap2 = centre_on(cams_full[0], centre2)
        cams2 = [ap2] + [orbit_camera(ap2, angle_deg=a, isocenter_world=centre2) for a in cfg.orbit_deg]
        images2 = simulate_views(W_after, int(seeds[6]), cams2)
        found2 = _landmarks(images2, cfg, rng, [f"verification ({n} after the move)" for n in names])
        D["verify_views_detected"] = sum(f is not None for f in found2)
        views2 = bone_views(images2, found2)
        pelvis2 = register_pelvis_per_view(
            views2, volume, initial_world_from_patient=tr.initial_world_from_patient, seed=int(seeds[8])
        )
        views2_ct = views_in_ct_frame(views2, pelvis2)
        cams2_ct = [v.camera for v in views2_ct]
        femur2 = register_femur(
            views2_ct, volume, side=tr.side, world_from_patient=np.eye(4), seed=int(seeds[9])
        )
        ct_from_femur2 = femur2.world_from_bone
        reg2 = register_cm(
            [
                CMView(
                    s.image, c, landmarks_px=None if f is None else f["landmarks_px"], name=f"{n} after move"
                )
                for s, c, f, n in zip(images2, cams2_ct, found2, names, strict=True)
            ],
            initial_control_points_deg=reg.control_points_deg,
            initial_world_from_cm=ct_from_femur2 @ femur_from_cm_target,
            config=CMRegistrationConfig(device=cfg.device),
            seed=int(seeds[7]),
        )
        img2, found2_ap = images2[0], found2[0]
    A.update(verify_image=img2, verify_detection=found2_ap, verify=reg2)
    carm2 = images2[0].camera.camera_from_world  # the true C-arm frame of the verification AP
    carm2_est_from_ct = cams2_ct[0].camera_from_world
    planned_tip_ct = _h(ct_from_femur2, plan.tip_target_world_mm)
    E["verify_tip_to_plan_mm"] = float(np.linalg.norm(reg2.tip_world[0] - planned_tip_ct))
    E["verify_tip_error_mm"] = float(
        np.linalg.norm(_h(carm2_est_from_ct, reg2.tip_world[0]) - _h(carm2, tip_after))
    )
    E["verify_femur_entry_mm"] = float(
        np.linalg.norm(
            _h(carm2_est_from_ct @ ct_from_femur2, tr.entry_ct) - _h(carm2 @ tr.world_from_femur, tr.entry_ct)
        )
    )
    D["verify"] = reg2.to_dict()

    # ----- one corrective move from the verification registration (closed loop) -----------------
    with stage("correct"):
        # slide the verified CM so that its registered tip meets the plan (tip_correction_target)
        target2 = tip_correction_target(
            femur_from_cm_registered(ct_from_femur2, reg2.world_from_cm[0]),
            kin.tip_cm(torch.as_tensor(reg2.control_points_deg, dtype=torch.float64)).numpy(),
            plan.tip_target_world_mm,
        )
        q_corr, W_final = sc.move_to_plan(
            q_target,
            ee_from_cm=ee_from_cm_used,
            carm_from_femur=carm2_est_from_ct @ ct_from_femur2,
            carm_from_cm=carm2_est_from_ct @ reg2.world_from_cm[0],
            femur_from_cm_target=target2,
            rng=rng,
        )
    D["q_corrected_deg"] = q_corr.tolist()
    D["true"]["world_from_cm_corrected"] = W_final.tolist()
    A["W_final"] = W_final
    E["corrected_tip_mm"] = float(np.linalg.norm(_h(W_final, pts_cm[2]) - planned_tip_true))
    E["corrected_axis_deg"] = axis_error_deg(W_final[:3, 2], W_plan_true[:3, 2])
    E["correction_joint_motion_deg"] = float(np.max(np.abs(wrap_deg(q_corr - q_target))))


def write_case(result: DemoResult, out: Path) -> Path | None:
    """``out/case/case.json`` + images + cameras: the demo's three views as a multi-view case file for
    ``fluoronav register`` (CT frame of the pelvis registration, detected landmarks, the multi-view
    initialisation, the ground truth). None when the run did not get that far."""
    A = result.artifacts
    if "cm_init" not in A or "cams_ct" not in A:
        return None
    case_dir = out / "case"
    case_dir.mkdir(parents=True, exist_ok=True)
    views = []
    for k, (sim, cam, det) in enumerate(zip(A["images"], A["cams_ct"], A["detections"], strict=True)):
        name = f"view{k}"
        np.savez_compressed(case_dir / f"{name}.npz", image=np.asarray(sim.image, np.float32))
        cam.save(case_dir / f"{name}_camera.json")
        views.append(
            {
                "name": name,
                "image": f"{name}.npz",
                "camera": f"{name}_camera.json",
            }
        )
        if det is not None:
            views[-1]["landmarks_px"] = np.asarray(det["landmarks_px"]).tolist()
            views[-1]["centerline_px"] = np.asarray(det["centerline_px"]).tolist()
    carm = A["images"][0].camera.camera_from_world
    ct_from_cm_true = A["cams_ct"][0].world_from_camera @ carm @ A["W_regi"]
    case = {
        "workflow": "multi-view",
        "views": views,
        "initial_control_points_deg": np.asarray(A["scene"].trial.initial_control_points_deg).tolist(),
        "initial_world_from_cm": np.asarray(A["cm_init"].world_from_cm).tolist(),
        "ground_truth": {
            "world_from_cm": ct_from_cm_true.tolist(),
            "control_points_deg": np.asarray(A["scene"].control_points_deg).tolist(),
        },
    }
    path = case_dir / "case.json"
    path.write_text(json.dumps(case, indent=1), encoding="utf-8")
    return path


def write_results(result: DemoResult, out: Path) -> Path:
    """``out/results.json`` (errors, timings, poses, config, version)."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / "results.json"
    path.write_text(json.dumps(result.to_json(), indent=2) + "\n", encoding="utf-8")
    return path
