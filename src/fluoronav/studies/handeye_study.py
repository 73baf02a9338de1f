"""The ``hand-eye`` and ``navigation`` simulation studies (``fluoronav study hand-eye|navigation``):
running the trials of :mod:`fluoronav.studies.handeye_trials` (what each trial does is described
there), resuming, the rows' columns, the figures and ``summary.json`` (with, for navigation, the
refusals and the unflagged gross failures).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from fluoronav import __version__
from fluoronav.anatomy.io import resolve_ct
from fluoronav.errors import InputError
from fluoronav.navigation.config import NavigationConfig
from fluoronav.runner import CsvLog, run_tasks
from fluoronav.settings import settings_dict
from fluoronav.simulation.navigation.faults import get_fault
from fluoronav.simulation.world import IDEAL, World
from fluoronav.studies.figures import column, study_figures
from fluoronav.studies.handeye_trials import (
    HANDEYE_DIAGNOSTICS,
    HANDEYE_METRICS,
    NAVIGATION_CAUSES,
    NAVIGATION_CHECKS,
    NAVIGATION_DIAGNOSTICS,
    NAVIGATION_METRICS,
    HandEyeStudyConfig,
    detector_or_none,
    navigation_row,
    run_handeye_trial,
    run_navigation_trial,
)
from fluoronav.studies.study_ct import HANDEYE_CT, NAVIGATION_CT, check_study_ct
from fluoronav.studies.summary import summarize, write_summary

__all__ = [
    "HANDEYE_METRICS",
    "NAVIGATION_METRICS",
    "HandEyeStudyConfig",
    "navigation_row",
    "refusals_named_right",
    "run_handeye_or_navigation_study",
    "run_handeye_study",
    "run_handeye_trial",
    "run_navigation_trial",
]

log = logging.getLogger(__name__)


def _columns(cfg: HandEyeStudyConfig) -> list[str]:
    head = ["trial", "seed", "workflow", "status", "reason"]
    tail = ["seconds", "seconds_registration", "seconds_bones"]
    if cfg.workflow == "navigation":
        return [
            *head,
            *NAVIGATION_METRICS,
            *NAVIGATION_DIAGNOSTICS,
            *NAVIGATION_CHECKS,
            "landmarks",
            "joint_motion_deg",
            "reposition_reason",
            "check",
            "cm_axis_deg",
            *tail,
            "seconds_verification",
            *(("fault", "fault_outcome", "fault_handled", "left_out") if cfg.fault is not None else ()),
            *NAVIGATION_CAUSES,  # last: a study resumed from before them keeps its columns aligned
        ]
    per_m = [
        f"{k}_m{m}"
        for m in sorted(cfg.poses)
        for k in ("handeye_tip_mm", "handeye_rotation_deg", "handeye_translation_mm", "seconds")
    ]
    return [
        *head,
        *HANDEYE_METRICS,
        *HANDEYE_DIAGNOSTICS,
        "n_poses",
        "converged",
        "mean_residual_px",
        "landmarks",
        "baseline_reason",
        *per_m,
        *[f"reason_m{m}" for m in sorted(cfg.poses)],
        *tail,
        "true_ee_from_cm",
        "est_ee_from_cm",
        "true_control_points_deg",
        "est_control_points_deg",
    ]


def _figures(rows: list[dict[str, Any]], out: Path, cfg: HandEyeStudyConfig) -> list[Path]:
    """The generic histograms plus: hand-eye error vs M; navigation repositioning histogram."""
    import matplotlib  # heavy: matplotlib, for the figures only

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after use("Agg")

    written = study_figures(rows, out, workflow=cfg.workflow)
    ok = [r for r in rows if str(r.get("status")) == "ok"]
    if cfg.workflow == "hand-eye":
        ms = sorted(cfg.poses)
        fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
        for ax, (key, label) in zip(
            axes,
            (
                ("handeye_tip_mm", "tip error (mm)"),
                ("handeye_rotation_deg", "rotation error (°)"),
                ("handeye_translation_mm", "translation error (mm)"),
            ),
            strict=True,
        ):
            data = [column(ok, f"{key}_m{m}") for m in ms]
            keep = [i for i, d in enumerate(data) if len(d)]
            if keep:
                ax.boxplot([data[i] for i in keep], showfliers=True)
                ax.plot(
                    range(1, len(keep) + 1),
                    [float(np.mean(data[i])) for i in keep],
                    "o-",
                    color="crimson",
                    label="mean",
                )
                ax.set_xticks(range(1, len(keep) + 1), [str(ms[i]) for i in keep])
            ax.set_xlabel("number of robot poses M")
            ax.set_ylabel(f"hand-eye {label}")
        if "baseline_tip_mm" in (ok[0] if ok else {}):
            axes[0].axhline(
                float(np.mean(column(ok, "baseline_tip_mm"))),
                color="grey",
                linestyle="--",
                label="tracker AX=XB, eq. 9",
            )
        axes[0].legend(fontsize=8)
        fig.suptitle(f"image-based hand-eye: error vs number of poses (n = {len(ok)} trials)")
        fig.tight_layout()
        p = out / "handeye_error_vs_poses.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        written.append(p)
    else:
        v = column(ok, "reposition_tip_mm")
        if len(v):
            fig, ax = plt.subplots(figsize=(5, 3.6))
            ax.hist(v, bins=min(30, max(5, len(v) // 2)), color="steelblue", edgecolor="white")
            ax.axvline(float(np.mean(v)), color="crimson", linestyle="--", label=f"mean {np.mean(v):.2f} mm")
            ax.set_xlabel("repositioning tip error (mm)")
            ax.set_ylabel("trials")
            ax.legend(fontsize=8)
            fig.tight_layout()
            p = out / "reposition_error_histogram.png"
            fig.savefig(p, dpi=100)
            plt.close(fig)
            written.append(p)
    return written


#: a navigation that said "ok" and left the true tip further than this from the plan failed unflagged
GROSS_FAILURE_MM = 2.0
#: a first command from a registration whose CM tip (mm) or axis (degrees) is further than these
#: from the truth went unflagged: it runs before any verification
FIRST_MOVE_TIP_MM = 2.0
FIRST_MOVE_AXIS_DEG = 5.0


def _cell(r: dict[str, Any], key: str) -> float:
    """A row's number (nan where empty or not a number)."""
    try:
        return float(r.get(key) or "nan")
    except (TypeError, ValueError):
        return float("nan")


def _first_move_failures(rows: list[dict[str, Any]], tip_key: str, axis_key: str) -> list[int]:
    """Trials whose first command was carried out from a registration with its CM tip more than
    :data:`FIRST_MOVE_TIP_MM` or its axis more than :data:`FIRST_MOVE_AXIS_DEG` from the truth."""
    return [
        int(r["trial"])
        for r in rows
        if math.isfinite(_cell(r, "reposition_open_loop_mm"))
        and (_cell(r, tip_key) > FIRST_MOVE_TIP_MM or _cell(r, axis_key) > FIRST_MOVE_AXIS_DEG)
    ]


def _navigation_outcomes(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """``unflagged_gross_failures``: rows with status ok whose final true tip is more than
    :data:`GROSS_FAILURE_MM` from the plan; ``unflagged_first_move_failures``: rows whose first
    command was carried out from a registration with its CM tip or axis too far from the truth in
    the femur's frame, the frame of the plan and of the move (``femur_tip_mm``,
    ``femur_axis_deg``); ``..._carm_frame``: the same in the AP view's C-arm frame (``tip_mm``,
    ``cm_axis_deg``), where an error the bones and the CM share counts too (docs/data-formats.md,
    study output); each with their trial numbers."""
    bad = [
        int(r["trial"])
        for r in rows
        if str(r.get("status")) == "ok" and _cell(r, "reposition_tip_mm") > GROSS_FAILURE_MM
    ]
    first = _first_move_failures(rows, "femur_tip_mm", "femur_axis_deg")
    carm = _first_move_failures(rows, "tip_mm", "cm_axis_deg")
    return {
        "unflagged_gross_failures": len(bad),
        "unflagged_gross_failure_trials": bad,
        "unflagged_first_move_failures": len(first),
        "unflagged_first_move_failure_trials": first,
        "unflagged_first_move_failures_carm_frame": len(carm),
        "unflagged_first_move_failure_trials_carm_frame": carm,
        "refusals_named_right": refusals_named_right(rows),
    }


def refusals_named_right(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """How many refusals (and bad inputs) named the cause the simulation knows (rows' ``true_cause``,
    ``named_cause``, ``cause_named_right``): ``fraction`` of those with a known cause (None without
    any), the counts ``named_right``, ``known_cause`` and ``refusals``, and per true cause the named
    ones (``named_by_true_cause``: true → named → count)."""
    refusals = [r for r in rows if str(r.get("true_cause") or "")]
    known = [r for r in refusals if str(r.get("cause_named_right")) in ("True", "False")]
    right = sum(str(r.get("cause_named_right")) == "True" for r in known)
    table: dict[str, dict[str, int]] = {}
    for r in refusals:
        named = table.setdefault(str(r["true_cause"]), {})
        key = str(r.get("named_cause") or "unnamed")
        named[key] = named.get(key, 0) + 1
    return {
        "fraction": right / len(known) if known else None,
        "named_right": right,
        "known_cause": len(known),
        "refusals": len(refusals),
        "named_by_true_cause": table,
    }


def _fault_outcomes(rows: list[dict[str, Any]], fault: str) -> dict[str, Any]:
    """A fault study's ``fault`` and its rows' counts per ``fault_outcome`` and handled."""
    counts = {k: 0 for k in ("landed", "refused_named", "refused_other", "unsafe", "failed")}
    for r in rows:
        key = str(r.get("fault_outcome") or "failed")
        counts[key] = counts.get(key, 0) + 1
    handled = sum(str(r.get("fault_handled")) == "True" for r in rows)
    return {"fault": fault, "fault_outcomes": counts, "fault_handled": handled}


def run_handeye_study(
    cfg: HandEyeStudyConfig, out: Path, *, scheduler: str | None = None, workers: int | None = None
) -> dict[str, Any]:
    """Run (or resume) a hand-eye or navigation study into ``out``: trials.csv, summary.json,
    config.json, figures/."""
    if cfg.workflow not in ("hand-eye", "navigation"):
        raise InputError("WORKFLOW", f"unknown workflow {cfg.workflow!r}; use hand-eye or navigation")
    if any(m < 1 for m in cfg.poses):
        raise InputError("--poses", "numbers of poses must be positive")
    if cfg.corrections not in (0, 1):
        raise InputError("--corrections", "0 (open loop) or 1 (one corrective move)")
    if cfg.fault is not None:
        if cfg.workflow != "navigation":
            raise InputError("--fault", "faults are injected into study navigation only")
        get_fault(cfg.fault)
    out.mkdir(parents=True, exist_ok=True)
    cfg_path = out / "config.json"
    cfg_dict = {**dataclasses.asdict(dataclasses.replace(cfg, navigation=None)), "version": __version__}
    cfg_dict["poses"] = list(cfg.poses)
    cfg_dict["world"] = cfg.world.to_dict()
    del cfg_dict["navigation"]  # recorded only where a site's settings file gave it
    if cfg.navigation is not None:
        cfg_dict["navigation"] = _site_settings(cfg.navigation)
    if cfg_path.exists():
        old = json.loads(cfg_path.read_text(encoding="utf-8"))
        keep = {*cfg_dict, "navigation"} - {"trials", "device", "version"}
        if any(old.get(k) != cfg_dict.get(k) for k in keep):
            raise InputError(cfg_path, "this directory holds a study with other settings; use another --out")
    if cfg.ct != "phantom":
        # fail early, in this process, on a bad CT or one without what the scene needs
        needs = HANDEYE_CT if cfg.workflow == "hand-eye" else NAVIGATION_CT
        check_study_ct(resolve_ct(cfg.ct), cfg.ct, needs)
    detector = detector_or_none(cfg.device)
    cfg_dict["detector_precision"] = None if detector is None else detector.precision
    cfg_path.write_text(json.dumps(cfg_dict, indent=2), encoding="utf-8")
    csv_log = CsvLog(out / "trials.csv", _columns(cfg))
    fn = run_handeye_trial if cfg.workflow == "hand-eye" else run_navigation_trial
    run_tasks(
        functools.partial(fn, cfg=cfg),
        cfg.trials,
        cfg.seed,
        csv_log,
        scheduler=scheduler,
        workers=workers,
        description=f"study {cfg.workflow}",
    )
    rows = sorted(csv_log.read(), key=lambda r: int(r["trial"]))
    names = list(HANDEYE_METRICS if cfg.workflow == "hand-eye" else NAVIGATION_METRICS)
    if cfg.workflow == "navigation":
        names += list(NAVIGATION_DIAGNOSTICS) + list(NAVIGATION_CHECKS)
    if cfg.workflow == "hand-eye":
        names += list(HANDEYE_DIAGNOSTICS)
        names += [
            f"{k}_m{m}"
            for m in sorted(cfg.poses)
            for k in ("handeye_tip_mm", "handeye_rotation_deg", "handeye_translation_mm")
        ]
    summary = summarize(
        cfg.workflow,
        rows,
        names,
        trials=cfg.trials,
        device=cfg.device,
        extra={
            "seed": cfg.seed,
            "ct": cfg.ct,
            "world": cfg.world.to_dict(),
            **({"verify_views": cfg.verify_views} if cfg.workflow == "navigation" else {}),
            "poses": list(cfg.poses),
            "landmarks": "oracle" if cfg.oracle_landmarks else "detector",
            **(_navigation_outcomes(rows) if cfg.workflow == "navigation" else {}),
            **(_fault_outcomes(rows, cfg.fault) if cfg.fault is not None else {}),
            "image_size": cfg.image_size,
        },
    )
    write_summary(out / "summary.json", summary)
    _figures(rows, out / "figures", cfg)
    return summary


def _site_settings(navigation: NavigationConfig) -> dict[str, Any]:
    """A site's navigation settings as ``config.json`` records them (each trial sets its own device
    and seed)."""
    return {k: v for k, v in settings_dict(navigation).items() if k not in ("device", "seed")}


def run_handeye_or_navigation_study(
    workflow: str,
    *,
    trials: int,
    seed: int,
    out: Path,
    ct: str = "phantom",
    scheduler: str | None = None,
    workers: int | None = None,
    device: str = "cpu",
    poses: Sequence[int] = (4, 8, 15),
    image_size: int = 768,
    corrections: int = 1,
    oracle_landmarks: bool = False,
    calibration_bend_deg: float | None = 2.5,
    fault: str | None = None,
    handeye_error_mm: float | None = None,
    handeye_error_deg: float | None = None,
    world: World = IDEAL,
    verify_views: int = 3,
    navigation: NavigationConfig | None = None,
) -> dict[str, Any]:
    """Entry point of ``fluoronav study hand-eye|navigation`` → the summary dict.

    ``world``: the navigation's simulated world (:mod:`fluoronav.simulation.world`);
    ``verify_views``: the navigation's verification images per case (1, 2 or 3); ``navigation``: its
    pipeline's settings (a site's settings file; None: the defaults).

    ``fault``: an input fault (:data:`fluoronav.simulation.navigation.faults.FAULTS`) for navigation;
    ``handeye_error_mm`` / ``handeye_error_deg``: the navigation's hand-eye error (None: the fault's,
    else :class:`HandEyeStudyConfig`'s default).
    """
    spec = get_fault(fault)
    if handeye_error_mm is None and spec is not None:
        handeye_error_mm = spec.handeye_error_mm
    cfg = HandEyeStudyConfig(
        workflow=workflow,
        trials=trials,
        seed=seed,
        ct=ct,
        poses=tuple(int(m) for m in poses),
        image_size=image_size,
        device=device,
        corrections=corrections,
        oracle_landmarks=oracle_landmarks,
        calibration_bend_deg=calibration_bend_deg,
        fault=fault,
        handeye_error_mm=HandEyeStudyConfig.handeye_error_mm
        if handeye_error_mm is None
        else handeye_error_mm,
        handeye_error_deg=HandEyeStudyConfig.handeye_error_deg
        if handeye_error_deg is None
        else handeye_error_deg,
        world=world,
        verify_views=verify_views,
        navigation=navigation,
    )
    return run_handeye_study(cfg, Path(out), scheduler=scheduler, workers=workers)
