"""The figures behind ``PreflightConfig.min_bone_contrast`` and ``mirror_margin`` (label_fit) on the
hip phantom: per spacing and seed, the labels as built, grown by 1–2 voxels or shrunk by 1,
mirrored left–right, the CT mirrored against them, shifted 5 mm (the best of ±x, ±y, ±z), the next
seed's, and the femur label turned 1°–10° about its head. Prints each label's robust contrast, the
worst of pelvis and femur_left, the mirrored map's gain and the finding; per seed the angle between
the left femur and the mirrored right one (from landmarks), the largest balls and median HU.

Run::

    python tools/label_fit_figures.py --spacing 2.5 1.0 --seeds 0 1 2 3 5 170 133 216 40 206
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.navigation.checks.label_fit import (
    BoneFit,
    bone_fit,
    check_label_fit,
    label_depth_mm,
    mirrored_labels,
    sample_ct,
)
from fluoronav.navigation.checks.preflight_config import PreflightConfig

NAMES = ("pelvis", "femur_left", "femur_right")
CHECKED = ("pelvis", "femur_left")
FEMUR_MARKS = ("femoral_head", "greater_trochanter", "lesser_trochanter")


def _scores(volume: Volume, cfg: PreflightConfig) -> tuple[float, str]:
    """One line's figures: each label's contrast, the worst checked one, the mirror's gain, the check."""
    s = sample_ct(volume, cfg.contrast_voxel_mm)
    m = mirrored_labels(volume, s)
    fits, mirrored = {}, {}
    for n in NAMES:
        v = volume.label_value(n) or 0
        fits[n] = bone_fit(s.hu, s.labels, v) or BoneFit(0.0, 0.0)
        mirrored[n] = bone_fit(s.hu, m, v) or BoneFit(0.0, 0.0)
    worst = min(fits[n].contrast for n in CHECKED)
    gain = min(mirrored[n].mean_contrast for n in CHECKED) - min(fits[n].mean_contrast for n in CHECKED)
    found = check_label_fit(volume, "left", cfg)
    text = "  ".join(f"{fits[n].contrast:5.2f}" for n in NAMES)
    return worst, text + f"   | {worst:5.2f}  {gain:+5.2f}  {found[0].check if found else '-'}"


def _line(what: str, figures: tuple[float, str]) -> str:
    return f"  {what:38s} {figures[1]}"


def _mirror_angle_deg(volume: Volume) -> float:
    """The rotation between the left femur's landmarks and the mirrored right femur's, degrees."""
    lm = volume.landmarks_world
    left = np.stack([lm[f"{m}_left"] for m in FEMUR_MARKS])
    right = np.stack([lm[f"{m}_right"] for m in FEMUR_MARKS]) * np.array([-1.0, 1.0, 1.0])
    a, b = left - left.mean(0), right - right.mean(0)
    u, _, vt = np.linalg.svd(b.T @ a)
    R = (u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt).T
    return float(np.degrees(Rotation.from_matrix(R).magnitude()))


def _shifted(labels: np.ndarray, mm: float, spacing: float, axis: int, sign: int) -> np.ndarray:
    n = round(mm / spacing) * sign
    out = np.zeros_like(labels)
    src = [slice(None)] * 3
    dst = [slice(None)] * 3
    src[axis] = slice(max(0, -n), labels.shape[axis] - max(0, n))
    dst[axis] = slice(max(0, n), labels.shape[axis] - max(0, -n))
    out[tuple(dst)] = labels[tuple(src)]
    return out


def _femur_turned(volume: Volume, deg: float) -> np.ndarray:
    """The label map with ``femur_left`` turned by ``deg`` about the AP axis through its head centre
    (an abduction: a femur posed otherwise than the CT's; the phantom's grid is axis-aligned)."""
    assert volume.labels is not None
    value = volume.label_value("femur_left") or 0
    head = volume.index_from_world @ np.append(volume.landmarks_world["femoral_head_left"], 1.0)
    centre = head[:3][::-1]  # (k, j, i)
    R = Rotation.from_rotvec(np.radians(deg) * np.array([0.0, 1.0, 0.0])).as_matrix()[::-1, ::-1]
    mask = (volume.labels == value).astype(np.uint8)
    turned = ndimage.affine_transform(mask, R.T, offset=centre - R.T @ centre, order=0) > 0
    out = np.where(volume.labels == value, 0, volume.labels)
    out[turned & (out == 0)] = value
    return out


def _grown(volume: Volume, voxels: int) -> np.ndarray:
    """The label map with every label grown (``voxels`` > 0, into the background) or shrunk by
    ``voxels`` of the CT: a segmentation drawn generously or tightly."""
    assert volume.labels is not None
    out = volume.labels.copy()
    for value in volume.label_names:
        mask = volume.labels == value
        if voxels > 0:
            out[ndimage.binary_dilation(mask, iterations=voxels) & (out == 0)] = value
        else:
            out[mask & ~ndimage.binary_erosion(mask, iterations=-voxels)] = 0
    return out


def run(spacing: float, seed: int, cfg: PreflightConfig) -> None:
    v = hip_phantom(seed=seed, spacing_mm=spacing)
    other = hip_phantom(seed=seed + 1, spacing_mm=spacing)
    s = sample_ct(v, cfg.contrast_voxel_mm)
    depth = {n: label_depth_mm(s, v.label_value(n) or 0) for n in CHECKED}
    hu = {n: float(np.median(s.hu[s.labels == v.label_value(n)])) for n in CHECKED}
    print(
        f"spacing {spacing:g} mm, seed {seed}: mirrored right femur {_mirror_angle_deg(v):.1f}° from the "
        f"left; largest ball {', '.join(f'{n} {d:.1f} mm' for n, d in depth.items() if d is not None)}; "
        f"median HU {', '.join(f'{n} {h:.0f}' for n, h in hu.items())}"
    )
    head = "  ".join(f"{n:>5s}" for n in ("pelv", "fem_l", "fem_r"))
    print(f"  {'':38s} {head}   | worst  mirror  finding")
    print(_line("correct", _scores(v, cfg)))
    assert v.labels is not None
    for n in (1, 2, -1):
        what = f"labels {'grown' if n > 0 else 'shrunk'} by {abs(n)} voxel{'s' if abs(n) > 1 else ''}"
        print(_line(what, _scores(v.replace(labels=_grown(v, n)), cfg)))
    print(_line("labels mirrored", _scores(v.replace(labels=v.labels[:, :, ::-1].copy()), cfg)))
    print(_line("CT mirrored", _scores(v.replace(data=v.data[:, :, ::-1].copy()), cfg)))
    shifts = []
    for axis, name in ((2, "x"), (1, "y"), (0, "z")):
        for sign in (-1, 1):
            sc = _scores(v.replace(labels=_shifted(v.labels, 5.0, spacing, axis, sign)), cfg)
            shifts.append((sc[0], f"shifted 5 mm ({'+' if sign > 0 else '-'}{name})", sc))
    _, what, sc = max(shifts, key=lambda t: t[0])
    print(_line(f"{what}, the best of 6", sc))
    for deg in (1.0, 2.0, 5.0, 10.0):
        print(
            _line(
                f"femur_left turned {deg:g}° about its head",
                _scores(v.replace(labels=_femur_turned(v, deg)), cfg),
            )
        )
    print(_line(f"labels of seed {seed + 1}", _scores(v.replace(labels=other.labels), cfg)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spacing", type=float, nargs="+", default=[2.5, 1.0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    args = parser.parse_args()
    cfg = PreflightConfig()
    for spacing in args.spacing:
        for seed in args.seeds:
            run(spacing, seed, cfg)


if __name__ == "__main__":
    main()
