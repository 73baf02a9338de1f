"""Detector API: the pipeline's coordinate handling, negatives, model files and image loaders."""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
import SimpleITK as sitk  # noqa: N813
import torch
from det_synthetic import tiny_config, with_settings
from scipy import ndimage
from torch import nn

import fluoronav.detection.model as model_module
from fluoronav.detection import decoder, runtime
from fluoronav.detection.checks import Finished
from fluoronav.detection.config import DetectorConfig
from fluoronav.detection.detector import Detection, Detector, load_image, truncated_landmarks, write_detection
from fluoronav.detection.localize import FineResult
from fluoronav.detection.model import (
    DetectorNet,
    PackedConvolution,
    fold_batch_norm,
    pack_for_cpu,
    save_model,
)
from fluoronav.detection.patches import patch_grid_px
from fluoronav.detection.views import View, scaled_view
from fluoronav.errors import FluoronavError, InputError

#: the intensity oracle below draws peak-1 heatmaps
_GAUSSIAN = {"decoder": {"heatmap": "gaussian"}}
TINY = tiny_config(64, accept={"min_confidence": 0.2}, coarse=_GAUSSIAN, fine=_GAUSSIAN)


def tiny(**updates: object) -> DetectorConfig:
    """:data:`TINY` with settings updated (:func:`~det_synthetic.with_settings`)."""
    return with_settings(TINY, **updates)  # type: ignore[arg-type]


def oracle_net(config: DetectorConfig = TINY) -> DetectorNet:
    """A model whose coarse and fine stages are :class:`IntensityOracle`s."""
    net = DetectorNet(config)
    net.coarse, net.fine = IntensityOracle(), IntensityOracle()
    return net


def tta_mean(net: nn.Module, views: np.ndarray, tta: int) -> torch.Tensor:
    """A view network's outputs on views (N, S, S) averaged over ``tta`` dihedral transforms."""
    x = torch.from_numpy(views)[:, None]
    with torch.no_grad():
        outs = [
            runtime.dihedral_inverse(net(runtime.dihedral(x, k, f)), k, f) for k, f in runtime.DIHEDRAL[:tta]
        ]
    return torch.stack(outs).mean(0)


def empty_net(config: DetectorConfig = TINY) -> DetectorNet:
    """An untrained net whose last layer is zeroed, with a seg bias of −10: its mask is always empty."""
    torch.manual_seed(0)
    net = DetectorNet(config)
    for stage in (net.coarse, net.fine):
        last = [m for m in stage.modules() if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d))][-1]
        assert last.out_channels == 3
        with torch.no_grad():
            last.weight.zero_()
            last.bias.copy_(torch.tensor([-10.0, 0.0, 0.0]))
    return net


class IntensityOracle(nn.Module):
    """Stands in for a trained stage on a drawn test image: CM where the normalised intensity is > 0.5,
    heatmap A where it is far above the bar (a bright marker), heatmap B where it is far below 0."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        seg = 40.0 * (x - 0.5)
        ha = ((x - 1.3) / 3.0).clamp(0.0, 1.0)
        hb = ((-x - 0.2) / 3.0).clamp(0.0, 1.0)
        return torch.cat([seg, ha, hb], dim=1)


def drawn_cm(rows: int = 200, cols: int = 260) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A bar from A to B (value 1, 12 px thick) with a bright square at A and a dark one at B."""
    a, b = np.array([60.0, 70.0]), np.array([190.0, 130.0])
    img = np.zeros((rows, cols), np.float32)
    cv2.line(img, (60, 70), (190, 130), 1.0, thickness=12)
    bar = img > 0.5
    img[68:73, 58:63] = 4.0
    img[128:133, 188:193] = -3.0
    return img, bar, np.stack([a, b])


def test_pipeline_maps_landmarks_mask_and_centerline_to_input_pixels() -> None:
    net = oracle_net()
    det = Detector(net, device="cpu").detect(drawn_cm()[0], pixel_spacing_mm=0.2)
    img, bar, lm = drawn_cm()
    assert det.found
    assert det.mask.shape == img.shape and det.mask.dtype == bool
    np.testing.assert_allclose(det.landmarks_px, lm, atol=2.0)
    assert np.all((det.landmark_confidence > 0.2) & (det.landmark_confidence <= 1.0))
    inter = np.logical_and(det.mask, bar).sum()
    assert 2 * inter / (det.mask.sum() + bar.sum()) > 0.85
    cl = det.centerline_px
    (
        np.testing.assert_allclose(cl[0], det.landmarks_px[0]),
        np.testing.assert_allclose(cl[-1], det.landmarks_px[1]),
    )
    # the centreline runs along the bar's axis
    d = lm[1] - lm[0]
    n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
    assert np.max(np.abs((cl - lm[0]) @ n)) < 2.0
    assert det.pixel_spacing_mm == 0.2


@pytest.mark.parametrize("tta", [1, 2, 4, 8])
def test_dihedral_tta_maps_every_transform_back(tta: int) -> None:
    # a pointwise stage is exactly equivariant: averaging over transforms mapped back changes nothing
    img = drawn_cm()[0]
    net = oracle_net()
    ref = Detector(net, device="cpu").detect(img)
    first = {1: 8, 2: 4, 4: 2, 8: 1}[tta]  # the passes before the last with another number
    net_tta = oracle_net(tiny(fine={"passes": {"tta": tta, "first_tta": first}}))
    res = Detector(net_tta, device="cpu").detect(img)
    np.testing.assert_allclose(res.landmarks_px, ref.landmarks_px, atol=1e-4)
    np.testing.assert_array_equal(res.mask, ref.mask)
    x = torch.arange(2 * 5 * 5, dtype=torch.float32).reshape(2, 1, 5, 5)
    outs = {tuple(runtime.dihedral(x, k, f).flatten().tolist()) for k, f in runtime.DIHEDRAL}
    assert len(outs) == 8  # eight distinct transforms
    for k, f in runtime.DIHEDRAL:
        torch.testing.assert_close(runtime.dihedral_inverse(runtime.dihedral(x, k, f), k, f), x)


@pytest.mark.parametrize(("sure_confidence", "last_tta"), [(0.0, 2), (1.01, None)])
def test_sure_first_pass_sets_the_last_pass_tta(sure_confidence: float, last_tta: int | None) -> None:
    # passes.sure_tta applies to the last pass only, and only after a pass sure of both landmarks:
    # with the bound at 0 every pass is sure, above 1 none is (the last pass then takes passes.tta)
    img = drawn_cm()[0]
    cfg = tiny(fine={"passes": {"tta": 8, "sure_tta": 2, "sure_confidence": sure_confidence}})
    det = Detector(oracle_net(cfg), device="cpu")
    calls: list[tuple[int, int | None]] = []
    fine_views = det.fine.views

    def spy(image: np.ndarray, views: list, *, tta: int | None = None, **kw: object) -> tuple:
        calls.append((len(views), tta))
        return fine_views(image, views, tta=tta, **kw)  # type: ignore[arg-type]

    det.fine.views = spy  # type: ignore[method-assign]
    res = det.detect(img)
    assert res.found
    first, last = calls[0], calls[1]
    assert first == (1, 8)  # the first pass: one view, passes.tta (first_tta unset)
    assert last == (len(cfg.fine.sampler.scales), last_tta)
    with pytest.raises(ValueError, match="sure_tta"):
        tiny(fine={"passes": {"sure_tta": 3}})
    assert DetectorConfig().fine.passes.sure_tta is None  # unless set: passes.tta always
    with pytest.raises(ValueError, match="sure_confidence"):
        tiny(fine={"passes": {"sure_confidence": float("nan")}})


def test_fine_scales_map_every_scaled_view_back() -> None:
    # an equivariant stage run on ROIs 0.8×–1.25× the size (other pixel grids and sizes) must give
    # the single-scale landmarks and mask: a scaled view mapped back with the wrong window would not
    img = drawn_cm()[0]
    results = []
    for scales in ((1.0,), (0.8, 1.0, 1.25), (0.9, 1.12)):
        net = oracle_net(tiny(fine={"sampler": {"scales": scales}}))
        results.append(Detector(net, device="cpu").detect(img))
    ref = results[0]
    for res in results[1:]:
        assert res.found
        # the oracle's markers are 5 px squares: their argmax may move by a pixel between grids
        np.testing.assert_allclose(res.landmarks_px, ref.landmarks_px, atol=1.5)
        assert 2 * np.logical_and(res.mask, ref.mask).sum() / (res.mask.sum() + ref.mask.sum()) > 0.97


class NearSightedOracle(nn.Module):
    """A coarse stage that sees only the left ``frac`` of its view (a CM found only in part)."""

    def __init__(self, frac: float) -> None:
        super().__init__()
        self.frac = frac

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        keep = torch.zeros_like(x)
        keep[..., : int(x.shape[-1] * self.frac)] = 1.0
        return IntensityOracle()(x * keep)


def _dice(a: np.ndarray, b: np.ndarray) -> float:
    return float(2 * np.logical_and(a, b).sum() / (a.sum() + b.sum()))


def test_extra_passes_grow_the_roi_until_the_cm_fits() -> None:
    # the coarse stage finds only the bar's left end (A); the fine stage's mask then reaches the edge
    # of its ROI, and only with spare passes does the ROI grow to hold the whole bar and B
    img, bar, lm = drawn_cm()
    results = {}
    for max_passes in (0, 6):
        net = DetectorNet(tiny(fine={"passes": {"max_passes": max_passes}}))
        net.coarse, net.fine = NearSightedOracle(0.45), IntensityOracle()
        results[max_passes] = Detector(net, device="cpu").detect(img)
    cut, grown = results[0], results[6]
    assert not cut.found and cut.landmark_confidence[1] < 0.2 and _dice(cut.mask, bar) < 0.8  # B unseen
    assert grown.found and _dice(grown.mask, bar) > 0.9
    np.testing.assert_allclose(grown.landmarks_px, lm, atol=2.0)
    # a CM that fits its first ROI takes no extra pass: the same result as without spare passes
    net = oracle_net(tiny(fine={"passes": {"max_passes": 6}}))
    ref_net = oracle_net()
    same, ref = Detector(net, device="cpu").detect(img), Detector(ref_net, device="cpu").detect(img)
    np.testing.assert_array_equal(same.landmarks_px, ref.landmarks_px)
    np.testing.assert_array_equal(same.mask, ref.mask)


def test_reaches_edge_counts_only_edges_inside_the_image() -> None:
    view = View(x0=-20, y0=10, side=40, size=40)  # 20 px hang over the left edge
    shape = (100, 100)
    inner = np.zeros((40, 40), bool)
    inner[10:30, 10:30] = True
    assert not decoder.reaches_edge(inner, view, shape)
    right = inner.copy()
    right[15:20, 30:] = True  # the view's right edge lies inside the image
    assert decoder.reaches_edge(right, view, shape)
    left = inner.copy()
    left[15:20, :10] = True  # its left edge is outside the image: the CM may end at the image's edge
    assert not decoder.reaches_edge(left, view, shape)


def test_scaled_view_keeps_the_centre() -> None:
    v = View(x0=-13, y0=40, side=101, size=64)
    for f in (0.8, 1.0, 1.25, 2.0):
        s = scaled_view(v, f)
        assert s.size == v.size and abs(s.side - f * v.side) <= 0.5
        np.testing.assert_allclose(s.x0 + s.side / 2, v.x0 + v.side / 2, atol=0.5)
        np.testing.assert_allclose(s.y0 + s.side / 2, v.y0 + v.side / 2, atol=0.5)


def test_tta_setting_is_validated_and_the_extras_are_off_by_default() -> None:
    with pytest.raises(ValueError, match="first_tta"):
        tiny(fine={"passes": {"first_tta": 3}})
    default = DetectorConfig()
    assert default.fine.passes.first_tta is None  # unless set: every pass as passes.tta
    for bad in ((), (0.1,), (1.0, 5.0)):
        with pytest.raises(ValueError, match="scales"):
            tiny(fine={"sampler": {"scales": bad}})
    cfg = tiny(fine={"sampler": {"scales": (0.8, 1.0, 1.25)}})
    assert DetectorConfig.from_dict(cfg.to_dict()) == cfg
    assert default.fine.sampler.scales == (1.0,)  # one ROI scale
    assert default.fine.passes.max_passes == 0  # no extra passes
    with pytest.raises(ValueError, match="max_passes"):
        tiny(fine={"passes": {"max_passes": -1}})
    with pytest.raises(ValueError, match="tta"):
        tiny(fine={"passes": {"tta": 3}})
    assert default.fine.decoder.min_separation_px == 0.0  # no constraint unless set
    assert default.fine.decoder.join_frac == 0.0  # the largest component unless set
    with pytest.raises(ValueError, match="join_frac"):
        tiny(fine={"decoder": {"join_frac": -0.1}})
    for bad_sep in (-1.0, 128.0):
        with pytest.raises(ValueError, match="min_separation_px"):
            tiny(fine={"sampler": {"size": 128}, "decoder": {"min_separation_px": bad_sep}})
    assert default.fine.decoder.support_px == 0.0  # no constraint unless set
    for bad_support in (-1.0, 128.0):
        with pytest.raises(ValueError, match="support_px"):
            tiny(fine={"sampler": {"size": 128}, "decoder": {"support_px": bad_support}})


def test_blank_image_gives_no_detection() -> None:
    det = Detector(empty_net(), device="cpu")
    for image in (
        np.zeros((120, 90), np.float32),
        np.random.default_rng(0).normal(size=(64, 64)).astype(np.float32),
    ):
        res = det.detect(image)
        assert not res.found
        assert res.landmarks_px is None and res.centerline_px is None
        assert res.mask.shape == image.shape and not res.mask.any()
        assert np.all(res.landmark_confidence == 0.0)


@pytest.mark.parametrize(
    ("weak_mask_px", "weak_min_confidence", "found"),
    [
        (0, 0.15, False),  # off: a coarse mask under min_mask_px is no detection
        (200, 0.15, False),  # the mask (117 coarse px) is under weak_mask_px too
        (100, 0.15, True),  # weak, and the fine landmarks (0.90, 0.93) are sure enough
        (100, 0.95, False),  # weak, and they are not
    ],
)
def test_weak_coarse_mask_needs_sure_fine_landmarks(
    weak_mask_px: int, weak_min_confidence: float, found: bool
) -> None:
    img, _, lm = drawn_cm()
    config = tiny(
        coarse={"decoder": {"min_mask_px": 400, "weak_mask_px": weak_mask_px}},
        accept={"weak_min_confidence": weak_min_confidence},
    )
    det = Detector(oracle_net(config), device="cpu")
    _, logit, _, _ = det.coarse(img)
    assert int((logit > 0.0).sum()) == 117
    res = det.detect(img)
    assert res.found is found
    if found:
        np.testing.assert_allclose(res.landmarks_px, lm, atol=2.0)
    else:
        assert res.landmarks_px is None and res.centerline_px is None
    # a mask of min_mask_px or more needs only min_confidence
    sure = Detector(
        oracle_net(with_settings(config, coarse={"decoder": {"min_mask_px": 100, "weak_mask_px": 0}}))
    )
    assert sure.detect(img).found


@pytest.mark.parametrize(
    ("min_mask_mm2", "spacing_mm", "found"),
    [
        (0.0, 0.2, True),  # off
        (70.0, 0.2, True),  # the bar's mask, about 1,930 px, covers about 77 mm² at 0.2 mm
        (85.0, 0.2, False),
        (85.0, 0.25, True),  # the same pixels cover 121 mm² at 0.25 mm
        (600.0, None, True),  # no spacing given: 0.582 mm pixels are assumed (about 650 mm²)
        (700.0, None, False),
    ],
)
def test_a_mask_smaller_than_the_cms_end_on_disc_is_no_detection(
    min_mask_mm2: float, spacing_mm: float | None, found: bool
) -> None:
    img = drawn_cm()[0]
    net = oracle_net(tiny(accept={"min_mask_mm2": min_mask_mm2}))
    res = Detector(net, device="cpu").detect(img, pixel_spacing_mm=spacing_mm)
    assert 1880 <= res.mask.sum() <= 1980
    assert res.found is found
    assert (res.landmarks_px is None) is not found
    with pytest.raises(ValueError, match="min_mask_mm2"):
        tiny(accept={"min_mask_mm2": -1.0})


def test_weak_mask_settings_are_validated() -> None:
    with pytest.raises(ValueError, match="weak_mask_px"):
        tiny(coarse={"decoder": {"min_mask_px": 10, "weak_mask_px": 11}})
    with pytest.raises(ValueError, match="weak_min_confidence"):
        tiny(accept={"weak_min_confidence": 1.5})


def test_model_file_roundtrip_and_bad_files(tmp_path: Path) -> None:
    path = tmp_path / "m.pt"
    save_model(path, empty_net(), extra={})
    loaded = Detector.load(path, device="cpu")
    assert loaded.config == TINY and not loaded.detect(np.zeros((64, 64), np.float32)).found
    bad = tmp_path / "corrupt.pt"
    bad.write_bytes(b"not a torch file at all")
    with pytest.raises(InputError, match=r"corrupt\.pt"):
        Detector.load(bad)
    with pytest.raises(InputError, match="not found"):
        Detector.load(tmp_path / "missing.pt")
    blob = torch.load(path, weights_only=True)
    assert blob["format_version"] == 2 and blob["config"]["stages"] == ["coarse", "fine"]
    blob["config"]["coarse"]["network"]["channels"] = [8, 16, 32]  # weights no longer match
    torch.save(blob, tmp_path / "mismatch.pt")
    with pytest.raises(InputError, match="do not match"):
        Detector.load(tmp_path / "mismatch.pt")
    # a file of format 1 (the flat configuration) is refused, naming the converter
    flat = {"input_size": 64, "roi_size": 64, "channels": [4, 8, 16], "roi_channels": [4, 8, 16]}
    torch.save({**blob, "format_version": 1, "config": flat}, tmp_path / "flat.pt")
    with pytest.raises(InputError, match=r"format 1 .*convert_flat_detector\.py"):
        Detector.load(tmp_path / "flat.pt")


def test_missing_shipped_weights_say_how_to_train(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(model_module, "shipped_model_path", lambda: tmp_path / "detector.pt")
    with pytest.raises(FluoronavError, match="fluoronav train"):
        Detector.load()


def test_malformed_images_raise_input_errors(tmp_path: Path) -> None:
    det = Detector(empty_net(), device="cpu")
    with pytest.raises(InputError, match="2-D"):
        det.detect(np.zeros((3, 32, 32), np.float32))
    with pytest.raises(InputError, match="NaN"):
        det.detect(np.full((32, 32), np.nan, np.float32))
    np.savez(tmp_path / "noimg.npz", other=np.zeros((8, 8)))
    with pytest.raises(InputError, match="no 'image'"):
        load_image(tmp_path / "noimg.npz")
    (tmp_path / "junk.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(InputError, match=r"junk\.png"):
        load_image(tmp_path / "junk.png")
    (tmp_path / "junk.dcm").write_bytes(b"garbage")
    with pytest.raises(InputError, match=r"junk\.dcm"):
        load_image(tmp_path / "junk.dcm")


def test_image_loaders_orient_intensities(tmp_path: Path) -> None:
    raw = np.tile(np.linspace(100, 60000, 40), (30, 1)).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "raw.png"), raw)
    img, spacing = load_image(tmp_path / "raw.png")
    assert spacing is None and img.shape == (30, 40)
    np.testing.assert_allclose(img, -np.log((raw + 1.0) / 65536.0), rtol=1e-5)
    assert np.all(np.diff(img[0]) < 0)  # dark (attenuating) raw pixels become bright
    flt = np.random.default_rng(0).random((20, 24)).astype(np.float32)
    cv2.imwrite(str(tmp_path / "log.tiff"), flt)
    np.testing.assert_array_equal(load_image(tmp_path / "log.tiff")[0], flt)
    np.savez(tmp_path / "s.npz", image=flt, pixel_spacing_mm=np.float32(0.25))
    img, spacing = load_image(tmp_path / "s.npz")
    np.testing.assert_array_equal(img, flt)
    assert spacing == pytest.approx(0.25)
    dcm = sitk.GetImageFromArray(raw)
    dcm.SetMetaData("0018|1164", "0.194\\0.194")
    sitk.WriteImage(dcm, str(tmp_path / "x.dcm"))
    img, spacing = load_image(tmp_path / "x.dcm")
    np.testing.assert_allclose(img, raw.astype(np.float32))  # MONOCHROME2: bright stays bright
    assert spacing == pytest.approx(0.194)


def test_write_detection_files(tmp_path: Path) -> None:
    net = oracle_net()
    det = Detector(net, device="cpu").detect(drawn_cm()[0])
    path = write_detection(det, tmp_path / "out", "img")
    import json

    data = json.loads(path.read_text())
    assert data["found"] is True and data["mask"] == "img_mask.png"
    assert np.asarray(data["landmarks_px"]).shape == (2, 2)
    assert len(data["landmark_confidence"]) == 2 and np.asarray(data["centerline_px"]).shape[1] == 2
    assert data["landmark_truncated"] == [False, False]
    png = cv2.imread(str(tmp_path / "out" / "img_mask.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(png > 0, det.mask)


def test_truncated_landmarks_sit_where_the_mask_meets_the_border() -> None:
    mask = np.zeros((60, 80), bool)
    mask[20:30, 0:50] = True  # a bar cut by the left border
    assert truncated_landmarks(mask, np.array([[0.5, 25.0], [49.0, 25.0]])).tolist() == [True, False]
    # the same point, but the mask meets the border 20 px away from it
    assert truncated_landmarks(mask, np.array([[0.5, 50.0], [49.0, 25.0]])).tolist() == [False, False]
    # near the right, top and bottom borders, where the mask does not reach them
    assert not truncated_landmarks(mask, np.array([[79.0, 25.0], [40.0, 0.5]])).any()
    mask[20:60, 60:70] = True  # a second bar down to the bottom border
    assert truncated_landmarks(mask, np.array([[40.0, 25.0], [64.0, 58.5]])).tolist() == [False, True]


def test_a_cm_cut_by_the_image_border_is_found_and_not_usable() -> None:
    net = oracle_net()
    detector = Detector(net, device="cpu")
    img = drawn_cm()[0][:, 64:].copy()  # A (u = 60) is outside: the bar leaves by the left border
    img[72:78, 0:4] = 4.0  # the detector's A: where the bar leaves the image
    det = detector.detect(img)
    assert det.found and det.landmarks_px is not None
    assert det.landmarks_px[0, 0] < 3.0
    assert det.landmark_truncated.tolist() == [True, False]
    assert not det.usable and det.unusable_reason == "the CM leaves the image at landmark A"
    whole = detector.detect(drawn_cm()[0])
    assert whole.usable and whole.unusable_reason is None


@pytest.mark.parametrize(
    ("b_uv", "spacing_mm", "off"),
    [
        ((50.0, 30.0), 0.5, False),  # on the bar
        ((50.0, 36.0), 0.5, False),  # 5 px = 2.5 mm beside it: within 3 mm
        ((50.0, 38.0), 0.5, True),  # 7 px = 3.5 mm
        ((50.0, 36.0), None, False),  # 5 px × 0.582 mm = 2.91 mm
        ((50.0, 37.0), None, True),  # 6 px × 0.582 mm = 3.49 mm
        ((50.0, 71.0), 0.1, True),  # 40 px = 4 mm
    ],
)
def test_a_landmark_off_the_mask_makes_a_detection_not_usable(
    b_uv: tuple[float, float], spacing_mm: float | None, off: bool
) -> None:
    mask = np.zeros((80, 100), bool)
    mask[27:32, 10:90] = True  # a bar: rows 27-31, so (50, 36) is 5 px from its last row
    lm = np.array([[10.0, 29.0], b_uv])
    det = Detection(True, lm, np.array([0.8, 0.8]), mask, None, spacing_mm)
    assert det.landmark_off_mask.tolist() == [False, off]
    assert det.usable is not off
    assert det.unusable_reason == ("landmark B off the CM's mask" if off else None)


def test_mask_fragments_along_the_landmarks_are_joined_and_a_distant_blob_is_not() -> None:
    rows, cols = 80, 120
    vv, uu = np.mgrid[0:rows, 0:cols]
    a, b = np.array([10.0, 20.0]), np.array([100.0, 50.0])
    d = b - a
    t = np.clip(((uu - a[0]) * d[0] + (vv - a[1]) * d[1]) / (d @ d), 0, 1)
    tube = np.hypot(uu - (a[0] + t * d[0]), vv - (a[1] + t * d[1])) <= 4.0
    cut = tube & ~((t > 0.55) & (t < 0.6))  # noise cuts the tube: 55 % and 40 % pieces
    blob = np.hypot(uu - 100, vv - 10) <= 6  # a bright blob away from the CM, larger than nothing
    mask = cut | blob
    joined = decoder.cm_components(mask, np.stack([a, b]), join_frac=0.15)
    np.testing.assert_array_equal(joined, cut)
    largest = decoder.cm_components(mask, np.stack([a, b]), join_frac=0.0)
    assert largest.sum() < 0.6 * tube.sum() and not (largest & blob).any()
    assert (largest <= cut).all()
    # one component: returned as it is
    np.testing.assert_array_equal(decoder.cm_components(tube, np.stack([a, b]), join_frac=0.15), tube)


@pytest.mark.parametrize(
    ("spacing_mm", "padded_min_confidence", "widened", "found"),
    [
        (None, 0.95, False, True),  # no spacing: the image alone, whatever the padded threshold
        (2.0, 0.95, False, True),  # 260 px × 2 mm = 520 mm, wider than the 340 mm field: alone
        (1.0, 0.25, True, True),  # a 260 mm image in a 340 mm field; landmarks (0.90, 0.93) sure enough
        (1.0, 0.95, True, False),  # widened, and they are not
    ],
)
def test_small_field_is_seen_at_the_coarse_scale_of_a_whole_one(
    spacing_mm: float | None, padded_min_confidence: float, widened: bool, found: bool
) -> None:
    img, bar, lm = drawn_cm()  # 200 × 260 px
    config = tiny(
        coarse={"sampler": {"min_field_mm": 340.0}}, accept={"padded_min_confidence": padded_min_confidence}
    )
    det = Detector(oracle_net(config), device="cpu")
    view = det.coarse.view(img.shape, spacing_mm)
    if widened:
        # 340 px centred on the 260 × 200 image: 40 px of repeated edge left and right, 70 above/below
        assert (view.x0, view.y0, view.side, view.size) == (-40, -70, 340, 64)
    else:
        assert (view.x0, view.y0, view.side) == (0, 0, 260)
    _, logit, pts, _ = det.coarse(img, pixel_spacing_mm=spacing_mm)
    # the bar shrinks in the widened coarse view: (260/340)² of its area
    area = int((logit > 0.0).sum())
    full = int((det.coarse(img)[1] > 0.0).sum())
    assert area == full if not widened else 0.45 * full < area < 0.75 * full
    np.testing.assert_allclose(pts, lm, atol=view.scale + 1.0)  # mapped back to the input's pixels
    res = det.detect(img, pixel_spacing_mm=spacing_mm)
    assert res.found is found
    if found:
        np.testing.assert_allclose(res.landmarks_px, lm, atol=2.0)
        assert _dice(res.mask, bar) > 0.9
    else:
        assert res.landmarks_px is None


def test_padding_settings_are_validated() -> None:
    with pytest.raises(ValueError, match="min_field_mm"):
        tiny(coarse={"sampler": {"min_field_mm": -1.0}})
    with pytest.raises(ValueError, match="padded_min_confidence"):
        tiny(accept={"padded_min_confidence": 1.5})
    assert DetectorConfig().coarse.sampler.min_field_mm == 0.0  # off unless set


def test_a_landmark_peaking_on_a_blob_apart_from_the_cm_is_taken_on_the_cm() -> None:
    from fluoronav.detection.decoder import off_support_exclusion
    from fluoronav.detection.heatmaps import decode_landmarks

    rows, cols, sigma = 64, 96, 2.0
    v, u = torch.meshgrid(torch.arange(float(rows)), torch.arange(float(cols)), indexing="ij")
    # the CM: a bar from u = 20 to 60 at v = 30 (6 px wide); a 5 × 5 blob beyond its right end
    seg = torch.full((rows, cols), -8.0)
    seg[27:33, 20:61] = 8.0
    seg[6:11, 83:88] = 8.0

    def gauss(cu: float, cv: float, w: float) -> torch.Tensor:
        return np.log(w) - ((u - cu) ** 2 + (v - cv) ** 2) / (2 * sigma**2)

    a = gauss(58.6, 30.4, 1.0)  # A at the bar's right end
    b = torch.logsumexp(torch.stack([gauss(85.2, 8.1, 1.0), gauss(21.3, 29.7, 0.4)]), 0)  # B: blob first
    maps = torch.stack([a, b])[None]
    exclude = off_support_exclusion(seg[None], maps, threshold_logit=0.0, support_px=4.0)
    assert not exclude[0, 0].any()  # A peaks on the CM: left alone
    assert exclude[0, 1, 8, 85] and not exclude[0, 1, 30, 21] and not exclude[0, 1, 26, 40]
    assert exclude[0, 1, 30, 66] and not exclude[0, 1, 30, 63]  # the bar grown by 4 px
    plain, _ = decode_landmarks(maps, mode="softmax", sigma_px=sigma)
    est, conf = decode_landmarks(maps, mode="softmax", sigma_px=sigma, exclude=exclude)
    torch.testing.assert_close(est[0, 0], plain[0, 0])
    assert float((plain[0, 1] - torch.tensor([85.2, 8.1])).abs().max()) < 0.05
    assert float((est[0, 1] - torch.tensor([21.3, 29.7])).abs().max()) < 0.05  # on the CM's far end
    # its confidence is the mass of the map there: 0.4 / 1.4 of the Gaussians' 0.86
    assert abs(float(conf[0, 1]) - 0.4 / 1.4 * (1 - np.exp(-2.0))) < 0.03
    # the bar cut 10 px short of a piece that goes on in its direction: B there is the far end of
    # the tube and stays
    cut = torch.full((rows, cols), -8.0)
    cut[27:33, 30:61] = 8.0
    cut[27:33, 71:81] = 8.0
    far_end = torch.stack([gauss(31.0, 30.0, 1.0), gauss(79.5, 30.2, 1.0)])[None]
    assert not off_support_exclusion(cut[None], far_end, threshold_logit=0.0, support_px=4.0).any()
    # pieces less than 2 × 4 px apart are one region: B on a piece 5 px past A's end stays
    near_piece = seg.clone()
    near_piece[28:32, 66:69] = 8.0
    near = torch.stack([a, gauss(67.0, 30.0, 1.0)])[None]
    assert not off_support_exclusion(near_piece[None], near, threshold_logit=0.0, support_px=4.0).any()
    assert off_support_exclusion(near_piece[None], near, threshold_logit=0.0, support_px=2.0)[0, 1].any()
    # both landmarks off the CM: both move onto it
    both = torch.stack([gauss(85.0, 8.0, 1.0), gauss(86.0, 9.0, 1.0)])[None]
    assert off_support_exclusion(seg[None], both, threshold_logit=0.0, support_px=4.0)[0, :, 8, 85].all()
    # a view without a mask excludes nothing
    no_mask = torch.full((1, rows, cols), -8.0)
    assert not off_support_exclusion(no_mask, maps, threshold_logit=0.0, support_px=4.0).any()
    with pytest.raises(ValueError, match="exclude must be"):
        decode_landmarks(maps, mode="softmax", sigma_px=sigma, exclude=exclude[:, :1])


def _fine(landmarks: list[list[float]], confidence: list[float], view_side: int = 80) -> FineResult:
    """A fine-stage hypothesis with a ROI of ``view_side`` px at the origin and a 10 × 10 mask."""
    mask = np.zeros((200, 260), bool)
    mask[100:110, 100:110] = True
    return FineResult(
        np.array(landmarks, dtype=np.float64),
        np.array(confidence, dtype=np.float64),
        mask,
        View(x0=0, y0=0, side=view_side, size=TINY.fine.sampler.size),
    )


@pytest.mark.parametrize(
    ("shift_px", "spacing_mm", "other_conf", "min_confidence", "taken", "hypotheses"),
    [
        (30.0, 0.2, 0.6, 0.0, True, 1),  # a landmark 6 mm away, the network 0.2 surer of it: taken
        (30.0, 0.2, 0.45, 0.0, False, 1),  # 6 mm away, but only 0.125 surer: the detection stays
        (30.0, 0.2, 0.6, 0.65, False, 1),  # surer, but its landmark A would not count as found
        (20.0, 0.2, 0.9, 0.0, False, 0),  # 4 mm: the same hypothesis, the fine stage is not run again
        (10.0, None, 0.6, 0.0, True, 1),  # 10 px at the assumed 0.582 mm are 5.8 mm
    ],
)
def test_second_look_takes_a_wider_hypothesis_the_network_is_surer_of(
    monkeypatch: pytest.MonkeyPatch,
    shift_px: float,
    spacing_mm: float | None,
    other_conf: float,
    min_confidence: float,
    taken: bool,
    hypotheses: int,
) -> None:
    config = tiny(
        fine={"hypotheses": {"wide_factors": (1.6, 2.2), "wide_min_shift_mm": 5.0, "min_gain": 0.15}}
    )
    det = Detector(DetectorNet(config), device="cpu")
    first = _fine([[50.0, 50.0], [120.0, 50.0]], [0.3, 0.7])
    other = _fine([[50.0, 50.0], [120.0 + shift_px, 50.0]], [other_conf, 0.8], view_side=120)
    seen: dict[str, list] = {"views": [], "starts": []}

    def fine_views(image: np.ndarray, views: list, *, tta: int | None = None) -> tuple:
        seen["views"].append(views)
        pts = np.stack([first.landmarks_px, other.landmarks_px])  # the 1.6× view agrees, the 2.2× not
        return np.zeros((2, 64, 64)), pts, np.array([[0.3, 0.7], [0.9, 0.9]])

    def refit(image: np.ndarray, view: object, *args: object) -> tuple:
        return view, False

    def fine_stage(image: np.ndarray, view: object) -> FineResult:
        seen["starts"].append(view)
        return other

    monkeypatch.setattr(det.fine, "views", fine_views)
    monkeypatch.setattr(det.fine, "refit", refit)
    monkeypatch.setattr(det.fine, "run", fine_stage)
    res = det.fine.second_look(
        np.zeros((200, 260), np.float32),
        first,
        pixel_spacing_mm=spacing_mm,
        accept=lambda r: float(r.confidence.min()) >= min_confidence,
    )
    assert res is (other if taken else first)
    # one batch of the last ROI scaled by each factor about its centre (40, 40)
    (views,) = seen["views"]
    assert [v.side for v in views] == [128, 176]
    for v in views:
        assert abs(v.x0 + v.side / 2 - 40) <= 1 and abs(v.y0 + v.side / 2 - 40) <= 1
    # the fine stage runs again only from the view whose landmark moved
    assert len(seen["starts"]) == hypotheses
    if hypotheses:
        assert seen["starts"][0] is views[1]


def test_second_look_is_off_by_default_and_never_adds_a_detection(monkeypatch: pytest.MonkeyPatch) -> None:
    img, _, lm = drawn_cm()
    # off (the default): no wider view is run
    net = oracle_net()
    det = Detector(net, device="cpu")
    first = _fine(lm.tolist(), [0.5, 0.5])
    monkeypatch.setattr(det.fine, "views", lambda *a, **k: pytest.fail("a wider view was run"))
    assert det.fine.second_look(img, first, accept=lambda r: True) is first
    # on, but the detection is surer (mean confidence 0.5) than wide_max_confidence: none either
    det.fine.config = tiny(fine={"hypotheses": {"wide_factors": (2.2,), "wide_max_confidence": 0.45}}).fine
    assert det.fine.second_look(img, first, accept=lambda r: True) is first
    # on: a detection is looked at again; a CM seen whole gives the same result as without
    wide = tiny(fine={"hypotheses": {"wide_factors": (1.6, 2.2)}})
    ref = Detector(net, device="cpu").detect(img)
    calls = []

    def counted(detector: Detector) -> Detector:
        looked_at = detector.fine.second_look
        monkeypatch.setattr(
            detector.fine, "second_look", lambda *a, **k: calls.append(1) or looked_at(*a, **k)
        )
        return detector

    res = counted(Detector(oracle_net(wide), device="cpu")).detect(img)
    assert calls == [1] and res.found
    np.testing.assert_array_equal(res.landmarks_px, ref.landmarks_px)
    np.testing.assert_array_equal(res.mask, ref.mask)
    # an image without a detection (landmarks below min_confidence) is not looked at again
    unsure = counted(Detector(oracle_net(with_settings(wide, accept={"min_confidence": 0.99})), device="cpu"))
    assert not unsure.detect(img).found and calls == [1]
    assert not DetectorConfig().fine.hypotheses.wide_unfound  # unless asked
    for bad, name in (
        ({"wide_factors": (0.8,)}, "wide_factors"),
        ({"wide_factors": (5.0,)}, "wide_factors"),
        ({"min_gain": 2.0}, "min_gain"),
        ({"wide_max_confidence": -0.1}, "wide_max_confidence"),
    ):
        with pytest.raises(ValueError, match=name):
            tiny(fine={"hypotheses": bad})
    assert DetectorConfig().fine.hypotheses.wide_factors == ()
    two = tiny(fine={"hypotheses": {"wide_factors": (2,)}})
    assert DetectorConfig.from_dict(two.to_dict()).fine.hypotheses.wide_factors == (2.0,)


def _fine_stage_spy(
    starts: list, c_pts: np.ndarray, sure_near_px: np.ndarray, radius_px: float, conf: float
) -> Callable[[np.ndarray, View], FineResult]:
    """A stand-in fine stage that records its ROIs and is sure (``conf``) only of ROIs centred
    within ``radius_px`` input px of ``sure_near_px``."""

    def fine_stage(image: np.ndarray, view: View) -> FineResult:
        starts.append(view)
        centre = np.array([view.x0 + view.side / 2, view.y0 + view.side / 2])
        sure = np.linalg.norm(centre - sure_near_px) < radius_px
        return _fine(c_pts.tolist(), [conf, conf] if sure else [0.05, 0.05])

    return fine_stage


@pytest.mark.parametrize(
    ("joined", "conf_at_a", "min_confidence", "taken"),
    [
        (False, 0.8, 0.0, True),  # A's component alone: the network is far surer of it
        (False, 0.3, 0.0, False),  # surer by 0.15 at most: the ROI over both stays
        (False, 0.8, 0.85, False),  # surer, but it would not be found itself
        (True, 0.8, 0.0, False),  # one component under both landmarks: no other hypothesis
    ],
)
def test_split_coarse_mask_tries_each_landmarks_component_alone(
    monkeypatch: pytest.MonkeyPatch, joined: bool, conf_at_a: float, min_confidence: float, taken: bool
) -> None:
    det = Detector(DetectorNet(tiny(fine={"hypotheses": {"coarse_split": True}})), device="cpu")
    cv = View(x0=0, y0=0, side=256, size=64)  # 4 input px per coarse px
    c_mask = np.zeros((64, 64), bool)
    c_mask[10:14, 10:20] = True  # under A
    c_mask[40:44, 40:50] = True  # under B, a blob far away
    if joined:
        c_mask[14:42, 18:20] = True
        c_mask[40:42, 18:40] = True
    c_pts = cv.to_input(np.array([[12.0, 12.0], [45.0, 42.0]]))
    first = _fine(c_pts.tolist(), [0.2, 0.25])
    starts: list = []
    monkeypatch.setattr(det.fine, "run", _fine_stage_spy(starts, c_pts, c_pts[0], 40.0, conf_at_a))

    def accept(r: FineResult) -> bool:
        return float(r.confidence.min()) >= min_confidence

    res = det.fine.hypotheses(np.zeros((256, 256), np.float32), cv, c_mask, c_pts, first, accept=accept)
    assert (res is not first) == taken
    if taken:
        np.testing.assert_array_equal(res.confidence, [conf_at_a, conf_at_a])
    assert len(starts) == (0 if joined else 2)
    # each ROI holds its own component only: A's 10 coarse px long (40 input px), B's likewise
    for view in starts:
        assert view.side < 80


def test_split_coarse_mask_is_off_by_default_and_round_trips(monkeypatch: pytest.MonkeyPatch) -> None:
    off = DetectorConfig()
    assert not TINY.fine.hypotheses.coarse_split and not off.fine.hypotheses.coarse_split
    on = tiny(fine={"hypotheses": {"coarse_split": True}})
    assert DetectorConfig.from_dict(on.to_dict()).fine.hypotheses.coarse_split
    img, _, _ = drawn_cm()
    for config, looks in ((TINY, 0), (on, 1)):
        det = Detector(oracle_net(config), device="cpu")
        calls: list[int] = []
        coarse_hypotheses = det.fine.hypotheses
        monkeypatch.setattr(
            det.fine, "hypotheses", lambda *a, c=calls, f=coarse_hypotheses, **k: c.append(1) or f(*a, **k)
        )
        ref = det.detect(img)
        assert ref.found and len(calls) == looks  # one bar: one component, the result unchanged


@pytest.mark.parametrize(
    ("min_px", "blob_px", "conf_at_blob", "tried", "taken"),
    [
        (3, 12, 0.8, True, True),  # both landmarks on one blob, the CM is the other: taken
        (3, 12, 0.3, True, False),  # the other blob is no surer: the first stays
        (20, 12, 0.8, False, False),  # a blob under coarse_other_min_px is not tried
        (0, 12, 0.8, False, False),  # off (the default)
    ],
)
def test_another_coarse_blob_is_a_hypothesis_too(
    monkeypatch: pytest.MonkeyPatch, min_px: int, blob_px: int, conf_at_blob: float, tried: bool, taken: bool
) -> None:
    det = Detector(DetectorNet(tiny(fine={"hypotheses": {"coarse_other_min_px": min_px}})), device="cpu")
    cv = View(x0=0, y0=0, side=256, size=64)
    c_mask = np.zeros((64, 64), bool)
    c_mask[10:14, 10:20] = True  # both coarse landmarks here
    c_mask[40:43, 40 : 40 + blob_px // 3] = True  # another blob of blob_px pixels
    c_pts = cv.to_input(np.array([[11.0, 12.0], [18.0, 12.0]]))
    first = _fine(c_pts.tolist(), [0.2, 0.25])
    starts: list = []
    blob_px = cv.to_input(np.array([[42.0, 41.5]]))[0]
    monkeypatch.setattr(det.fine, "run", _fine_stage_spy(starts, c_pts, blob_px, 20.0, conf_at_blob))
    first_mask = decoder.component_at(c_mask, cv.from_input(c_pts))
    img = np.zeros((256, 256), np.float32)
    res = det.fine.hypotheses(img, cv, c_mask, c_pts, first, accept=lambda r: True, first_mask=first_mask)
    assert len(starts) == (1 if tried else 0)
    assert (res is not first) == taken
    with pytest.raises(ValueError, match="coarse_other_min_px"):
        tiny(fine={"hypotheses": {"coarse_other_min_px": -1}})
    three = tiny(fine={"hypotheses": {"coarse_other_min_px": 3}})
    assert DetectorConfig.from_dict(three.to_dict()).fine.hypotheses.coarse_other_min_px == 3


@pytest.mark.parametrize(
    ("blur_px", "min_ratio", "unsure_below", "found"),
    [
        (0.0, 0.0, 1.0, True),  # unsure, checked: the bar's boundary is a sharp edge
        (12.0, 0.0, 1.0, False),  # unsure, checked: a soft blob (ratio 2.0), no edge where its mask ends
        (12.0, 0.0, 0.5, True),  # its landmarks (0.85, 1.0) are sure enough not to need 2.5
        (12.0, 2.5, 0.0, False),  # every detection needs 2.5
        (12.0, 1.5, 0.0, True),  # every detection needs 1.5: it has that
        (12.0, 0.0, 0.0, True),  # no ratio needed
    ],
)
def test_a_detection_needs_an_edge_on_its_mask_boundary(
    blur_px: float, min_ratio: float, unsure_below: float, found: bool
) -> None:
    img, _, lm = drawn_cm()
    bar = np.zeros_like(img)
    cv2.line(bar, (60, 70), (190, 130), 1.0, thickness=24)
    bar = ndimage.gaussian_filter(bar, blur_px) if blur_px else bar
    rng = np.random.default_rng(0)
    img = bar + 0.02 * rng.standard_normal(img.shape).astype(np.float32)
    img[68:73, 58:63] = 4.0  # the oracle's landmark markers, as drawn_cm's
    img[128:133, 188:193] = -3.0
    edge = {"min_ratio": min_ratio, "unsure_below_confidence": unsure_below, "unsure_min_ratio": 2.5}
    res = Detector(oracle_net(tiny(add=("edge",), edge=edge)), device="cpu").detect(
        img, pixel_spacing_mm=0.582
    )
    assert res.found is found
    if found:
        np.testing.assert_allclose(res.landmarks_px, lm, atol=2.0)
    else:
        assert res.landmarks_px is None and res.centerline_px is None
        assert res.landmark_confidence.min() > 0.5  # reported, as for any rejected detection
        assert res.mask.any()
    # without the stage: the soft blob is found
    assert Detector(oracle_net(), device="cpu").detect(img, pixel_spacing_mm=0.582).found


def test_edge_check_settings_are_validated() -> None:
    for bad, name in (
        ({"unsure_below_confidence": 1.5}, "unsure_below_confidence"),
        ({"min_ratio": -1.0}, "min_ratio"),
        ({"unsure_min_ratio": -1.0}, "unsure_min_ratio"),
    ):
        with pytest.raises(ValueError, match=name):
            tiny(add=("edge",), edge=bad)
    # no edge check unless listed; listed, it round-trips
    assert DetectorConfig().edge is None
    cfg = tiny(add=("edge",), edge={"min_ratio": 1.4})
    back = DetectorConfig.from_dict(cfg.to_dict())
    assert "edge" in back.stages and back.edge is not None and back.edge.min_ratio == 1.4


@pytest.mark.parametrize(
    ("unfound", "surer", "looked", "found"),
    [
        (False, True, False, False),  # off (the default): a result under the floor is no detection
        (True, False, True, False),  # looked at again, no surer hypothesis: still none
        (True, True, True, True),  # looked at again, a hypothesis that counts: a detection
    ],
)
def test_fine_wide_unfound_looks_again_at_a_result_under_the_floor(
    monkeypatch: pytest.MonkeyPatch, unfound: bool, surer: bool, looked: bool, found: bool
) -> None:
    img, _, lm = drawn_cm()
    # the oracle's landmark confidences (about 0.8-0.9) are under this floor
    config = tiny(
        fine={"hypotheses": {"wide_factors": (2.2,), "wide_unfound": unfound}},
        accept={"min_confidence": 0.99},
    )
    det = Detector(oracle_net(config), device="cpu")
    seen: list[FineResult] = []

    def second_look(image: np.ndarray, first: FineResult, **kwargs: object) -> object:
        seen.append(first)
        accept = kwargs["accept"]
        assert callable(accept) and not accept(first)
        sure = dataclasses.replace(first, confidence=np.array([0.995, 0.995]))
        assert accept(sure)  # the detection's own test decides
        return sure if surer else first

    monkeypatch.setattr(det.fine, "second_look", second_look)
    res = det.detect(img)
    assert bool(seen) is looked and res.found is found
    if found:
        np.testing.assert_allclose(res.landmarks_px, lm, atol=2.0)
        np.testing.assert_allclose(res.landmark_confidence, 0.995)


def _stub_detection() -> tuple[np.ndarray, np.ndarray]:
    """A 20-px tube from (40, 100) to (200, 100) (u, v), bright on a dark background with noise, and
    the mask of all of it: a CM from A (100, 100) to B (195, 100) on a shaft stub to (40, 100), whose
    far end the fine stage took for A."""
    img = np.zeros((200, 260), np.float32)
    cv2.line(img, (40, 100), (200, 100), 1.0, thickness=20)
    mask = img > 0.5
    img += 0.05 * np.random.default_rng(0).standard_normal(img.shape).astype(np.float32)
    return img, mask


@pytest.mark.parametrize(
    ("fine_a", "next_a", "cut_at", "moved"),
    [
        ((45.0, 100.0), (100.0, 100.0), 100, True),  # A on the stub's free end, its next mode at the junction
        ((45.0, 100.0), None, 100, False),  # the same, but A is too unsure to be looked at (floor 0.6)
        ((45.0, 100.0), (150.0, 100.0), 40, False),  # the next place is mid-tube (no shaft around): stays
        ((45.0, 100.0), (100.0, 160.0), 100, False),  # the next place is off the mask: stays
        ((45.0, 100.0), (197.0, 100.0), 100, False),  # beyond B (its tip goes on there): stays
        ((100.0, 100.0), None, 100, False),  # A where the shaft goes on: not looked at again
    ],
)
def test_a_landmark_on_a_free_end_is_read_again_where_the_cm_meets_its_shaft(
    monkeypatch: pytest.MonkeyPatch,
    fine_a: tuple[float, float],
    next_a: tuple[float, float] | None,
    cut_at: int,
    moved: bool,
) -> None:
    img, stub_mask = _stub_detection()
    min_confidence = 0.6 if (next_a is None and fine_a[0] < 100.0) else 0.45
    config = tiny(
        add=("free_end",),
        free_end={"max_continuation": 0.35, "min_confidence": min_confidence},
        fine={"sampler": {"scales": (1.0, 1.2)}},
    )
    det = Detector(empty_net(config), device="cpu")
    assert det.free_end is not None
    fine_mask = stub_mask.copy()
    if fine_a[0] >= 100.0:
        fine_mask[:, :100] = False  # the fine stage stopped at the junction
    view = View(0, 60, 200, 64)
    pts = np.array([fine_a, [195.0, 100.0]])
    res = FineResult(pts, np.array([0.5, 0.8]), fine_mask, view)
    final = Finished(res.landmarks_px.copy(), np.zeros((2, 2)), fine_mask.copy())
    calls: list[tuple[int, np.ndarray, float]] = []

    def fine_views(image: np.ndarray, views: list, **kwargs: object) -> tuple:
        disk = kwargs["exclude_disk"]
        assert isinstance(disk, tuple)
        calls.append(disk)
        assert len(views) == 2  # the last pass's views at every scale
        pts = np.tile(np.array([next_a, [195.0, 100.0]]), (len(views), 1, 1))
        return None, pts, np.full((len(views), 2), 0.5)

    finished: list[np.ndarray] = []

    def finish(fine_pts: np.ndarray) -> Finished:
        finished.append(fine_pts)
        m = stub_mask.copy()
        m[:, :cut_at] = False  # the mask-end stage redraws the end at the new A
        return Finished(fine_pts.copy(), np.zeros((2, 2)), m)

    monkeypatch.setattr(det.fine, "views", fine_views)
    out = det.free_end(img, res, final, finish)
    if next_a is None:
        assert not calls and out is final
        return
    k, centre, radius = calls[0]
    assert k == 0 and np.allclose(centre, fine_a) and radius == pytest.approx(20.0, abs=2.0)
    if moved:
        np.testing.assert_allclose(out.landmarks_px, [next_a, [195.0, 100.0]])
        assert not out.mask[:, :100].any()
    else:
        assert out is final
        # a place off the mask or not short of B is not even finished
        assert bool(finished) is (next_a[0] < 190.0 and next_a[1] == 100.0)


def test_the_free_end_exclusion_reaches_the_heatmap_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    # the disk is drawn in each view's pixels: a landmark peaking inside it is taken outside it
    det = Detector(empty_net(tiny(fine={"decoder": {"min_separation_px": 0.0}})), device="cpu")
    size = TINY.fine.sampler.size
    view = View(0, 0, 2 * size, size)  # 2 input px per view px

    class Peaks(nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            out = torch.full((x.shape[0], 3, size, size), -20.0)
            out[:, 1, 10, 10] = 10.0  # A's best peak, at input (21, 21)
            out[:, 1, 40, 50] = 5.0  # its second mode, at input (101, 81)
            out[:, 2, 50, 50] = 10.0
            return out

    det.net.fine = Peaks()
    img = np.random.default_rng(0).standard_normal((2 * size, 2 * size)).astype(np.float32)
    _, pts, _ = det.fine.views(img, [view], tta=1)
    np.testing.assert_allclose(pts[0, 0], [21.0, 21.0], atol=1.0)
    _, pts, _ = det.fine.views(img, [view], tta=1, exclude_disk=(0, np.array([21.0, 21.0]), 10.0))
    np.testing.assert_allclose(pts[0, 0], [101.0, 81.0], atol=1.0)
    np.testing.assert_allclose(pts[0, 1], [101.0, 101.0], atol=1.0)  # B's map is not excluded


def test_free_end_setting_is_validated_and_off_by_default() -> None:
    with pytest.raises(ValueError, match="max_continuation"):
        tiny(add=("free_end",), free_end={"max_continuation": 1.5})
    with pytest.raises(ValueError, match="min_confidence"):
        tiny(add=("free_end",), free_end={"min_confidence": -0.1})
    cfg = DetectorConfig()  # no such check unless listed
    assert cfg.free_end is None and "free_end" not in cfg.stages
    assert Detector(empty_net(), device="cpu").free_end is None


def test_channels_last_weights_on_the_cpu_give_the_same_outputs() -> None:
    # the CPU detector keeps its weights channels-last (faster with oneDNN); every stage must
    # compute what the plain layout computes, to fp32 rounding
    torch.manual_seed(3)
    config = TINY
    det = Detector(DetectorNet(config), device="cpu")
    conv = next(m for m in det.net.fine.modules() if isinstance(m, nn.Conv2d))
    assert conv.weight.is_contiguous(memory_format=torch.channels_last)
    plain = Detector(DetectorNet(config), device="cpu")
    plain.net.load_state_dict(det.net.state_dict())
    plain.networks.net = plain.net.to(memory_format=torch.contiguous_format)  # type: ignore[call-overload]
    views = np.random.default_rng(0).standard_normal((3, 64, 64)).astype(np.float32)
    ours, theirs = det.networks.views("fine", views, tta=8), plain.networks.views("fine", views, tta=8)
    torch.testing.assert_close(ours, theirs, rtol=1e-4, atol=1e-4)


def _with_batch_statistics(net: DetectorNet, seed: int) -> DetectorNet:
    """``net`` with random batch-norm affine parameters and running statistics (fresh ones are
    0 / 1, which would make folding look right when it scales the wrong axis)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, nn.BatchNorm2d):
                n = m.num_features
                m.weight.copy_(0.5 + torch.rand(n, generator=g))
                m.bias.copy_(torch.randn(n, generator=g))
                m.running_mean.copy_(torch.randn(n, generator=g))
                m.running_var.copy_(0.2 + torch.rand(n, generator=g))
    return net


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_folded_batch_norm_computes_the_unfolded_network(dtype: torch.dtype) -> None:
    torch.manual_seed(5)
    net = _with_batch_statistics(
        DetectorNet(tiny(add=("refine",), refine={"network": {"channels": (4, 8)}})), 5
    )
    net = net.to(dtype).eval()
    folded = fold_batch_norm(copy.deepcopy(net))
    assert not any(isinstance(m, nn.BatchNorm2d) for m in folded.modules())
    assert any(isinstance(m, nn.BatchNorm2d) for m in net.modules())
    tol = {torch.float32: 1e-5, torch.float64: 1e-12}[dtype]
    x = torch.randn(3, 1, 64, 64, dtype=dtype)
    with torch.no_grad():
        for stage in ("coarse", "fine", "refine"):
            ref, out = getattr(net, stage)(x), getattr(folded, stage)(x)
            assert ref.abs().max() > 1.0  # the statistics matter to the output
            torch.testing.assert_close(out, ref, rtol=tol, atol=tol * float(ref.abs().max()))
    # folding again finds no batch norm: a no-op
    again = fold_batch_norm(copy.deepcopy(folded))
    for a, b in zip(again.state_dict().values(), folded.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="eval mode"):
        fold_batch_norm(net.train())


def test_a_detector_runs_a_folded_copy_and_leaves_the_callers_networks_trainable() -> None:
    torch.manual_seed(6)
    net = _with_batch_statistics(DetectorNet(TINY), 6)
    det = Detector(net, device="cpu")
    assert net.training and any(isinstance(m, nn.BatchNorm2d) for m in net.modules())
    assert not any(isinstance(m, nn.BatchNorm2d) for m in det.net.modules())
    views = np.random.default_rng(1).standard_normal((2, 64, 64)).astype(np.float32)
    ours = det.networks.views("fine", views, tta=2)
    theirs = tta_mean(net.eval().fine, views, 2)
    torch.testing.assert_close(ours, theirs, rtol=1e-4, atol=1e-4)


@pytest.mark.skipif(not torch.backends.mkldnn.is_available(), reason="this PyTorch has no oneDNN")
def test_packed_convolutions_compute_the_eager_blocks() -> None:
    torch.manual_seed(7)
    config = tiny(add=("refine",), refine={"network": {"channels": (4, 8)}})
    eager = fold_batch_norm(_with_batch_statistics(DetectorNet(config), 7).eval())
    packed = pack_for_cpu(copy.deepcopy(eager))
    blocks = [m for m in packed.modules() if isinstance(m, PackedConvolution)]
    # every block of the three U-Nets: per level but the last a down and an up block, and the bottom
    # one (channels (4, 8, 16): 5 blocks, (4, 8): 3); each net's output layer has no PReLU
    assert len(blocks) == 5 + 5 + 3
    assert sum(b.slope is None for b in blocks) == 3
    x = torch.randn(3, 1, 64, 64)
    with torch.no_grad():
        for stage in ("coarse", "fine", "refine"):
            ref, out = getattr(eager, stage)(x), getattr(packed, stage)(x)
            torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5 * float(ref.abs().max()))
        # a copy packs its own weights; a change of the weights is seen
        copied = copy.deepcopy(packed)
        torch.testing.assert_close(copied.fine(x), packed.fine(x), rtol=0.0, atol=0.0)
        for net in (eager, packed):
            net.fine.model[0].conv.weight.mul_(2.0)  # type: ignore[index, union-attr]
        torch.testing.assert_close(packed.fine(x), eager.fine(x), rtol=1e-5, atol=1e-4)
        # autocast, float64: the eager block's function
        with torch.autocast("cpu", dtype=torch.bfloat16):
            assert packed.fine(x).dtype == torch.bfloat16
        torch.testing.assert_close(
            copy.deepcopy(packed).double().fine(x.double()), copy.deepcopy(eager).double().fine(x.double())
        )
    # with autograd too (oneDNN's fused calls have no backward)
    y = packed.fine(x.requires_grad_())
    y.sum().backward()
    assert x.grad is not None


def test_a_cpu_detector_runs_packed_networks_with_the_eager_result() -> None:
    torch.manual_seed(8)
    net = _with_batch_statistics(DetectorNet(TINY), 8)
    det = Detector(net, device="cpu")
    packed = any(isinstance(m, PackedConvolution) for m in det.net.modules())
    assert packed == torch.backends.mkldnn.is_available()
    views = np.random.default_rng(2).standard_normal((3, 64, 64)).astype(np.float32)
    eager = fold_batch_norm(copy.deepcopy(net).eval())
    torch.testing.assert_close(
        det.networks.views("fine", views, tta=8), tta_mean(eager.fine, views, 8), rtol=1e-5, atol=1e-5
    )


@pytest.mark.parametrize(
    ("cm_from_u", "strength", "reread_a", "expect_a"),
    [
        (100.0, 5.0, (101.0, 100.0), (101.0, 100.0)),  # A on the shaft: the fine stage's new A, on the CM
        (100.0, 5.0, (60.0, 100.0), None),  # its new A back on the shaft: the centreline's cut point
        (100.0, 1.5, None, None),  # the stage sees nothing clearly (logits under shaft_min_cm_logit)
        (40.0, 5.0, None, None),  # the shaft stage's CM begins at A: nothing moves
        (48.0, 5.0, None, None),  # it begins 6 px (3.5 mm at 0.582 mm) beyond A: under shaft_cut_min_mm
    ],
)
def test_a_on_the_shaft_is_read_again_where_the_shaft_stage_says_the_cm_begins(
    monkeypatch: pytest.MonkeyPatch,
    cm_from_u: float,
    strength: float,
    reread_a: tuple[float, float] | None,
    expect_a: tuple[float, float] | None,
) -> None:
    img, stub_mask = _stub_detection()  # a CM from u = 100 to B at 195 on a shaft from u = 40
    config = tiny(
        add=("shaft",),
        shaft={
            "network": {"channels": (4, 8, 16, 32)},
            "cut_min_mm": 5.0,
            "min_cm_logit": 2.0,
            "sampler": {"spacing_px": 16.0},
            "band_px": 8.0,
        },
        fine={"sampler": {"scales": (1.0, 1.2)}},
    )
    det = Detector(empty_net(config), device="cpu")
    assert det.shaft is not None
    res = FineResult(
        np.array([[42.0, 100.0], [195.0, 100.0]]),
        np.array([0.5, 0.8]),
        stub_mask,
        View(0, 60, 200, 64),
    )
    line = np.stack([np.linspace(42.0, 195.0, 100), np.full(100, 100.0)], axis=1)
    final = Finished(res.landmarks_px.copy(), line, stub_mask.copy())

    def patch_logits(image: np.ndarray, frames: list) -> np.ndarray:
        # the shaft stage: CM where u ≥ cm_from_u, each patch pixel by its input position
        out = []
        for f in frames:
            uv = patch_grid_px(f)
            out.append(np.where(uv[..., 0] >= cm_from_u, strength, -strength).astype(np.float32))
        return np.stack(out)

    views_seen: list[list] = []

    def fine_views(image: np.ndarray, views: list, **kwargs: object) -> tuple:
        views_seen.append(views)
        pts = np.tile(np.array([reread_a, [195.0, 100.0]]), (len(views), 1, 1))
        return None, pts, np.full((len(views), 2), 0.5)

    finished: list[np.ndarray] = []

    def finish(fine_pts: np.ndarray) -> Finished:
        finished.append(fine_pts.copy())
        return Finished(fine_pts.copy(), line, stub_mask.copy())

    monkeypatch.setattr(det.shaft, "logits", patch_logits)
    monkeypatch.setattr(det.fine, "views", fine_views)
    out = det.shaft(img, res, final, finish)
    if reread_a is None:
        assert out is final and not finished and not views_seen
        return
    # the re-read sees the CM without the shaft: its ROI starts near u = 100 - margin, not at 40
    assert len(views_seen) == 1 and len(views_seen[0]) == 2 and views_seen[0][0].x0 > 60
    a = finished[0][0]
    if expect_a is not None:
        np.testing.assert_allclose(a, expect_a)
    else:
        assert abs(a[0] - 100.0) <= 3.0 and a[1] == pytest.approx(100.0)
    np.testing.assert_allclose(finished[0][1], [195.0, 100.0])  # B's fine landmark stays
    assert not out.mask[:, :95].any() and out.mask[:, 110:190].any()  # the shaft is out of the mask
    # a model without the stage has no such check
    assert Detector(empty_net(), device="cpu").shaft is None


def test_shaft_settings_are_validated_and_off_by_default() -> None:
    with pytest.raises(ValueError, match="cut_min_mm"):
        tiny(add=("shaft",), shaft={"cut_min_mm": -1.0})
    with pytest.raises(ValueError, match="cut_run_mm"):
        tiny(add=("shaft",), shaft={"cut_run_mm": 0.0})
    cfg = DetectorConfig()
    assert cfg.shaft is None and "shaft" not in cfg.stages
    assert DetectorNet(cfg).shaft is None


def test_precision_names_resolve_per_device(monkeypatch: pytest.MonkeyPatch) -> None:
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert runtime.resolve_precision("float32", cpu) == "float32"
    assert runtime.resolve_precision("BFloat16", cuda) == "bfloat16"
    monkeypatch.setattr(runtime, "native_bf16", lambda: True)
    assert runtime.resolve_precision("auto", cpu) == "bfloat16"
    assert runtime.resolve_precision("auto", cuda) == "float32"  # measured on CPUs only
    monkeypatch.setattr(runtime, "native_bf16", lambda: False)
    assert runtime.resolve_precision("auto", cpu) == "float32"  # emulated bf16 is slower
    with pytest.raises(InputError, match="--precision: unknown precision 'half'"):
        runtime.resolve_precision("half", cpu)
    assert Detector(DetectorNet(TINY), device="cpu").precision == "float32"  # the default everywhere


def test_bf16_stages_run_in_bfloat16_and_decode_in_float32() -> None:
    torch.manual_seed(4)
    config = tiny(bf16_stages=("fine",))
    net = DetectorNet(config)
    fast = Detector(net, device="cpu", precision="bfloat16")
    exact = Detector(net, device="cpu", precision="float32")
    assert (fast.precision, exact.precision) == ("bfloat16", "float32")
    # a bfloat16 stage runs as trained (its batch norms in float32 under autocast); the float32 ones
    # folded
    has_norm = {
        f"{tag} {name}": any(isinstance(m, nn.BatchNorm2d) for m in getattr(det.net, name).modules())
        for det, tag in ((fast, "fast"), (exact, "exact"))
        for name in ("coarse", "fine")
    }
    assert has_norm == {"fast coarse": False, "fast fine": True, "exact coarse": False, "exact fine": False}
    dtypes: dict[str, torch.dtype] = {}
    for det, tag in ((fast, "fast"), (exact, "exact")):
        for name in ("coarse", "fine"):
            getattr(det.net, name).register_forward_hook(
                lambda _m, _i, out, key=f"{tag} {name}": dtypes.__setitem__(key, out.dtype)
            )
    views = np.random.default_rng(1).standard_normal((3, 64, 64)).astype(np.float32)
    ours = fast.networks.views("fine", views, tta=8).numpy()
    theirs = exact.networks.views("fine", views, tta=8).numpy()
    fast.networks.views("coarse", views[:1])
    exact.networks.views("coarse", views[:1])
    # only the listed stage, and only where the precision allows it
    assert dtypes == {
        "fast fine": torch.bfloat16,
        "fast coarse": torch.float32,
        "exact fine": torch.float32,
        "exact coarse": torch.float32,
    }
    assert ours.dtype == theirs.dtype == np.float32  # decoded in float32
    # bfloat16 keeps 8 bits of mantissa: logits to ~1 % of their range
    scale = float(np.abs(theirs[:, 0]).max())
    np.testing.assert_allclose(ours[:, 0], theirs[:, 0], atol=0.02 * scale)
    # the patch stages' mirror mean hands float32 on, whatever the network ran in
    with fast.networks.autocast("fine"):
        patches = torch.randn(2, 1, 64, 64)
        assert runtime.mirror_mean(fast.net.fine, patches, 2).dtype == torch.float32
        assert runtime.mirror_mean(fast.net.fine, patches, 1).dtype == torch.float32


def test_bf16_stages_are_validated_and_round_trip() -> None:
    with pytest.raises(ValueError, match="bf16_stages"):
        tiny(bf16_stages=("fine", "decoder"))
    config = tiny(bf16_stages=("coarse", "fine"))
    assert DetectorConfig.from_dict(config.to_dict()) == config
    assert DetectorConfig().bf16_stages == ()  # float32 everywhere unless listed
