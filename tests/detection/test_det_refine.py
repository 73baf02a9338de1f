"""Landmark refinement stage: patch geometry, direction, prior decoding, detector use, training."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from det_synthetic import first_tiny_model, tiny_config, with_settings

from fluoronav.detection.config import DetectorConfig
from fluoronav.detection.decoder import add_center_prior, decode_refine_logits
from fluoronav.detection.detector import Detector
from fluoronav.detection.model import DetectorNet
from fluoronav.detection.patches import RefinePatch, landmark_direction, refine_patch
from fluoronav.detection.training.dataset import RefineDataset
from fluoronav.detection.training.train import TrainConfig, sidecar_path, train


def test_patch_frame_maps_hand_computed_points_and_round_trips() -> None:
    f = RefinePatch(np.array([10.0, 20.0]), np.array([0.0, 1.0]), 0.5, (4, 6))
    # moved 3 patch px along t = +v: 1.5 input px
    g = f.shifted(3.0)
    np.testing.assert_allclose(g.center_px, [10.0, 21.5], atol=1e-12)
    assert g.tangent is f.tangent and g.step_px == f.step_px and g.shape == f.shape
    # patch (col 0, row 0): 2.5 patch px back along t = +v, 1.5 px along −n; n = (−1, 0)
    np.testing.assert_allclose(f.to_input(np.array([0.0, 0.0])), [10.75, 18.75], atol=1e-12)
    np.testing.assert_allclose(f.to_input(np.array([2.5, 1.5])), [10.0, 20.0], atol=1e-12)  # the centre
    q = np.random.default_rng(0).uniform(-3, 9, size=(7, 2))
    np.testing.assert_allclose(f.from_input(f.to_input(q)), q, atol=1e-12)


def test_patch_samples_a_ramp_and_mirrors_exactly_about_the_axis() -> None:
    vv, uu = np.mgrid[0:64, 0:64].astype(np.float64)
    ramp = 2.0 * uu + 3.0 * vv
    f = RefinePatch(np.array([30.2, 25.7]), np.array([0.6, 0.8]), 0.5, (8, 16))
    jj, kk = np.mgrid[0:8, 0:16].astype(np.float64)
    uv = f.to_input(np.stack([kk, jj], axis=-1))
    expect = 2.0 * uv[..., 0] + 3.0 * uv[..., 1]
    expect = (expect - expect.mean()) / expect.std()
    np.testing.assert_allclose(f.sample(ramp), expect, atol=1e-4)
    # row j and row rows − 1 − j are mirror images about the tube's axis (the line through c along t)
    a, b = uv, uv[::-1]
    mid, diff = (a + b) / 2 - f.center_px, b - a
    np.testing.assert_allclose(mid[..., 0] * f.tangent[1] - mid[..., 1] * f.tangent[0], 0.0, atol=1e-12)
    np.testing.assert_allclose(diff @ f.tangent, 0.0, atol=1e-12)


def test_direction_points_from_the_landmark_into_the_mask() -> None:
    mask = np.zeros((64, 128), bool)
    mask[28:33, 40:110] = True
    d = landmark_direction(mask, np.array([40.0, 30.0]), ring_px=(4.0, 16.0))
    assert d is not None
    np.testing.assert_allclose(d, [1.0, 0.0], atol=1e-6)
    d = landmark_direction(mask, np.array([109.0, 30.0]), ring_px=(4.0, 16.0))
    np.testing.assert_allclose(d, [-1.0, 0.0], atol=1e-6)
    assert landmark_direction(mask, np.array([5.0, 5.0]), ring_px=(4.0, 16.0)) is None
    assert refine_patch(mask, np.array([5.0, 5.0]), step_px=0.5, shape=(8, 16)) is None


def _gauss_logp(rows: int, cols: int, peaks: list[tuple[float, float, float]], sigma: float) -> torch.Tensor:
    """log of a mixture of Gaussians (col, row, weight), (1, 1, rows, cols)."""
    v, u = np.mgrid[0:rows, 0:cols].astype(np.float64)
    p = sum(w * np.exp(-((u - cu) ** 2 + (v - cr) ** 2) / (2 * sigma**2)) for cu, cr, w in peaks)
    return torch.from_numpy(np.log(p + 1e-30))[None, None].float()


def test_decoding_recovers_a_sub_pixel_peak_and_the_prior_picks_the_near_mode() -> None:
    rows, cols = 48, 80
    centre = ((cols - 1) / 2.0, (rows - 1) / 2.0)
    logits = _gauss_logp(rows, cols, [(30.3, 20.6, 1.0)], 1.5)
    pts, conf = decode_refine_logits(logits, sigma_px=1.5, prior_px=0.0)
    np.testing.assert_allclose(pts[0].numpy(), [30.3, 20.6], atol=0.02)
    assert 0.8 < float(conf[0]) <= 1.0
    # two modes: the far one (the tube's end, 20 patch px away) is a little stronger
    near = (centre[0] + 2.0, centre[1], 1.0)
    far = (centre[0] + 20.0, centre[1], 1.3)
    logits = _gauss_logp(rows, cols, [near, far], 1.5)
    p0, _ = decode_refine_logits(logits, sigma_px=1.5, prior_px=0.0)
    p3, _ = decode_refine_logits(logits, sigma_px=1.5, prior_px=3.0)
    assert abs(float(p0[0, 0]) - far[0]) < 0.1
    assert abs(float(p3[0, 0]) - near[0]) < 0.5  # pulled towards the centre by ≤ σ²/(σ²+s²)·2 px
    # the prior is a Gaussian at the centre: 0 there, −r²/(2s²) elsewhere
    z = add_center_prior(torch.zeros(1, 1, 3, 5), sigma_px=2.0)
    assert float(z[0, 0, 1, 2]) == 0.0 and float(z[0, 0, 0, 0]) == pytest.approx(-(4 + 1) / 8.0)
    # or at a given (col, row) per patch
    z = add_center_prior(
        torch.zeros(2, 1, 3, 5), sigma_px=2.0, center_px=torch.tensor([[1.0, 2.0], [4.0, 0.0]])
    )
    assert float(z[0, 0, 2, 1]) == 0.0 and float(z[1, 0, 0, 4]) == 0.0
    assert float(z[0, 0, 0, 0]) == pytest.approx(-(1 + 4) / 8.0)
    assert float(z[1, 0, 2, 0]) == pytest.approx(-(16 + 4) / 8.0)
    # a prior away from the centre picks the mode near it: here the far one
    pf, _ = decode_refine_logits(
        logits, sigma_px=1.5, prior_px=3.0, prior_center_px=torch.tensor([[far[0] - 1.0, far[1]]])
    )
    assert abs(float(pf[0, 0]) - far[0]) < 0.5


class _DotOracle(torch.nn.Module):
    """Refinement 'network' whose logits are the patch itself (sharpened): it finds the brightest spot."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([8.0 * x, 8.0 * x], dim=1)


def _tube_scene(true_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    vv, uu = np.mgrid[0:96, 0:160].astype(np.float64)
    mask = (np.abs(vv - true_px[1]) <= 3) & (uu >= true_px[0]) & (uu <= true_px[0] + 60)
    image = 0.2 * mask + 3.0 * np.exp(-((uu - true_px[0]) ** 2 + (vv - true_px[1]) ** 2) / (2 * 1.0**2))
    return image.astype(np.float32), mask


#: a detector small enough to build in a test; its refinement stage is replaced by :class:`_DotOracle`
_VIEW = {"network": {"channels": (4, 8)}, "sampler": {"size": 32}}
ORACLE_CFG = with_settings(
    DetectorConfig(),
    add=("refine",),
    coarse=_VIEW,
    fine=_VIEW,
    refine={"network": {"channels": (4, 8)}, "sampler": {"shape": (16, 32)}, "decoder": {"prior_px": 3.0}},
)


def oracle_detector(config: DetectorConfig = ORACLE_CFG) -> Detector:
    """A detector whose refinement network is :class:`_DotOracle`."""
    net = DetectorNet(config)
    net.refine = _DotOracle()
    return Detector(net, device="cpu")


def test_detector_refines_landmarks_towards_what_the_patch_shows() -> None:
    det = oracle_detector()
    assert det.refine is not None
    true = np.array([50.3, 40.6])
    image, mask = _tube_scene(true)
    start = np.array([true + np.array([2.0, 0.4]), [150.0, 40.0]])  # A 2 px off along the tube
    mask_b = mask.copy()
    mask_b[:, 105:] = False  # B is 46 px beyond the mask's end: no direction, kept as it is
    out = det.refine(image, start, mask_b, pixel_spacing_mm=0.582)
    assert np.linalg.norm(out[0] - true) < 0.35 < np.linalg.norm(start[0] - true)
    np.testing.assert_array_equal(out[1], start[1])
    # a model without a refinement stage: its last steps keep the fine landmarks
    plain = Detector(DetectorNet(tiny_config()), device="cpu")
    assert plain.net.refine is None and plain.refine is None
    np.testing.assert_array_equal(plain.finish(image, mask_b, start).landmarks_px, start)


def test_detector_averages_patches_moved_along_the_tube_with_the_prior_at_the_landmark() -> None:
    true = np.array([50.3, 40.6])
    image, mask = _tube_scene(true)
    start = np.array([true + np.array([1.0, 0.3]), [150.0, 40.0]])
    one = oracle_detector()
    moved = oracle_detector(with_settings(ORACLE_CFG, refine={"sampler": {"shifts_px": (-4.0, 0.0, 4.0)}}))
    assert one.refine is not None and moved.refine is not None
    a, b = one.refine(image, start, mask), moved.refine(image, start, mask)
    # every moved patch still shows the dot where it is: the same point, mapped back from each
    assert np.linalg.norm(b[0] - true) < 0.35 and np.linalg.norm(b[0] - a[0]) < 0.1
    np.testing.assert_array_equal(b[1], start[1])
    # a second dot as bright 6 input px into the tube: a patch moved 10 patch px (5 input px) towards
    # it is centred near it, but the prior stays at the fine landmark, so the true dot is still taken
    vv, uu = np.mgrid[0 : image.shape[0], 0 : image.shape[1]].astype(np.float64)
    decoy = true + np.array([6.0, 0.0])
    image2 = image + 3.0 * np.exp(-((uu - decoy[0]) ** 2 + (vv - decoy[1]) ** 2) / 2.0).astype(np.float32)
    far = oracle_detector(with_settings(ORACLE_CFG, refine={"sampler": {"shifts_px": (10.0,)}}))
    assert far.refine is not None
    c = far.refine(image2, start, mask)
    assert np.linalg.norm(c[0] - true) < 0.5


def test_refine_settings_are_validated_and_round_trip() -> None:
    with pytest.raises(ValueError, match="tta"):
        with_settings(ORACLE_CFG, refine={"tta": 3})
    with pytest.raises(ValueError, match="shape"):
        with_settings(
            ORACLE_CFG, refine={"network": {"channels": (4, 8, 16)}, "sampler": {"shape": (10, 16)}}
        )
    with pytest.raises(ValueError, match="prior_px"):
        with_settings(ORACLE_CFG, refine={"decoder": {"prior_px": -1.0}})
    for bad in ((), (0.0, 20.0)):
        with pytest.raises(ValueError, match="shifts_px"):
            with_settings(ORACLE_CFG, refine={"sampler": {"shifts_px": bad}})
    cfg = with_settings(
        ORACLE_CFG, refine={"network": {"channels": (8, 16)}, "sampler": {"shifts_px": (-2.0, 0.0, 2.0)}}
    )
    assert DetectorConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert DetectorConfig().refine is None  # not run unless listed


TINY = tiny_config()


def test_training_the_refinement_stage_adds_it_and_leaves_the_others(tmp_path: Path) -> None:
    data, cfg, first, w0 = first_tiny_model(tmp_path, TINY)
    assert Detector.load(first, device="cpu").net.refine is None

    out = tmp_path / "refined.pt"
    m = train(
        data,
        out,
        config=dataclasses.replace(cfg, stages=("refine",), refine_repeats=2),
        init=first,
        progress=False,
    )
    assert np.isfinite(m["val_landmark_px"]) and np.isfinite(m["val_start_px"])
    det = Detector.load(out, device="cpu")
    assert det.net.refine is not None and det.config.refine is not None
    assert det.config.refine.network.channels == (16, 32, 64, 128)
    w1 = torch.load(out, weights_only=True)["state_dict"]
    assert all(torch.equal(w0[k], w1[k]) for k in w0)  # coarse and fine untouched
    assert any(k.startswith("refine.") for k in w1)
    assert json.loads(sidecar_path(out).read_text())["train"]["augmentation"]["along_sigma_px"] == 4.0
    # items: both landmarks' patches, targets near the centre, NaN on negatives
    ds = RefineDataset(data, config=det.config, split="all", repeats=2, seed=0)
    assert len(ds) == 2 * 8
    targets = np.stack([ds[i]["refine_landmarks"].numpy() for i in range(len(ds))])
    pos = np.isfinite(targets).all(axis=-1)
    assert pos.any() and (~pos).any()
    assert ds[0]["refine_image"].shape == (2, 1, 48, 80)
    with pytest.raises(ValueError, match="refine"):
        TrainConfig(stages=("refine", "fine"))
