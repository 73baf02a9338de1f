"""ArticulatedSimulator's memory savings: the femur's mask held in its box (exact) and the ``rest``
body's uint16 densities (the float32 images up to the quantisation)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from fluoronav.simulation.articulated import ArticulatedSimulator, _BoxMask, femur_in_box, split_femur

#: a quantised simulator's largest image difference to the float32 one, relative to the image's maximum
REL_TOL = 1e-4


def _whole_volume_split(vol, side: str, dilate_voxels: int) -> tuple[np.ndarray, tuple[slice, ...]]:
    """The femur's mask and box computed on the whole volume (the reference)."""
    femur = vol.labels == vol.label_value(f"femur_{side}")
    mask = femur
    if dilate_voxels > 0:
        other = (vol.labels > 0) & ~femur
        mask = ndimage.binary_dilation(femur, iterations=dilate_voxels) & ~other
    idx = np.argwhere(mask)
    lo = np.maximum(idx.min(0) - 1, 0)
    hi = np.minimum(idx.max(0) + 2, mask.shape)
    return mask, tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))


@pytest.mark.parametrize("side", ["left", "right"])
@pytest.mark.parametrize("dilate_voxels", [0, 1, 3])
def test_femur_in_box_equals_the_whole_volume_split(setup, side: str, dilate_voxels: int) -> None:
    vol = setup[0]
    mask, box = _whole_volume_split(vol, side, dilate_voxels)
    crop, got_box = femur_in_box(vol, side, dilate_voxels=dilate_voxels)
    assert got_box == box
    np.testing.assert_array_equal(crop, mask[box])
    assert not mask.sum() - mask[box].sum()  # nothing outside the box
    full, full_box = split_femur(vol, side, dilate_voxels=dilate_voxels)
    assert full_box == box
    np.testing.assert_array_equal(full, mask)


def test_box_mask_reads_as_the_whole_volume_mask(setup) -> None:
    vol = setup[0]
    mask, box = split_femur(vol, "left")
    held = _BoxMask(mask[box], box)
    rng = np.random.default_rng(0)
    shape = np.array(mask.shape)
    regions = [box, tuple(slice(0, int(n)) for n in shape), tuple(slice(0, 1) for _ in shape)]
    for _ in range(30):
        lo = rng.integers(0, shape)
        hi = np.minimum(lo + rng.integers(1, shape // 2 + 2), shape)
        regions.append(tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True)))
    for region in regions:
        np.testing.assert_array_equal(held[region], mask[region])


def test_quantised_rest_matches_the_float32_images(setup) -> None:
    """Noise-free images with a moved femur, the CM and its drilled path: within REL_TOL of the
    image's maximum; labels identical. The femur body stays float32."""
    vol, cfg, camera, world_from_cm, cp = setup
    plain = ArticulatedSimulator(vol, config=cfg)
    quantised = ArticulatedSimulator(vol, config=cfg, quantise=True)
    assert all(r.mu.dtype == torch.float32 for r in plain._rest.values())
    assert set(quantised._rest) == set(plain._rest)
    assert all(r.mu.dtype == torch.uint16 and r.scale is not None for r in quantised._rest.values())
    assert all(r.mu.dtype == torch.float32 for r in quantised._femur.values())
    wf = np.eye(4)
    wf[:3, 3] = [3.0, -2.0, 1.0]
    kw = {"world_from_patient": np.eye(4), "world_from_femur": wf, "cm": (world_from_cm, cp), "seed": 0}
    ref = plain.simulate(camera, **kw)
    img = quantised.simulate(camera, **kw)
    assert ref.mask.sum() > 20  # the CM is in the image, so the comparison covers the drilling
    assert float(np.abs(img.image - ref.image).max()) <= REL_TOL * float(np.abs(ref.image).max())
    np.testing.assert_array_equal(img.mask, ref.mask)
    np.testing.assert_array_equal(img.landmarks_px, ref.landmarks_px)
    stored = plain.stored_camera(camera)
    d_ref = plain.areal_densities(camera, world_from_patient=np.eye(4), world_from_femur=wf, stored=stored)
    d_q = quantised.areal_densities(camera, world_from_patient=np.eye(4), world_from_femur=wf, stored=stored)
    for m, v in d_ref.items():
        assert float((d_q[m] - v).abs().max()) <= REL_TOL * float(v.abs().max())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_quantise_keeps_cuda_float32(setup) -> None:
    vol, cfg = setup[:2]
    sim = ArticulatedSimulator(vol, config=cfg, device="cuda", quantise=True)
    assert all(r.mu.dtype == torch.float32 and r.mu.device.type == "cuda" for r in sim._rest.values())
