"""``report.html`` of ``fluoronav demo``: one self-contained page with the pictures and the numbers.

Sections: errors against the truth (beside the paper's figures), per-stage timings, detection per
view, Fig. 12-style overlays (edges of the registered CM DRR on the image, and of the registered
femur on the whole view), a 3D picture of the scene (pelvis, femur, CM estimated and true, the plan,
C-arm sources and detectors, the robot), and the convergence of every registration.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from fluoronav.navigation.demo import STAGES, DemoResult
from fluoronav.studies.report import Section, figure_png, html_page

log = logging.getLogger(__name__)

__all__ = ["demo_figures", "write_report"]

#: (label, key in DemoResult.errors, unit, the paper's figure for comparison or "")
ERROR_ROWS = (
    (
        "CM landmark detection (mean of A, B over the views)",
        "landmark_mm_at_detector",
        "mm at detector",
        "0.449",
    ),
    ("pelvis rotation (mean over views)", "pelvis_rotation_deg", "deg", ""),
    ("pelvis centre (mean over views)", "pelvis_center_mm", "mm", ""),
    ("femur rotation", "femur_rotation_deg", "deg", ""),
    ("femur entry point", "femur_entry_mm", "mm", ""),
    ("CM tip after centreline initialisation", "cm_init_tip_mm", "mm", ""),
    ("CM tip (multi-view registration)", "cm_tip_mm", "mm", "0.59 (multi-view)"),
    ("CM base translation", "cm_base_translation_mm", "mm", "0.52"),
    ("CM base rotation", "cm_base_rotation_deg", "deg", "1.38"),
    ("CM notch rotation (mean)", "cm_notch_rotation_deg", "deg", "0.22"),
    ("repositioning: true tip to plan", "reposition_tip_mm", "mm", "2.86 ± 0.80 (cadaver)"),
    ("repositioning: CM axis to plan", "reposition_axis_deg", "deg", ""),
    ("verification: registered tip error", "verify_tip_error_mm", "mm", "0.59 (multi-view)"),
    ("verification: registered tip to plan (what the images say)", "verify_tip_to_plan_mm", "mm", ""),
    ("after one corrective move: true tip to plan", "corrected_tip_mm", "mm", "2.86 ± 0.80 (cadaver)"),
    ("after one corrective move: CM axis to plan", "corrected_axis_deg", "deg", ""),
)


def _gray(ax: Any, img: np.ndarray, extent: Any = None) -> None:
    lo, hi = np.percentile(img, [1, 99.5])
    ax.imshow(img, cmap="gray", vmin=lo, vmax=hi, extent=extent, interpolation="nearest")
    ax.set_xticks([])
    ax.set_yticks([])


def _edges(img: np.ndarray, frac: float = 0.2) -> np.ndarray:
    """Thin (Canny) edges of a DRR, thresholds relative to its strongest gradient."""
    from skimage.feature import canny

    img = np.asarray(img, dtype=np.float64)
    top = float(np.ptp(img))
    if top <= 0:
        return np.zeros(img.shape, bool)
    return canny(img / top, sigma=1.0, low_threshold=0.5 * frac * 0.25, high_threshold=frac * 0.25)


def _box(points: np.ndarray, shape: tuple[int, int], margin: float) -> tuple[int, int, int, int]:
    lo = np.floor(points.min(axis=0) - margin).astype(int)
    hi = np.ceil(points.max(axis=0) + margin).astype(int)
    c0, r0 = max(lo[0], 0), max(lo[1], 0)
    c1, r1 = min(hi[0], shape[1]), min(hi[1], shape[0])
    return r0, r1, c0, c1


def _detection_figure(result: DemoResult) -> bytes:
    import matplotlib.pyplot as plt

    A = result.artifacts
    images, dets, names = A["images"], A["detections"], A["names"]
    fig, axes = plt.subplots(1, len(images), figsize=(4.2 * len(images), 4.2))
    for ax, sim, det, name in zip(np.atleast_1d(axes), images, dets, names, strict=True):
        if det is None:
            vv, uu = np.nonzero(sim.mask)
            pts = np.stack([uu, vv], axis=1).astype(float)
            r0, r1, c0, c1 = _box(pts, sim.image.shape, 25.0)
            _gray(ax, sim.image[r0:r1, c0:c1], extent=(c0 - 0.5, c1 - 0.5, r1 - 0.5, r0 - 0.5))
            ax.set_title(f"{name}: no CM detected", fontsize=9)
            continue
        vv, uu = np.nonzero(det["mask"]) if det["mask"].any() else np.nonzero(sim.mask)
        pts = np.stack([uu, vv], axis=1).astype(float)
        r0, r1, c0, c1 = _box(pts, sim.image.shape, 25.0)
        _gray(ax, sim.image[r0:r1, c0:c1], extent=(c0 - 0.5, c1 - 0.5, r1 - 0.5, r0 - 0.5))
        ax.contour(
            np.arange(c0, c1),
            np.arange(r0, r1),
            det["mask"][r0:r1, c0:c1],
            [0.5],
            colors="yellow",
            linewidths=0.7,
        )
        cl = det["centerline_px"]
        ax.plot(cl[:, 0], cl[:, 1], "-", color="cyan", lw=1)
        lm, lt = det["landmarks_px"], sim.landmarks_px
        ax.plot(lt[:, 0], lt[:, 1], "o", mfc="none", mec="lime", ms=9, label="true A, B")
        ax.plot(lm[:, 0], lm[:, 1], "+", color="red", ms=10, mew=1.5, label="detected A, B")
        for (u, v), t in zip(lm, "AB", strict=True):
            ax.annotate(t, (u, v), xytext=(5, -5), textcoords="offset points", color="red")
        err = np.linalg.norm(lm - lt, axis=1)
        ax.set_title(f"{name}: A {err[0]:.2f} px, B {err[1]:.2f} px", fontsize=9)
    np.atleast_1d(axes)[0].legend(loc="lower left", fontsize=7)
    fig.suptitle("Detection: mask (yellow), centreline (cyan), landmarks", fontsize=10)
    return figure_png(fig)


def _cm_overlay_figure(reg: Any, title: str) -> bytes:
    """Fig. 12 style: edges of the registered CM DRR (green) on the ROI image."""
    import matplotlib.pyplot as plt

    k = len(reg.view_names)
    fig, axes = plt.subplots(1, k, figsize=(4.2 * k, 4.4))
    for ax, name, img, drr in zip(
        np.atleast_1d(axes), reg.view_names, reg.roi_images, reg.roi_drrs, strict=True
    ):
        lo, hi = np.percentile(img, [1, 99.5])
        rgb = np.repeat(np.clip((img - lo) / max(hi - lo, 1e-9), 0, 1)[..., None], 3, axis=-1)
        rgb[_edges(drr)] = (0.1, 1.0, 0.1)
        ax.imshow(rgb, interpolation="nearest")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(name, fontsize=9)
    fig.suptitle(title, fontsize=10)
    return figure_png(fig)


def _femur_overlay_figure(result: DemoResult) -> bytes:
    """Edges of the femur DRR at the registered pose (green) on each whole view."""
    import matplotlib.pyplot as plt
    import torch

    from fluoronav.registration.bone import bone_excess_mu
    from fluoronav.rendering.ct import render_line_integrals

    A = result.artifacts
    volume, images, cams_ct, names = A["volume"], A["images"], A["cams_ct"], A["names"]
    side = A["scene"].trial.side
    mu, w_idx = bone_excess_mu(volume, [f"femur_{side}"])
    size = 256
    fig, axes = plt.subplots(1, len(images), figsize=(4.2 * len(images), 4.4))
    for ax, sim, cam, name in zip(np.atleast_1d(axes), images, cams_ct, names, strict=True):
        f = max(1, sim.camera.cols // size)
        small = cam.downsample(f)
        T = (small.camera_from_world @ A["ct_from_femur"])[None]
        drr = (
            render_line_integrals(torch.from_numpy(mu), w_idx, small.K[None], T, small.rows, small.cols)[0]
            .cpu()
            .numpy()
        )
        img = (
            sim.image[: small.rows * f, : small.cols * f]
            .reshape(small.rows, f, small.cols, f)
            .mean(axis=(1, 3))
        )
        lo, hi = np.percentile(img, [1, 99.5])
        rgb = np.repeat(np.clip((img - lo) / max(hi - lo, 1e-9), 0, 1)[..., None], 3, axis=-1)
        rgb[_edges(drr, 0.15)] = (0.1, 1.0, 0.1)
        ax.imshow(rgb, interpolation="nearest")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(name, fontsize=9)
    fig.suptitle("Femur registration: edges of the registered femur DRR (green)", fontsize=10)
    return figure_png(fig)


def _surface_points(volume: Any, label: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """Up to n world points on the boundary of a label (for a light 3D picture)."""
    from scipy import ndimage

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


def _scene_figure(result: DemoResult) -> bytes:
    """3D: pelvis and femur (true pose), CM true / estimated / after the move, plan, C-arm, robot."""
    import matplotlib.pyplot as plt
    import torch

    A = result.artifacts
    sc, kin, volume = A["scene"], A["kin"], A["volume"]
    tr = sc.trial
    rng = np.random.default_rng(0)
    fig = plt.figure(figsize=(11, 8.5))
    ax = fig.add_subplot(111, projection="3d")

    def h(T: np.ndarray, p: np.ndarray) -> np.ndarray:
        return p @ T[:3, :3].T + T[:3, 3]

    pel = h(tr.world_from_patient, _surface_points(volume, "pelvis", 2500, rng))
    fem = h(tr.world_from_femur, _surface_points(volume, f"femur_{tr.side}", 1500, rng))
    ax.scatter(*pel.T, s=0.6, c="#888888", alpha=0.5, label="pelvis")
    ax.scatter(*fem.T, s=0.4, c="#d9a066", alpha=0.5, label="femur")
    cp = torch.as_tensor(sc.control_points_deg, dtype=torch.float64)
    axis_cm = kin.centerline_cm(cp, n_points=40, to_z_mm=kin.config.tip_z_mm).numpy()
    W_true = A["W_regi"]
    # the estimate in the world frame: through the true AP camera and the estimated C-arm frame
    cam0_true = A["images"][0].camera.camera_from_world
    world_from_ct_est = np.linalg.inv(cam0_true) @ A["cams_ct"][0].camera_from_world
    reg = A["cm"]
    cp_est = torch.as_tensor(reg.control_points_deg, dtype=torch.float64)
    axis_est = kin.centerline_cm(cp_est, n_points=40, to_z_mm=kin.config.tip_z_mm).numpy()
    W_est = world_from_ct_est @ reg.world_from_cm[0]
    for pts, style, label in (
        (h(W_true, axis_cm), dict(color="k", lw=4), "CM (true)"),
        (h(W_est, axis_est), dict(color="tab:red", lw=1.5, ls="--"), "CM (registered)"),
        (h(A["W_after"], axis_cm), dict(color="tab:blue", lw=3), "CM after the move (true)"),
        *(
            [(h(A["W_final"], axis_cm), dict(color="tab:cyan", lw=3), "CM after the correction (true)")]
            if "W_final" in A
            else []
        ),
        (h(A["W_plan_true"], axis_est), dict(color="tab:green", lw=1.5, ls="--"), "plan"),
    ):
        ax.plot(*pts.T, label=label, **style)
    entry = h(tr.world_from_femur, tr.entry_ct)
    ax.scatter(*entry, s=40, c="tab:green", marker="x")
    # C-arm: source, detector centre and the central ray (shortened) per view
    centre = h(W_true, axis_cm).mean(axis=0)
    for cam, name in zip(A["cams_full"], A["names"], strict=True):
        src = cam.source_world
        ray = centre - src
        det = src + ray / np.linalg.norm(ray) * (np.linalg.norm(ray) + 150.0)
        start = src + 0.6 * ray
        ax.plot(*np.stack([start, det]).T, color="tab:purple", lw=1)
        ax.scatter(*det, s=25, c="tab:purple", marker="s")
        ax.text(*det, f" detector {name}", fontsize=7, color="tab:purple")
    # robot: joint origins of the true arm at the registration configuration (base far away: clip)
    Wb = sc.world_from_rbase
    frames = sc.true_robot.rbase_from_links(A["q_regi_actual"])
    joints = np.concatenate([[Wb[:3, 3]], h(Wb, frames[:, :3, 3])])
    flange = joints[-1]
    near = np.linalg.norm(joints - centre, axis=1) < 350.0
    if near.any():
        ax.plot(*joints[near].T, "-o", color="tab:gray", lw=2, ms=3, label="robot (joints within 350 mm)")
    ax.plot(*np.stack([flange, h(W_true, np.zeros(3))]).T, color="tab:gray", lw=1, ls=":")
    lim = 120.0
    ax.set_xlim(centre[0] - lim, centre[0] + lim)
    ax.set_ylim(centre[1] - lim, centre[1] + lim)
    ax.set_zlim(centre[2] - lim, centre[2] + lim)
    ax.set_xlabel("x (mm, L)")
    ax.set_ylabel("y (mm, P)")
    ax.set_zlabel("z (mm, S)")
    ax.legend(loc="upper left", fontsize=7)
    ax.view_init(elev=18, azim=-60)
    ax.set_title("Scene (world frame, LPS): anatomy, CM, plan, C-arm views and robot", fontsize=10)
    return figure_png(fig, dpi=90)


def _convergence_figure(result: DemoResult) -> bytes:
    import matplotlib.pyplot as plt

    A = result.artifacts
    runs: list[tuple[str, Any]] = [
        (f"pelvis ({n})", p.trace) for n, p in zip(A["names"], A.get("pelvis", []), strict=False)
    ]
    for key, label in (("femur", "femur"), ("cm", "CM multi-view"), ("verify", "CM verification")):
        if key in A:
            runs.append((label, A[key].trace))
    fig, axes = plt.subplots(1, len(runs), figsize=(3.3 * len(runs), 3.0), squeeze=False)
    for ax, (label, trace) in zip(axes[0], runs, strict=True):
        offset = 0
        for lv in trace.levels:
            ev = [offset + it.n_evals for it in lv.iterations]
            ax.plot(ev, [it.best_cost for it in lv.iterations], lw=1, label=lv.name or f"level {lv.index}")
            offset = ev[-1] if ev else offset
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("evaluations", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6)
    axes[0][0].set_ylabel("best cost per generation", fontsize=8)
    fig.tight_layout()
    return figure_png(fig)


def _timing_figure(result: DemoResult) -> bytes:
    import matplotlib.pyplot as plt

    names = [s for s in STAGES if s in result.timings_s]
    secs = [result.timings_s[s] for s in names]
    fig, ax = plt.subplots(figsize=(7, 3))
    ax.barh(names[::-1], secs[::-1], color="tab:blue")
    ax.set_xlabel("seconds")
    ax.set_title(f"time per stage (total {sum(secs):.0f} s)", fontsize=10)
    fig.tight_layout()
    return figure_png(fig)


def demo_figures(result: DemoResult) -> list[tuple[str, str, bytes]]:
    """(section, caption, PNG) for every picture whose material the run produced."""
    A = result.artifacts
    out: list[tuple[str, str, bytes]] = []
    makers = [
        ("Detection", "mask, centreline and landmarks per view", "detections", _detection_figure),
        (
            "Overlays",
            "CM registration, all views",
            "cm",
            lambda r: _cm_overlay_figure(
                r.artifacts["cm"], "CM registration: edges of the registered CM DRR (green) on the ROI"
            ),
        ),
        ("Overlays", "femur registration, all views", "ct_from_femur", _femur_overlay_figure),
        (
            "Overlays",
            "verification image after the move",
            "verify",
            lambda r: _cm_overlay_figure(r.artifacts["verify"], "Verification: registered CM after the move"),
        ),
        (
            "3D scene",
            "anatomy, CM (true, registered, moved), plan, C-arm and robot",
            "W_after",
            _scene_figure,
        ),
        ("Convergence", "best cost per CMA-ES generation of every registration", "cm", _convergence_figure),
    ]
    for section, caption, need, make in makers:
        if need not in A:
            continue
        try:
            out.append((section, caption, make(result)))
        except Exception:  # a picture must not cost the run its report
            log.exception("figure %r failed", caption)
    out.append(("Timings", "seconds per stage", _timing_figure(result)))
    return out


def write_report(result: DemoResult, out: Path) -> Path:
    """Write ``out/report.html`` (self-contained: figures embedded)."""
    from fluoronav import __version__

    cfg = result.config
    E, T = result.errors, result.timings_s
    rows = [[label, E[key], unit, paper] for label, key, unit, paper in ERROR_ROWS if key in E]
    status = "completed" if result.status == "ok" else f"FAILED: {result.reason}"
    sections = [
        Section(
            "Summary",
            paragraphs=[
                f"Run {status}. Simulated navigation on the built-in hip phantom (seed {cfg.seed}); "
                f"three physics-simulated C-arm views at {cfg.image_size}² (the 1536² CIOS Fusion "
                "detector binned), detector → pelvis → femur → centreline initialisation → multi-view CM "
                "registration → plan → robot command (eqs. 7–8, UR-10 with joint and calibration errors, "
                f"hand-eye error {cfg.handeye_error_deg}° / {cfg.handeye_error_mm} mm) → move → a new "
                "image and its registration. Errors are against the simulated truth; the paper's figures "
                "are its simulation means (Table I / text) and cadaver repositioning.",
            ],
            tables=[
                (["error", "value", "unit", "paper"], rows),
                (["stage", "seconds"], [[s, T[s]] for s in STAGES if s in T] + [["total", sum(T.values())]]),
            ],
        )
    ]
    by_section: dict[str, Section] = {}
    for name, caption, png in demo_figures(result):
        if name not in by_section:
            by_section[name] = Section(name)
            sections.append(by_section[name])
        by_section[name].figures.append((caption, png))
    page = html_page(
        "fluoronav demo: simulated fluoroscopic navigation",
        sections,
        subtitle=f"fluoronav {__version__}; results.json holds every number on this page.",
    )
    out.mkdir(parents=True, exist_ok=True)
    path = out / "report.html"
    path.write_text(page, encoding="utf-8")
    return path
