"""``fluoronav calibrate CASE --out DIR``: image-based hand-eye calibration of a case file.

The case file (JSON, paths relative to its folder; docs/robot-and-calibration.md) holds ONE static
C-arm camera, M ≥ 3 views (an image each, its robot pose as ``rbase_from_ee`` or ``joints_deg``, or
a ``robot_poses`` log for all; optional landmarks, tracker poses of the shaft marker O_s and the
tip-segment marker O_t), the initial ``ee_from_cm`` and control points (the FBG reading), and
optionally the tip in O_t, the binning and a ground truth. Writes ``DIR/handeye.json``
(ee_from_cm, carm_from_rbase, control points, per-pose landmark residuals; the tracker baselines,
the eq. 9 vs eq. 10 tip comparison and errors against a ground truth where their inputs are given),
``DIR/trace.json`` and ``DIR/overlay_<view>.png``.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import typer

from fluoronav.cli.common import DEVICE_OPTION, SEED_OPTION
from fluoronav.errors import InputError, read_json_object

if TYPE_CHECKING:
    from fluoronav.manipulator.kinematics import CMKinematics

__all__ = ["CalibrationCase", "load_calibration_case", "run_calibration", "write_example_calibration_case"]

_ROBOTS = ("UR10",)


class CalibrationCase:
    """A parsed calibration case (see the module docstring)."""

    def __init__(
        self,
        *,
        views: list[Any],
        rbase_from_ee: np.ndarray,
        initial_ee_from_cm: np.ndarray,
        initial_control_points_deg: np.ndarray,
        tracker_from_marker: np.ndarray | None,
        tracker_from_tip_marker: np.ndarray | None,
        tip_in_tip_marker_mm: np.ndarray | None,
        ground_truth: dict[str, np.ndarray] | None,
        source: str,
    ) -> None:
        self.views = views
        self.rbase_from_ee = rbase_from_ee
        self.initial_ee_from_cm = initial_ee_from_cm
        self.initial_control_points_deg = initial_control_points_deg
        self.tracker_from_marker = tracker_from_marker
        self.tracker_from_tip_marker = tracker_from_tip_marker
        self.tip_in_tip_marker_mm = tip_in_tip_marker_mm
        self.ground_truth = ground_truth
        self.source = source


def _array(value: Any, shape: tuple[int, ...], what: str, src: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(src, f"{what} is not a numeric array") from None
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise InputError(src, f"{what} must be a finite array of shape {shape}, got {a.shape}")
    return a


def _robot(name: Any, src: str) -> Any:
    from fluoronav.manipulator.robot import UR10  # lazy: fast --help

    if name not in _ROBOTS:
        raise InputError(
            src, f"'robot' must be one of {', '.join(_ROBOTS)} for joint-angle poses, got {name!r}"
        )
    return UR10


def _poses_from_rows(rows: list[Any], robot_name: Any, src: str) -> np.ndarray:
    out = []
    for i, r in enumerate(rows):
        a = np.asarray(r, dtype=np.float64) if not isinstance(r, str) else None
        if a is None or not np.all(np.isfinite(a)):
            raise InputError(src, f"robot pose {i} is not numeric")
        if a.size == 16:
            out.append(a.reshape(4, 4))
        elif a.size == 6:
            out.append(_robot(robot_name, src).rbase_from_ee(a.reshape(6)))
        else:
            raise InputError(src, f"robot pose {i} must be a 4x4 matrix (16 values) or 6 joint angles")
    return np.asarray(out)


def _read_robot_poses(path: Path, robot_name: Any) -> np.ndarray:
    src = str(path)
    if not path.is_file():
        raise InputError(src, "robot pose file not found")
    try:
        if path.suffix.lower() == ".csv":
            with path.open(newline="") as f:
                rows = [
                    [float(x) for x in r] for r in csv.reader(f) if r and not r[0].lstrip().startswith("#")
                ]
        else:
            rows = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, OSError, UnicodeDecodeError) as exc:
        raise InputError(src, f"cannot parse robot poses ({exc.__class__.__name__})") from None
    if not isinstance(rows, list) or not rows:
        raise InputError(src, "robot poses must be a non-empty list")
    return _poses_from_rows(rows, robot_name, src)


def _calibration_views(
    d: dict[str, Any], vlist: list[Any], root: Path, camera: Any, binning: int | None, src: str
) -> tuple[list[Any], list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """The case's views → (CM views, robot poses given per view, tracker_from_marker and
    tracker_from_tip_marker given per view)."""
    from fluoronav.cli.register_case import detect_landmarks  # lazy: fast --help
    from fluoronav.detection.detector import load_image  # lazy: fast --help
    from fluoronav.registration.cm import CMView  # lazy: fast --help

    views, poses, t_os, t_ot = [], [], [], []
    for k, v in enumerate(vlist):
        if not isinstance(v, dict) or "image" not in v:
            raise InputError(src, f"views[{k}] must be an object with 'image'")
        if not isinstance(v["image"], str) or not v["image"]:
            raise InputError(src, f"views[{k}].image must be a file name")
        img, _ = load_image(root / v["image"])
        if img.shape != (camera.rows, camera.cols):
            raise InputError(
                src, f"views[{k}]: image {img.shape} does not match camera {camera.rows}x{camera.cols}"
            )
        lm = (
            _array(v["landmarks_px"], (2, 2), f"views[{k}].landmarks_px", src)
            if v.get("landmarks_px") is not None
            else detect_landmarks(img, src)
        )
        views.append(
            CMView(
                image=img,
                camera=camera,
                landmarks_px=lm,
                binning=binning,
                name=str(v.get("name", f"pose{k}")),
            )
        )
        if "rbase_from_ee" in v:
            poses.append(_array(v["rbase_from_ee"], (4, 4), f"views[{k}].rbase_from_ee", src))
        elif "joints_deg" in v:
            poses.append(
                _robot(d.get("robot"), src).rbase_from_ee(
                    _array(v["joints_deg"], (6,), f"views[{k}].joints_deg", src)
                )
            )
        if v.get("tracker_from_marker") is not None:
            t_os.append(_array(v["tracker_from_marker"], (4, 4), f"views[{k}].tracker_from_marker", src))
        if v.get("tracker_from_tip_marker") is not None:
            t_ot.append(
                _array(v["tracker_from_tip_marker"], (4, 4), f"views[{k}].tracker_from_tip_marker", src)
            )
    return views, poses, t_os, t_ot


def _calibration_truth(g: Any, src: str) -> dict[str, np.ndarray]:
    """``ground_truth`` → ``ee_from_cm`` (4, 4) and, when given, ``control_points_deg`` (5,)."""
    if not isinstance(g, dict) or "ee_from_cm" not in g:
        raise InputError(src, "'ground_truth' needs 'ee_from_cm'")
    gt = {"ee_from_cm": _array(g["ee_from_cm"], (4, 4), "ground_truth.ee_from_cm", src)}
    if g.get("control_points_deg") is not None:
        gt["control_points_deg"] = _array(
            g["control_points_deg"], (5,), "ground_truth.control_points_deg", src
        )
    return gt


def load_calibration_case(path: str | Path) -> CalibrationCase:
    """Read a calibration case file (module docstring).

    Raises:
        InputError: naming the file, for anything malformed or missing.
    """
    from fluoronav.geometry.camera import Camera  # lazy: fast --help

    p = Path(path)
    src = str(p)
    d = read_json_object(p, what="calibration case")
    root = p.parent
    if "camera" not in d:
        raise InputError(src, "'camera' (the one C-arm camera file) is required")
    cam_entry = d["camera"]
    if not isinstance(cam_entry, (str, dict)) or cam_entry == "":
        raise InputError(src, "'camera' must be a camera file name or a camera object")
    camera = (
        Camera.from_dict(cam_entry, source=f"{src} camera")
        if isinstance(cam_entry, dict)
        else Camera.load(root / str(cam_entry))
    )
    vlist = d.get("views")
    if not isinstance(vlist, list) or not vlist:
        raise InputError(src, "'views' must be a non-empty list")
    binning = d.get("binning")
    if binning is not None and (not isinstance(binning, int) or binning < 1):
        raise InputError(src, "'binning' must be a positive integer")
    views, poses, t_os, t_ot = _calibration_views(d, vlist, root, camera, binning, src)
    if len({v.name for v in views}) != len(views):
        raise InputError(src, "view names must be unique")
    if d.get("robot_poses") is not None:
        if poses:
            raise InputError(src, "give robot poses either per view or in 'robot_poses', not both")
        A = _read_robot_poses(root / str(d["robot_poses"]), d.get("robot"))
    elif len(poses) == len(views):
        A = np.asarray(poses)
    else:
        raise InputError(src, "every view needs 'rbase_from_ee' or 'joints_deg' (or give 'robot_poses')")
    if len(A) != len(views):
        raise InputError(src, f"{len(A)} robot poses for {len(views)} views")
    for name in ("initial_ee_from_cm", "initial_control_points_deg"):
        if name not in d:
            raise InputError(src, f"'{name}' is required")
    X0 = _array(d["initial_ee_from_cm"], (4, 4), "initial_ee_from_cm", src)
    cp0 = _array(d["initial_control_points_deg"], (5,), "initial_control_points_deg", src)
    for what, lst in (("tracker_from_marker", t_os), ("tracker_from_tip_marker", t_ot)):
        if lst and len(lst) != len(views):
            raise InputError(src, f"'{what}' must be given for every view or none")
    tip_ot = (
        _array(d["tip_in_tip_marker_mm"], (3,), "tip_in_tip_marker_mm", src)
        if d.get("tip_in_tip_marker_mm") is not None
        else None
    )
    gt = _calibration_truth(d["ground_truth"], src) if d.get("ground_truth") is not None else None
    return CalibrationCase(
        views=views,
        rbase_from_ee=A,
        initial_ee_from_cm=X0,
        initial_control_points_deg=cp0,
        tracker_from_marker=np.asarray(t_os) if t_os else None,
        tracker_from_tip_marker=np.asarray(t_ot) if t_ot else None,
        tip_in_tip_marker_mm=tip_ot,
        ground_truth=gt,
        source=src,
    )


def run_calibration(
    case_path: Path, out: Path, *, seed: int = 0, device: str = "cpu", config: Any = None
) -> dict[str, Any]:
    """Calibrate a case and write ``handeye.json``, ``trace.json`` and overlays; returns handeye.json."""
    import torch  # heavy: torch

    from fluoronav.calibration.handeye import tip_rbase_image_chain  # lazy: fast --help
    from fluoronav.calibration.image_handeye import (  # lazy: fast --help
        ImageHandEyeConfig,
        calibrate_hand_eye_from_images,
    )
    from fluoronav.calibration.results import HandEyeFailure  # lazy: fast --help
    from fluoronav.device import resolve_device  # heavy: torch
    from fluoronav.manipulator.kinematics import CMKinematics  # lazy: fast --help

    case = load_calibration_case(case_path)
    cfg = (config or ImageHandEyeConfig()).with_(device=str(resolve_device(device)))
    res = calibrate_hand_eye_from_images(
        case.views,
        case.rbase_from_ee,
        initial_ee_from_cm=case.initial_ee_from_cm,
        initial_control_points_deg=case.initial_control_points_deg,
        config=cfg,
        seed=seed,
    )
    out.mkdir(parents=True, exist_ok=True)
    d: dict[str, Any] = {"case": str(case_path), "seed": seed, "n_poses": len(case.views)}
    if isinstance(res, HandEyeFailure):
        d.update(ok=False, reason=res.reason)
        (out / "handeye.json").write_text(json.dumps(d, indent=1), encoding="utf-8")
        return d
    d.update(ok=True, **res.to_dict())
    kin = CMKinematics(cfg.cm_config)
    tip_cm = kin.tip_cm(torch.as_tensor(res.control_points_deg)).numpy()
    carm_from_cm = np.stack([case.views[0].camera.camera_from_world @ W for W in res.world_from_cm])
    tip_carm = np.einsum("mij,j->mi", carm_from_cm[:, :3, :3], tip_cm) + carm_from_cm[:, :3, 3]
    tip10 = tip_rbase_image_chain(case.rbase_from_ee, res.ee_from_cm, carm_from_cm, tip_carm)
    d["tip_rbase_eq10_mm"] = tip10.tolist()
    if case.tracker_from_marker is not None:
        d["tracker_baselines"] = _tracker_baselines(case, case.tracker_from_marker, tip10)
    if case.ground_truth is not None:
        d["errors"] = _ground_truth_errors(case, case.ground_truth, res.ee_from_cm, kin, tip10)
    (out / "handeye.json").write_text(json.dumps(d, indent=1), encoding="utf-8")
    res.trace.to_json(out / "trace.json")
    _overlays(res, out)
    return d


def _tracker_baselines(
    case: CalibrationCase, tracker_from_marker: np.ndarray, tip10: np.ndarray
) -> dict[str, dict[str, Any]]:
    """Per tracker method (AX = XB and AX = YB) its hand-eye from the shaft marker's poses, and with
    the tip marker its eq. 9 tip beside the images' eq. 10 tip ``tip10`` (M, 3) mm."""
    from fluoronav.calibration.handeye import (  # lazy: fast --help
        AX_XB_METHODS,
        AX_YB_METHODS,
        calibrate_hand_eye,
        calibrate_robot_world_hand_eye,
        tip_rbase_tracker_chain,
    )
    from fluoronav.calibration.results import HandEyeFailure  # lazy: fast --help

    baselines = {}
    for method in (*AX_XB_METHODS, *AX_YB_METHODS):
        solve = calibrate_hand_eye if method in AX_XB_METHODS else calibrate_robot_world_hand_eye
        b = solve(case.rbase_from_ee, tracker_from_marker, method=method)
        if isinstance(b, HandEyeFailure):
            baselines[method] = {"ok": False, "reason": b.reason}
            continue
        entry: dict[str, Any] = {
            "ok": True,
            "formulation": b.formulation,
            "ee_from_marker": b.ee_from_marker.tolist(),
            "mean_residual_rotation_deg": b.mean_residual_rotation_deg,
            "mean_residual_translation_mm": b.mean_residual_translation_mm,
        }
        if case.tracker_from_tip_marker is not None and case.tip_in_tip_marker_mm is not None:
            tip9 = tip_rbase_tracker_chain(
                case.rbase_from_ee,
                b.ee_from_marker,
                tracker_from_marker,
                case.tracker_from_tip_marker,
                case.tip_in_tip_marker_mm,
            )
            dist = np.linalg.norm(tip9 - tip10, axis=1)
            entry["eq9_vs_eq10_mm"] = {
                "mean": float(dist.mean()),
                "std": float(dist.std()),
                "per_pose": dist.tolist(),
            }
        baselines[method] = entry
    return baselines


def _ground_truth_errors(
    case: CalibrationCase,
    truth: dict[str, np.ndarray],
    ee_from_cm: np.ndarray,
    kin: CMKinematics,
    tip10: np.ndarray,
) -> dict[str, float]:
    """The calibration's errors against the case's ``truth``: hand-eye rotation (degrees) and
    translation (mm), and with the true shape the mean tip error against ``tip10`` (M, 3) mm."""
    import torch  # heavy: torch

    from fluoronav.calibration.handeye import transform_error  # lazy: fast --help

    rot, trans = transform_error(ee_from_cm, truth["ee_from_cm"])
    errors = {"handeye_rotation_deg": rot, "handeye_translation_mm": trans}
    if "control_points_deg" in truth:
        true_tip = case.rbase_from_ee @ truth["ee_from_cm"]
        tt = kin.tip_cm(torch.as_tensor(truth["control_points_deg"])).numpy()
        p = np.einsum("mij,j->mi", true_tip[:, :3, :3], tt) + true_tip[:, :3, 3]
        errors["handeye_tip_mm"] = float(np.linalg.norm(p - tip10, axis=1).mean())
    return errors


def _overlays(res: Any, out: Path) -> None:
    import cv2  # heavy: cv2

    from fluoronav.registration.cm.overlays import edge_mask, to_uint8  # lazy: fast --help

    for name, img, drr in zip(res.view_names, res.roi_images, res.roi_drrs, strict=True):
        rgb = np.repeat(to_uint8(img)[..., None], 3, axis=-1)
        rgb[edge_mask(drr)] = (0, 255, 0)
        cv2.imwrite(str(out / f"overlay_{name}.png"), np.kron(rgb, np.ones((4, 4, 1), np.uint8))[..., ::-1])


def write_example_calibration_case(
    out_dir: str | Path, *, seed: int = 0, n_poses: int = 6, image_size: int = 384, with_tracker: bool = True
) -> Path:
    """Simulate a calibration case of the phantom (physics simulator, true robot with errors, nominal
    FK in the file, oracle landmarks, simulated tracker readings) → path of ``case.json``.

    The initial hand-eye is the truth perturbed by 5° / 5 mm; ``ground_truth`` holds the truth."""
    import torch  # heavy: torch

    from fluoronav.calibration.tracker import DEFAULT_BODY, OpticalTracker  # lazy: fast --help
    from fluoronav.geometry import se3  # lazy: fast --help
    from fluoronav.manipulator.kinematics import CMKinematics  # lazy: fast --help
    from fluoronav.simulation.articulated import anatomy_and_simulator  # lazy: fast --help
    from fluoronav.simulation.robot_scene import (  # lazy: fast --help
        perturb_transform,
        sample_handeye_scenario,
        simulate_scenario_images,
    )

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    volume, simulator = anatomy_and_simulator("phantom", 0, image_size, "cpu")
    sc = sample_handeye_scenario(volume, rng, n_poses=n_poses)
    images = simulate_scenario_images(sc, simulator, seed=int(rng.integers(2**31)), image_size=image_size)
    cam = images[0].camera
    cam.save(out / "camera.json")
    b = max(1, round(1536 / image_size))
    views = []
    for m, im in enumerate(images):
        np.savez_compressed(out / f"pose{m}.npz", image=im.image.astype(np.float32))
        lm = (sc.landmarks_px[m] + rng.uniform(-3.0, 3.0, (2, 2)) + 0.5) / b - 0.5
        views.append(
            {
                "image": f"pose{m}.npz",
                "name": f"pose{m}",
                "joints_deg": sc.q_deg[m].tolist(),
                "landmarks_px": lm.tolist(),
            }
        )
    d: dict[str, Any] = {
        "camera": "camera.json",
        "robot": "UR10",
        "views": views,
        "initial_ee_from_cm": perturb_transform(sc.ee_from_cm, rng, 5.0, 5.0).tolist(),
        "initial_control_points_deg": (sc.control_points_deg + rng.uniform(-0.5, 0.5, 5)).tolist(),
        "ground_truth": {
            "ee_from_cm": sc.ee_from_cm.tolist(),
            "control_points_deg": sc.control_points_deg.tolist(),
        },
    }
    if with_tracker:
        kin = CMKinematics()
        tracker = OpticalTracker()
        cm_from_os = se3.make(np.eye(3), [30.0, 0.0, -60.0])
        link = kin.link_transforms(torch.as_tensor(sc.control_points_deg, dtype=torch.float64))[-1].numpy()
        cm_from_ot = link @ se3.make(np.eye(3), [15.0, 0.0, 0.0])
        tip_cm = kin.tip_cm(torch.as_tensor(sc.control_points_deg, dtype=torch.float64)).numpy()
        tracker_from_rbase = np.linalg.inv(se3.make(np.eye(3), [1500.0, 0.0, 500.0]))
        true_ee = sc.true_robot.rbase_from_ee(sc.q_actual_deg)
        t_os = tracker.track(tracker_from_rbase @ true_ee @ sc.ee_from_cm @ cm_from_os, DEFAULT_BODY, rng=rng)
        t_ot = tracker.track(tracker_from_rbase @ true_ee @ sc.ee_from_cm @ cm_from_ot, DEFAULT_BODY, rng=rng)
        for m, v in enumerate(views):
            v["tracker_from_marker"] = t_os.tracker_from_body[m].tolist()
            v["tracker_from_tip_marker"] = t_ot.tracker_from_body[m].tolist()
        d["tip_in_tip_marker_mm"] = (np.linalg.inv(cm_from_ot) @ np.append(tip_cm, 1.0))[:3].tolist()
    path = out / "case.json"
    path.write_text(json.dumps(d, indent=1), encoding="utf-8")
    return path


def calibrate_command(
    case: Path = typer.Argument(..., help="Calibration case file (JSON), see docs/robot-and-calibration.md."),
    out: Path = typer.Option(..., "--out", help="Output directory (handeye.json, trace.json, overlays)."),
    seed: int = SEED_OPTION,
    device: str = DEVICE_OPTION,
) -> None:
    """Image-based hand-eye calibration (ee_from_cm) from X-ray images and robot poses."""
    d = run_calibration(case, out, seed=seed, device=device)
    if not d.get("ok"):
        typer.echo(f"calibration failed: {d.get('reason')} -> {out / 'handeye.json'}")
        raise typer.Exit(1)
    msg = f"hand-eye from {d['n_poses']} poses: {d['reason']} in {d['seconds']:.1f} s"
    if "errors" in d:
        e = d["errors"]
        msg += f"; error {e['handeye_rotation_deg']:.2f}° / {e['handeye_translation_mm']:.2f} mm"
    typer.echo(f"{msg} -> {out / 'handeye.json'}")


def register(app: typer.Typer) -> None:
    app.command("calibrate")(calibrate_command)
