"""Synthetic stand-ins for simulated CM images, for the detection tests only.

A curved ribbon (an arc of a tube) with periodic notches lies on a smooth noisy background; a solid
"base" continues beyond landmark A (outside the mask) so that A and B can be told apart, as on the
real CM. Landmarks sit on the ribbon's axis at its two ends.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy import ndimage

from fluoronav.detection.config import STAGE_ORDER, DetectorConfig
from fluoronav.detection.training.train import TrainConfig, train


def with_settings(config: DetectorConfig, *, add: tuple[str, ...] = (), **updates: Any) -> DetectorConfig:
    """``config`` with stages ``add`` listed and its settings updated: each keyword a top-level
    setting, dicts merged into the settings there (``fine={"passes": {"tta": 2}}``)."""

    def merge(old: Any, new: Any) -> Any:
        if isinstance(old, dict) and isinstance(new, dict):
            return {**old, **{k: merge(old.get(k), v) for k, v in new.items()}}
        return new

    data = merge(config.to_dict(), updates)
    data["stages"] = [s for s in STAGE_ORDER if s in data["stages"] or s in add]
    return DetectorConfig.model_validate(data)


def tiny_config(size: int = 32, **updates: Any) -> DetectorConfig:
    """A small model's configuration: coarse and fine U-Nets of channels (4, 8, 16) at ``size``²."""
    view = {"network": {"channels": (4, 8, 16)}, "sampler": {"size": size}}
    return with_settings(with_settings(DetectorConfig(), coarse=view, fine=view), **updates)


def arc_polar(shape: tuple[int, int], centre: np.ndarray, mid_angle: float) -> tuple[np.ndarray, np.ndarray]:
    """Radius and angle (relative to ``mid_angle``, in (−π, π]) of every pixel about ``centre`` (u, v)."""
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    du, dv = u - centre[0], v - centre[1]
    r = np.hypot(du, dv)
    ang = np.angle(np.exp(1j * (np.arctan2(dv, du) - mid_angle)))
    return r, ang


def arc_mask(
    shape: tuple[int, int],
    centre: np.ndarray,
    radius: float,
    theta0: float,
    theta1: float,
    width: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Mask of a tube arc (axis radius ``radius``, angles theta0 → theta1 rad) and its landmarks (2, 2)."""
    mid = 0.5 * (theta0 + theta1)
    r, ang = arc_polar(shape, centre, mid)
    half = 0.5 * abs(theta1 - theta0)
    mask = (np.abs(r - radius) <= width / 2) & (np.abs(ang) <= half)
    lm = np.array([centre + radius * np.array([np.cos(t), np.sin(t)]) for t in (theta0, theta1)])
    return mask, lm


def make_sample(rng: np.random.Generator, size: int = 128, *, positive: bool = True) -> dict:
    """One synthetic image (size × size float32, bright = attenuating), mask (uint8), landmarks (2, 2)."""
    bg = ndimage.gaussian_filter(rng.standard_normal((size, size)), size / 8) * (size / 8) * 0.8
    v, u = np.mgrid[0:size, 0:size] / size
    image = 1.0 + bg + 0.3 * (rng.uniform(-1, 1) * u + rng.uniform(-1, 1) * v)
    mask = np.zeros((size, size), dtype=bool)
    landmarks = None
    if positive:
        width = rng.uniform(0.07, 0.1) * size
        radius = rng.uniform(0.5, 1.5) * size
        length = rng.uniform(0.35, 0.55) * size
        span = length / radius
        theta0 = rng.uniform(-np.pi, np.pi)
        theta1 = theta0 + span * rng.choice([-1.0, 1.0])
        mid_pt = rng.uniform(0.35, 0.65, size=2) * size
        mid = 0.5 * (theta0 + theta1)
        centre = mid_pt - radius * np.array([np.cos(mid), np.sin(mid)])
        mask, landmarks = arc_mask((size, size), centre, radius, theta0, theta1, width)
        r, ang = arc_polar((size, size), centre, mid)
        s = ang * radius * np.sign(theta1 - theta0)  # arc length from the middle, towards B
        notch = (np.sin(2 * np.pi * s / (0.06 * size)) > 0.3) & ((r - radius) * np.sign(theta1 - theta0) > 0)
        ribbon = mask.astype(np.float64) * np.where(notch, 0.35, 1.0)
        base_len = 0.12 * size
        base = (np.abs(r - radius) <= width / 2) & (s < -length / 2) & (s > -length / 2 - base_len)
        image = image + 0.8 * ndimage.gaussian_filter(ribbon + 1.3 * base, 0.7)
    image = image + rng.normal(0.0, 0.03, size=(size, size))
    return {
        "image": image.astype(np.float32),
        "mask": mask.astype(np.uint8),
        "landmarks_px": None if landmarks is None else landmarks.astype(np.float64),
    }


def write_dataset(root: Path, n: int, *, size: int = 128, seed: int = 0, negative_every: int = 0) -> Path:
    """Write ``n`` samples in the ``simulate`` data set format (manifest.jsonl + .npz) under ``root``."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    with open(root / "manifest.jsonl", "w") as fh:
        for i in range(n):
            positive = not (negative_every and i % negative_every == negative_every - 1)
            sample = make_sample(rng, size, positive=positive)
            name = f"s{i:05d}.npz"
            lm = sample["landmarks_px"]
            arrays = {"image": sample["image"], "mask": sample["mask"]}
            if lm is not None:
                arrays["landmarks_px"] = lm
            np.savez_compressed(root / name, **arrays)
            fh.write(
                json.dumps(
                    {
                        "id": f"s{i:05d}",
                        "file": name,
                        "rows": size,
                        "cols": size,
                        "pixel_spacing_mm": 0.5,
                        "landmarks_px": None if lm is None else lm.tolist(),
                        "control_points_deg": [0.0] * 5,
                        "camera": None,
                        "world_from_cm": None,
                        "ct": "synthetic",
                    }
                )
                + "\n"
            )
    return root


def first_tiny_model(
    tmp_path: Path, model_config: DetectorConfig
) -> tuple[Path, TrainConfig, Path, dict[str, torch.Tensor]]:
    """The common start of the stage-training tests: a set of 8 synthetic 128² images (2 negatives),
    two-step training settings, a ``model_config`` model trained with them (coarse and fine stages)
    and that model's weights: (data, settings, model file, state dict)."""
    data = write_dataset(tmp_path / "data", 8, size=128, seed=5, negative_every=4)
    cfg = TrainConfig(epochs=1, batch_size=2, max_steps_per_epoch=2, device="cpu", val_fraction=0.3, seed=1)
    first = tmp_path / "first.pt"
    train(data, first, config=cfg, model_config=model_config, progress=False)
    return data, cfg, first, torch.load(first, weights_only=True)["state_dict"]
