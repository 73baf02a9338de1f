"""Draw docs/figures/conventions.png: world (LPS), C-arm camera, detector pixels and the CM frame.

Run: python tools/make_conventions_figure.py
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch

from fluoronav.geometry import carm_camera
from fluoronav.manipulator import CMKinematics


def _arrow(ax, origin, vec, color, label):  # type: ignore[no-untyped-def]
    ax.quiver(*origin, *vec, color=color, arrow_length_ratio=0.15, linewidth=2)
    ax.text(*(origin + vec * 1.12), label, color=color, fontsize=9)


def main() -> None:
    fig = plt.figure(figsize=(15, 6.5))
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    cam = carm_camera(lao_rao_deg=25.0, cran_caud_deg=90.0, source_to_isocenter_mm=450.0)
    o = np.zeros(3)
    for i, (name, c) in enumerate(zip(("x: Left", "y: Posterior", "z: Superior"), "rgb", strict=True)):
        _arrow(ax, o, np.eye(3)[i] * 150, c, name)
    ax.text(-60, 0, -90, "world (LPS) = CT frame", fontsize=9)
    src = cam.source_world
    R = cam.world_from_camera[:3, :3]
    for i, (name, c) in enumerate(
        zip(("x_cam: +cols", "y_cam: +rows", "z_cam: to detector"), "rgb", strict=True)
    ):
        _arrow(ax, src, R[:, i] * (150 if i < 2 else 300), c, name)
    ax.scatter(*src, color="k", s=40)
    ax.text(*src + np.array([0, 40, -120]), "X-ray source = camera origin", fontsize=9)
    # detector outline at SDD
    c, r = cam.cols - 1, cam.rows - 1
    corners_uv = np.array([[0, 0], [c, 0], [c, r], [0, r], [0, 0]])
    det = cam.backproject(corners_uv, 1020.0)
    ax.plot(det[:, 0], det[:, 1], det[:, 2], "k-")
    first = cam.backproject(np.array([[0.0, 0.0]]), 1020.0)[0]
    ax.scatter(*first, color="m", s=30)
    ax.text(*first, "  pixel (u,v)=(0,0)", color="m", fontsize=8)
    for p in (src, first):
        ax.plot([src[0], p[0]], [src[1], p[1]], [src[2], p[2]], "k:", linewidth=0.6)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_title("C-arm camera (OpenCV pinhole), LAO/RAO 25°, CRAN/CAUD 90°")
    ax.view_init(elev=18, azim=-35)
    ax.set_box_aspect((1, 1.6, 1))

    ax2 = fig.add_subplot(1, 2, 2)
    kin = CMKinematics()
    for cp, style in ((torch.zeros(5), "k--"), (torch.full((5,), 4.0), "b-")):
        line = kin.centerline_cm(
            cp.double(), n_points=100, from_z_mm=-kin.config.base_length_mm, to_z_mm=kin.config.tip_z_mm
        ).numpy()
        ax2.plot(line[:, 2], line[:, 1], style, linewidth=1.5)
        lm = kin.landmarks_cm(cp.double()).numpy()
        tip = kin.tip_cm(cp.double()).numpy()
        ax2.plot(lm[:, 2], lm[:, 1], "ro")
        ax2.plot(tip[2], tip[1], "gs")
    ax2.annotate("A (origin)", (0, 0), textcoords="offset points", xytext=(-10, 10))
    ax2.annotate(
        "B: distal plane of last notch",
        (kin.config.distal_notch_plane_mm, 0),
        textcoords="offset points",
        xytext=(-60, 12),
    )
    ax2.annotate("tip", (kin.config.tip_z_mm, 0), textcoords="offset points", xytext=(4, 4))
    ax2.arrow(0, -26, 8, 0, head_width=0.8, color="b")
    ax2.text(9, -26, "+z (axis)", color="b")
    ax2.arrow(0, -26, 0, 6, head_width=0.8, color="g")
    ax2.text(0.5, -19, "+y", color="g")
    ax2.text(-3, -29, "x out of the page (joint axis)", fontsize=8)
    ax2.set_aspect("equal")
    ax2.set_xlabel("z (mm)")
    ax2.set_ylabel("y (mm)")
    ax2.set_title("CM base frame: straight (dashed) and all control points 4° (blue)")
    out = Path(__file__).resolve().parents[1] / "docs" / "figures" / "conventions.png"
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(out)


if __name__ == "__main__":
    main()
