"""``report.html`` of a navigation: one self-contained page with the pictures and the numbers.

Sections: the status (a red banner when the run refused, with its reason), the stages with their
seconds and checks, the robot commands, errors against the truth where a simulation knows it,
detection per view, Fig. 12-style overlays (edges of the registered CM DRR on the image, and of the
registered femur on each whole view), a 3D picture in the CT frame (pelvis, femur at its registered
pose, the registered CM, the plan, the C-arm sources), and the convergence of every registration.
"""

from __future__ import annotations

import html
import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy import ndimage
from skimage.feature import canny

from fluoronav import __version__
from fluoronav.geometry import se3
from fluoronav.htmlpage import Section, figure_png, html_page
from fluoronav.manipulator.kinematics import CMKinematics
from fluoronav.navigation.case.model import NavigationCase
from fluoronav.navigation.pipeline import NavigationResult
from fluoronav.registration.bone import bone_excess_mu
from fluoronav.registration.view_set import ViewSetRegistration
from fluoronav.rendering.ct import render_line_integrals

log = logging.getLogger(__name__)

__all__ = ["navigation_figures", "write_report"]


def _pyplot() -> Any:
    """matplotlib's pyplot, imported when a figure is drawn, not when the navigation starts."""
    import matplotlib.pyplot as plt

    return plt


def _gray(ax: Any, img: np.ndarray, extent: Any = None) -> None:
    lo, hi = np.percentile(img, [1, 99.5])
    ax.imshow(img, cmap="gray", vmin=lo, vmax=hi, extent=extent, interpolation="nearest")
    ax.set_xticks([])
    ax.set_yticks([])


def _edges(img: np.ndarray, frac: float = 0.2) -> np.ndarray:
    """Thin (Canny) edges of a DRR, thresholds relative to its strongest gradient."""
    img = np.asarray(img, dtype=np.float64)
    top = float(np.ptp(img))
    if top <= 0:
        return np.zeros(img.shape, bool)
    return canny(img / top, sigma=1.0, low_threshold=0.5 * frac * 0.25, high_threshold=frac * 0.25)


def _box(points: np.ndarray, shape: tuple[int, ...], margin: float) -> tuple[int, int, int, int]:
    lo = np.floor(points.min(axis=0) - margin).astype(int)
    hi = np.ceil(points.max(axis=0) + margin).astype(int)
    c0, r0 = max(lo[0], 0), max(lo[1], 0)
    c1, r1 = min(hi[0], shape[1]), min(hi[1], shape[0])
    return r0, r1, c0, c1


def _detection_figure(reg: ViewSetRegistration, true_landmarks: Sequence[np.ndarray] | None) -> bytes:
    n = len(reg.views)
    fig, axes = _pyplot().subplots(1, n, figsize=(4.2 * n, 4.2), squeeze=False)
    for k, (ax, view, det) in enumerate(zip(axes[0], reg.views, reg.detections, strict=True)):
        img = view.image
        if det is None:
            _gray(ax, img)
            ax.set_title(f"{view.name}: no CM", fontsize=9)
            continue
        vv, uu = np.nonzero(det.mask) if det.mask.any() else np.nonzero(np.ones_like(img, bool))
        r0, r1, c0, c1 = _box(np.stack([uu, vv], axis=1).astype(float), img.shape, 25.0)
        _gray(ax, img[r0:r1, c0:c1], extent=(c0 - 0.5, c1 - 0.5, r1 - 0.5, r0 - 0.5))
        ax.contour(
            np.arange(c0, c1),
            np.arange(r0, r1),
            det.mask[r0:r1, c0:c1],
            [0.5],
            colors="yellow",
            linewidths=0.7,
        )
        ax.plot(det.centerline_px[:, 0], det.centerline_px[:, 1], "-", color="cyan", lw=1)
        lm = det.landmarks_px
        title = f"{view.name} ({det.source})"
        if true_landmarks is not None:
            lt = np.asarray(true_landmarks[k])
            ax.plot(lt[:, 0], lt[:, 1], "o", mfc="none", mec="lime", ms=9, label="true A, B")
            err = np.linalg.norm(lm - lt, axis=1)
            title += f": A {err[0]:.2f} px, B {err[1]:.2f} px"
        ax.plot(lm[:, 0], lm[:, 1], "+", color="red", ms=10, mew=1.5, label="A, B")
        for (u, v), t in zip(lm, "AB", strict=True):
            ax.annotate(t, (u, v), xytext=(5, -5), textcoords="offset points", color="red")
        ax.set_title(title, fontsize=9)
    axes[0][0].legend(loc="lower left", fontsize=7)
    fig.suptitle("Detection: mask (yellow), centreline (cyan), landmarks", fontsize=10)
    return figure_png(fig)


def _cm_overlay_figure(reg: ViewSetRegistration, title: str) -> bytes:
    """Fig. 12 style: edges of the registered CM DRR (green) on each view's ROI."""
    cm = reg.cm
    k = len(cm.view_names)
    fig, axes = _pyplot().subplots(1, k, figsize=(4.2 * k, 4.4), squeeze=False)
    for ax, name, img, drr in zip(axes[0], cm.view_names, cm.roi_images, cm.roi_drrs, strict=True):
        lo, hi = np.percentile(img, [1, 99.5])
        rgb = np.repeat(np.clip((img - lo) / max(hi - lo, 1e-9), 0, 1)[..., None], 3, axis=-1)
        rgb[_edges(drr)] = (0.1, 1.0, 0.1)
        ax.imshow(rgb, interpolation="nearest")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(name, fontsize=9)
    fig.suptitle(title, fontsize=10)
    return figure_png(fig)


def _femur_overlay_figure(reg: ViewSetRegistration, case: NavigationCase) -> bytes:
    """Edges of the femur DRR at the registered pose (green) on each whole view."""
    mu, w_idx = bone_excess_mu(case.volume, [f"femur_{case.side}"])
    size = 256
    n = len(reg.views)
    fig, axes = _pyplot().subplots(1, n, figsize=(4.2 * n, 4.4), squeeze=False)
    for ax, view, cam in zip(axes[0], reg.views, reg.cameras_ct, strict=True):
        f = max(1, cam.cols // size)
        small = cam.downsample(f)
        T = (small.camera_from_world @ reg.ct_from_femur)[None]
        drr = render_line_integrals(torch.from_numpy(mu), w_idx, small.K[None], T, small.rows, small.cols)[0]
        img = (
            view.image[: small.rows * f, : small.cols * f]
            .reshape(small.rows, f, small.cols, f)
            .mean(axis=(1, 3))
        )
        lo, hi = np.percentile(img, [1, 99.5])
        rgb = np.repeat(np.clip((img - lo) / max(hi - lo, 1e-9), 0, 1)[..., None], 3, axis=-1)
        rgb[_edges(drr.cpu().numpy(), 0.15)] = (0.1, 1.0, 0.1)
        ax.imshow(rgb, interpolation="nearest")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(view.name, fontsize=9)
    fig.suptitle("Femur registration: edges of the registered femur DRR (green)", fontsize=10)
    return figure_png(fig)


def _surface_points(volume: Any, label: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """Up to n CT points on the boundary of a label (for a light 3D picture)."""
    v = volume.label_value(label)
    if v is None or volume.labels is None:
        return np.zeros((0, 3))
    m = volume.labels[::2, ::2, ::2] == v
    edge = m & ~ndimage.binary_erosion(m)
    idx = np.argwhere(edge)[:, ::-1].astype(np.float64) * 2.0  # (i, j, k) in the full grid
    if len(idx) > n:
        idx = idx[rng.choice(len(idx), n, replace=False)]
    W = np.asarray(volume.world_from_index, np.float64)
    return idx @ W[:3, :3].T + W[:3, 3]


def _scene_figure(
    result: NavigationResult, case: NavigationCase, true_ct_from_cm: Mapping[str, np.ndarray] | None
) -> bytes:
    """3D, CT frame: pelvis, femur (registered), the CM registered (and true), the plan, C-arms."""
    first = result.first
    assert first is not None
    kin = CMKinematics(case.cm_config)
    rng = np.random.default_rng(0)
    fig = _pyplot().figure(figsize=(10, 8))
    ax = fig.add_subplot(111, projection="3d")
    pel = _surface_points(case.volume, "pelvis", 2500, rng)
    fem = se3.apply(first.ct_from_femur, _surface_points(case.volume, f"femur_{case.side}", 1500, rng))
    ax.scatter(*pel.T, s=0.6, c="#888888", alpha=0.5, label="pelvis (CT)")
    ax.scatter(*fem.T, s=0.4, c="#d9a066", alpha=0.5, label="femur (registered)")

    def axis_of(cp: np.ndarray) -> np.ndarray:
        t = torch.as_tensor(np.asarray(cp, np.float64), dtype=torch.float64)
        return kin.centerline_cm(t, n_points=40, to_z_mm=kin.config.tip_z_mm).numpy()

    cp_est = np.asarray(first.cm.control_points_deg)
    curves: list[tuple[np.ndarray, dict[str, Any], str]] = [
        (se3.apply(first.ct_from_cm, axis_of(cp_est)), dict(color="tab:red", lw=2), "CM (registered)")
    ]
    if result.femur_from_cm_target is not None:
        plan_ct = first.ct_from_femur @ result.femur_from_cm_target
        curves.append((se3.apply(plan_ct, axis_of(cp_est)), dict(color="tab:green", lw=1.5, ls="--"), "plan"))
    if result.verification is not None:
        v = result.verification
        curves.append(
            (
                se3.apply(v.ct_from_cm, axis_of(v.cm.control_points_deg)),
                dict(color="tab:blue", lw=2),
                "CM after the move (registered)",
            )
        )
    for label, T in (true_ct_from_cm or {}).items():
        curves.append((se3.apply(np.asarray(T), axis_of(cp_est)), dict(color="k", lw=1, ls=":"), label))
    for pts, style, label in curves:
        ax.plot(*pts.T, label=label, **style)
    centre = curves[0][0].mean(axis=0)
    for cam, view in zip(first.cameras_ct, first.views, strict=True):
        src = cam.source_world
        ray = centre - src
        det = src + ray / np.linalg.norm(ray) * (np.linalg.norm(ray) + 150.0)
        ax.plot(*np.stack([src + 0.6 * ray, det]).T, color="tab:purple", lw=1)
        ax.scatter(*det, s=25, c="tab:purple", marker="s")
        ax.text(*det, f" detector {view.name}", fontsize=7, color="tab:purple")
    lim = 120.0
    ax.set_xlim(centre[0] - lim, centre[0] + lim)
    ax.set_ylim(centre[1] - lim, centre[1] + lim)
    ax.set_zlim(centre[2] - lim, centre[2] + lim)
    ax.set_xlabel("x (mm, L)")
    ax.set_ylabel("y (mm, P)")
    ax.set_zlabel("z (mm, S)")
    ax.legend(loc="upper left", fontsize=7)
    ax.view_init(elev=18, azim=-60)
    ax.set_title("CT frame (LPS): anatomy, CM, plan and C-arm views", fontsize=10)
    return figure_png(fig, dpi=90)


def _convergence_figure(result: NavigationResult) -> bytes:
    runs: list[tuple[str, Any]] = []
    for reg, tag in ((result.first, ""), (result.verification, " (verification)")):
        if reg is None:
            continue
        runs += [(f"pelvis {v.name}", p.trace) for v, p in zip(reg.views, reg.pelvis, strict=True)]
        runs += [(f"femur{tag}", reg.femur.trace), (f"CM{tag}", reg.cm.trace)]
    fig, axes = _pyplot().subplots(1, len(runs), figsize=(3.0 * len(runs), 3.0), squeeze=False)
    for ax, (label, trace) in zip(axes[0], runs, strict=True):
        offset = 0
        for lv in trace.levels:
            ev = [offset + it.n_evals for it in lv.iterations]
            ax.plot(ev, [it.best_cost for it in lv.iterations], lw=1, label=lv.name or f"level {lv.index}")
            offset = ev[-1] if ev else offset
        ax.set_title(label, fontsize=8)
        ax.set_xlabel("evaluations", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6)
    axes[0][0].set_ylabel("best cost per generation", fontsize=8)
    fig.tight_layout()
    return figure_png(fig)


def _timing_figure(timings_s: Mapping[str, float]) -> bytes:
    names = list(timings_s)
    secs = [timings_s[s] for s in names]
    fig, ax = _pyplot().subplots(figsize=(7, 0.6 + 0.25 * len(names)))
    ax.barh(names[::-1], secs[::-1], color="tab:blue")
    ax.set_xlabel("seconds")
    ax.set_title(f"time per stage (total {sum(secs):.0f} s)", fontsize=10)
    fig.tight_layout()
    return figure_png(fig)


def navigation_figures(
    result: NavigationResult,
    case: NavigationCase,
    *,
    timings_s: Mapping[str, float],
    true_landmarks_px: Sequence[np.ndarray] | None = None,
    true_ct_from_cm: Mapping[str, np.ndarray] | None = None,
) -> list[tuple[str, str, bytes]]:
    """(section, caption, PNG) for every picture whose material the run produced."""
    makers: list[tuple[str, str, Any]] = []
    first, ver = result.first, result.verification
    if first is not None:
        makers += [
            (
                "Detection",
                "mask, centreline and landmarks per view",
                lambda: _detection_figure(first, true_landmarks_px),
            ),
            (
                "Overlays",
                "CM registration, all views",
                lambda: _cm_overlay_figure(
                    first, "CM registration: edges of the registered CM DRR (green) on the ROI"
                ),
            ),
            ("Overlays", "femur registration, all views", lambda: _femur_overlay_figure(first, case)),
            (
                "3D scene",
                "anatomy, CM, plan and C-arm views (CT frame)",
                lambda: _scene_figure(result, case, true_ct_from_cm),
            ),
            (
                "Convergence",
                "best cost per CMA-ES generation of every registration",
                lambda: _convergence_figure(result),
            ),
        ]
    if ver is not None:
        makers.insert(
            3,
            (
                "Overlays",
                "verification: the CM after the move",
                lambda: _cm_overlay_figure(ver, "Verification: registered CM after the move"),
            ),
        )
    out: list[tuple[str, str, bytes]] = []
    for section, caption, make in makers:
        try:
            out.append((section, caption, make()))
        except Exception:  # a picture must not cost the run its report
            log.exception("figure %r failed", caption)
    out.append(("Timings", "seconds per stage", _timing_figure(timings_s)))
    return out


def _banner(result: NavigationResult) -> str:
    warnings = "".join(
        "<div style='background:#fff3e0;border:2px solid #ef6c00;padding:.5em 1em;margin-top:.4em'>"
        f"<b>Warning</b>: {html.escape(w)}</div>"
        for w in (result.warnings if result.status == "ok" else [])
    )
    return _status_banner(result) + warnings


def _status_banner(result: NavigationResult) -> str:
    if result.status == "ok" and not result.verified:
        return (
            "<div style='background:#fff8e1;border:2px solid #f9a825;padding:.6em 1em;font-size:1.1em'>"
            "<b>Status: ok, UNVERIFIED</b>: every stage passed its checks, but no images were taken "
            "after the move; a wrong hand-eye matrix or a robot that moved wrongly cannot be seen "
            "before then. Take verification images after the move.</div>"
        )
    if result.status == "ok":
        return (
            "<div style='background:#e6f4ea;border:2px solid #2e7d32;padding:.6em 1em;font-size:1.1em'>"
            "<b>Status: ok</b>: every stage passed its checks, and the move was verified on images "
            "taken after it; the robot commands below may be sent.</div>"
        )
    return (
        "<div style='background:#fdecea;border:3px solid #c62828;padding:.6em 1em;font-size:1.15em;"
        f"color:#b71c1c'><b>REFUSED</b>: {html.escape(result.reason)}<br>No robot command was given "
        "from this run. Take new images or register by hand before moving the robot.</div>"
    )


def _stage_rows(result: NavigationResult) -> list[list[Any]]:
    rows = []
    for name, rec in result.stages.items():
        d = rec.diagnostics
        keys = [
            k
            for k in ("views_detected", "cost", "converged", "init_cost_px", "roll_deg", "joint_motion_deg")
            if k in d
        ]
        rows.append(
            [name, rec.seconds, "yes" if rec.passed else "NO", ", ".join(f"{k} {d[k]}" for k in keys)]
        )
    return rows


def _motion_rows(result: NavigationResult) -> list[list[Any]]:
    """Per measured command: its joint motion and the CM tip's swept path (also when refused)."""
    rows = []
    for name, label in (("robot", "first move"), ("correct", "correction")):
        d = result.stages[name].diagnostics if name in result.stages else {}
        if "swept_path_mm" not in d:
            continue
        rows.append(
            [
                label,
                round(float(d["joint_motion_deg"]), 2),
                ", ".join(f"{v:.1f}" for v in d["joint_motion_per_joint_deg"]),
                round(float(d["tip_move_mm"]), 2),
                round(float(d["rotation_deg"]), 2),
                round(float(d["swept_path_mm"]), 2),
                round(float(d["swept_max_deviation_mm"]), 2),
            ]
        )
    return rows


def write_report(
    result: NavigationResult,
    case: NavigationCase,
    out: Path,
    *,
    title: str = "fluoronav navigate",
    description: str = "",
    timings_s: Mapping[str, float] | None = None,
    error_rows: Sequence[Sequence[Any]] = (),
    true_landmarks_px: Sequence[np.ndarray] | None = None,
    true_ct_from_cm: Mapping[str, np.ndarray] | None = None,
) -> Path:
    """Write ``out/report.html`` (self-contained: figures embedded).

    Args:
        result, case: the navigation and its case.
        title, description: the page's heading and a summary paragraph.
        timings_s: seconds per stage (default: the pipeline's stages).
        error_rows: (label, value, unit, paper) rows of errors against a known truth (simulations).
        true_landmarks_px, true_ct_from_cm: the truth to draw beside the estimates (simulations).
    """
    timings = dict(timings_s) if timings_s is not None else {k: v.seconds for k, v in result.stages.items()}
    summary = Section("Summary", paragraphs=[description] if description else [])
    summary.banner_html = _banner(result)
    summary.tables.append((["stage", "seconds", "checks passed", "diagnostics"], _stage_rows(result)))
    if result.status == "ok" and result.joints_target_deg is not None:
        cmd = [["first move", *np.round(result.joints_target_deg, 3).tolist()]]
        if result.joints_correction_deg is not None:
            cmd.append(["correction", *np.round(result.joints_correction_deg, 3).tolist()])
        summary.tables.append(
            (["robot command (joints, deg)", *[f"q{i + 1}" for i in range(len(cmd[0]) - 1)]], cmd)
        )
    motion = _motion_rows(result)
    if motion:
        header = [
            "command motion",
            "largest joint turn (deg)",
            "per joint (deg)",
            "CM tip moves (mm)",
            "CM turns (deg)",
            "tip's swept path (mm)",
            "path's largest deviation from straight (mm)",
        ]
        summary.tables.append((header, motion))
    if error_rows:
        summary.tables.append(
            (["error against the truth", "value", "unit", "paper"], [list(r) for r in error_rows])
        )
    sections = [summary]
    by_section: dict[str, Section] = {}
    for name, caption, png in navigation_figures(
        result, case, timings_s=timings, true_landmarks_px=true_landmarks_px, true_ct_from_cm=true_ct_from_cm
    ):
        if name not in by_section:
            by_section[name] = Section(name)
            sections.append(by_section[name])
        by_section[name].figures.append((caption, png))
    page = html_page(
        title, sections, subtitle=f"fluoronav {__version__}; navigation.json holds every number on this page."
    )
    out.mkdir(parents=True, exist_ok=True)
    path = out / "report.html"
    path.write_text(page, encoding="utf-8")
    return path
