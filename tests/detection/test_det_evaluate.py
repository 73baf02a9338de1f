"""Evaluation metrics and the ``evaluate`` command."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from det_synthetic import write_dataset
from test_det_detector import empty_net

from fluoronav.cli.evaluate import _model_files
from fluoronav.cli.main import main
from fluoronav.detection.detector import Detection, Detector
from fluoronav.detection.training.dataset import load_sample, read_manifest, shaft_length_of
from fluoronav.detection.training.evaluate import (
    OVER_SHAFT_MAX_DEG,
    VIEW_KINDS,
    _confidence_classes,
    comparison_markdown,
    dice_score,
    evaluate,
    evaluate_models,
    evaluate_sets,
    projected_shaft_mm,
    shaft_angle_deg,
    view_kind,
)
from fluoronav.detection.training.train import save_model
from fluoronav.errors import InputError


def test_dice_score() -> None:
    a = np.zeros((10, 10), bool)
    b = a.copy()
    assert dice_score(a, b) == 1.0
    a[:5] = True
    b[:, :5] = True
    assert dice_score(a, b) == pytest.approx(2 * 25 / 100)


def test_evaluate_counts_found_and_false_positives(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "d", 8, size=48, seed=1, negative_every=4)
    summary = evaluate(Detector(empty_net(), device="cpu"), data, split="all", progress=False)
    assert summary["positives"] == 6 and summary["negatives"] == 2
    assert summary["found_rate"] == 0.0 and summary["false_positive_rate"] == 0.0
    assert summary["dice"]["mean"] == 0.0 and summary["landmark_px"]["mean"] is None

    model = tmp_path / "m.pt"
    save_model(model, empty_net(), extra={})
    out = tmp_path / "eval.json"
    main(
        [
            "evaluate",
            "--data",
            str(data),
            "--model",
            str(model),
            "--out",
            str(out),
            "--split",
            "all",
            "--device",
            "cpu",
            "--no-progress",
        ]
    )
    assert json.loads(out.read_text())["samples"] == 8


def test_evaluate_on_collimated_fields_crops_every_image_reproducibly(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "d", 6, size=96, seed=2, negative_every=3)
    images: list[np.ndarray] = []

    class Recording(Detector):
        def detect(self, image: np.ndarray, *, pixel_spacing_mm: float | None = None):  # type: ignore[no-untyped-def]
            images.append(image)
            return super().detect(image, pixel_spacing_mm=pixel_spacing_mm)

    det = Recording(empty_net(), device="cpu")
    summary = evaluate(det, data, split="all", progress=False, field_frac=0.5, seed=4)
    assert summary["field_frac"] == 0.5 and summary["seed"] == 4
    first = [im.copy() for im in images]
    # each side is half the image's unless the CM needs more; every crop is a part of the image
    assert all(im.shape[0] < 96 and im.shape[1] < 96 for im in first)
    assert sum(im.shape == (48, 48) for im in first) >= 3
    images.clear()
    evaluate(det, data, split="all", progress=False, field_frac=0.5, seed=4)
    assert all(np.array_equal(a, b) for a, b in zip(first, images, strict=True))
    images.clear()
    evaluate(det, data, split="all", progress=False, field_frac=0.5, seed=5)
    assert not all(np.array_equal(a, b) for a, b in zip(first, images, strict=True))
    with pytest.raises(SystemExit) as exc:
        main(["evaluate", "--data", str(data), "--field-frac", "1.5", "--no-progress"])
    assert exc.value.code != 0


class _KnownErrors(Detector):
    """Returns each positive's true mask and landmarks with A moved by (6, 8) px (10 px = 5 mm at the
    synthetic set's 0.5 mm pixels); finds nothing in the images listed in ``miss`` (by order)."""

    def __init__(self, data: Path | list[Path], miss: set[int]) -> None:
        super().__init__(empty_net(), device="cpu")
        sets = data if isinstance(data, list) else [data]
        self.samples = [load_sample(d, r) for d in sets for r in read_manifest(d)]
        self.miss = miss
        self.calls = 0

    def detect(self, image: np.ndarray, *, pixel_spacing_mm: float | None = None) -> Detection:
        s = self.samples[self.calls]
        self.calls += 1
        assert np.array_equal(image, s.image)
        if s.landmarks_px is None or self.calls - 1 in self.miss:
            return Detection(False, None, np.zeros(2), np.zeros(image.shape, bool), None, pixel_spacing_mm)
        lm = s.landmarks_px + np.array([[6.0, 8.0], [0.0, 0.0]])
        return Detection(True, lm, np.array([0.9, 0.8]), s.mask.copy(), None, pixel_spacing_mm)


def test_evaluate_per_sample_records_and_foreshortening_classes(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "d", 9, size=64, seed=3, negative_every=3)
    per_sample = tmp_path / "out" / "samples.jsonl"
    summary = evaluate(_KnownErrors(data, miss={1}), data, split="all", progress=False, per_sample=per_sample)
    rows = [json.loads(line) for line in per_sample.read_text().splitlines()]
    assert [r["id"] for r in rows] == [str(r["id"]) for r in read_manifest(data)]
    pos = [r for r in rows if r["positive"]]
    assert len(pos) == summary["positives"] == 6 and summary["negatives"] == 3
    missed = rows[1]
    assert missed["positive"] and not missed["found"] and not missed["usable"]
    assert missed["dice"] == 0.0 and missed["landmark_px"] is None
    for r in pos:
        if r is missed:
            continue
        assert r["found"] and r["dice"] == 1.0 and r["confidence"] == pytest.approx([0.9, 0.8])
        assert r["landmark_px"] == pytest.approx([10.0, 0.0]) and r["landmark_mm"] == pytest.approx(
            [5.0, 0.0]
        )
        assert r["ab_mm"] == pytest.approx(0.5 * r["ab_px"])
    # every found A is 5 mm off: a gross error; every B is exact
    assert summary["landmark_gross"] == {"threshold_mm": 3.0, "count": 5, "of": 10}
    assert summary["landmark_mm"]["mean"] == pytest.approx(2.5)
    classes = summary["by_projected_ab"]
    assert sum(c["positives"] for c in classes) == 6
    for c in classes:
        lo, hi = c["ab_mm"]
        inside = [r for r in pos if lo <= r["ab_mm"] < (hi if hi is not None else np.inf)]
        assert c["positives"] == len(inside)
        if inside:
            assert c["dice_mean"] == pytest.approx(np.mean([r["dice"] for r in inside]))
            assert c["found_rate"] == pytest.approx(np.mean([r["found"] for r in inside]))
    # both landmarks of every found CM are sure (0.9, 0.8): one class holds all ten
    sure = summary["by_landmark_confidence"][-1]
    assert sure["confidence"] == [0.4, None] and sure["landmarks"] == 10
    assert sure["landmark_mm_mean"] == pytest.approx(2.5) and sure["landmark_gross"] == 5
    # the CLI writes the same file
    model = tmp_path / "m.pt"
    save_model(model, empty_net(), extra={})
    cli_rows = tmp_path / "cli.jsonl"
    main(
        [
            *("evaluate", "--data", str(data), "--model", str(model), "--split", "all"),
            *("--device", "cpu", "--no-progress", "--per-sample", str(cli_rows)),
        ]
    )
    assert len(cli_rows.read_text().splitlines()) == 9


def test_evaluate_sets_gives_each_set_and_the_pooled_figures(tmp_path: Path) -> None:
    a = write_dataset(tmp_path / "a", 9, size=64, seed=3, negative_every=3)
    b = write_dataset(tmp_path / "b", 4, size=64, seed=5, negative_every=2)
    per_sample = tmp_path / "rows.jsonl"
    # image 1 of set a is missed; set b's images come after a's 9
    both = evaluate_sets(
        _KnownErrors([a, b], miss={1}), [a, b], split="all", progress=False, per_sample=per_sample
    )
    alone = [evaluate(_KnownErrors(a, miss={1}), a, split="all", progress=False)]
    alone.append(evaluate(_KnownErrors(b, miss=set()), b, split="all", progress=False))
    for got, want in zip(both["sets"], alone, strict=True):
        assert {k: v for k, v in got.items() if k != "detect_ms"} == {
            k: v for k, v in want.items() if k != "detect_ms"
        }
    pooled = both["pooled"]
    assert pooled["data"] == [str(a), str(b)] and pooled["samples"] == 13
    assert pooled["positives"] == 6 + 2 and pooled["negatives"] == 3 + 2
    assert pooled["found_rate"] == pytest.approx(7 / 8)
    # every found A is 5 mm off, every B exact: 7 gross of 14 landmarks, mean 2.5 mm
    assert pooled["landmark_gross"] == {"threshold_mm": 3.0, "count": 7, "of": 14}
    assert pooled["landmark_mm"]["mean"] == pytest.approx(2.5)
    dices = [d for s in alone for d in [s["dice"]["mean"]] * s["positives"]]
    assert pooled["dice"]["mean"] == pytest.approx(np.mean(dices))
    rows = [json.loads(line) for line in per_sample.read_text().splitlines()]
    assert [r["data"] for r in rows] == [str(a)] * 9 + [str(b)] * 4
    assert [r["id"] for r in rows[9:]] == [str(r["id"]) for r in read_manifest(b)]


def test_evaluate_command_pools_repeated_data(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    a = write_dataset(tmp_path / "a", 3, size=64, seed=3, negative_every=3)
    b = write_dataset(tmp_path / "b", 2, size=64, seed=5, negative_every=2)
    model = tmp_path / "m.pt"
    save_model(model, empty_net(), extra={})
    args = ["evaluate", "--model", str(model), "--split", "all", "--device", "cpu", "--no-progress"]
    main([*args, "--data", str(a), "--data", str(b)])
    summary = json.loads(capsys.readouterr().out)
    assert [s["data"] for s in summary["sets"]] == [str(a), str(b)]
    assert summary["pooled"]["samples"] == 5
    main([*args, "--data", str(a)])  # one set: evaluate's summary, as before
    assert json.loads(capsys.readouterr().out)["data"] == str(a)


def _without_times(summary: dict) -> dict:
    """A summary without its ``detect_ms`` figures (timings differ from run to run)."""
    if isinstance(summary, dict):
        return {k: _without_times(v) for k, v in summary.items() if k != "detect_ms"}
    return [_without_times(v) for v in summary] if isinstance(summary, list) else summary


def test_evaluate_models_scores_every_model_on_the_same_images(tmp_path: Path) -> None:
    a = write_dataset(tmp_path / "a", 9, size=64, seed=3, negative_every=3)
    b = write_dataset(tmp_path / "b", 4, size=64, seed=5, negative_every=2)
    per_sample = tmp_path / "rows.jsonl"
    # "old" misses image 1 (a positive of set a); "new" and its twin "same" miss nothing
    models = {
        "old": _KnownErrors([a, b], miss={1}),
        "new": _KnownErrors([a, b], miss=set()),
        "same": _KnownErrors([a, b], miss=set()),
    }
    got = evaluate_models(models, [a, b], split="all", progress=False, per_sample=per_sample)
    assert all(m.calls == 13 for m in models.values())  # every image once to each model
    assert list(got["models"]) == ["old", "new", "same"]
    # each model's summary is what evaluate_sets gives for it alone
    alone = evaluate_sets(_KnownErrors([a, b], miss={1}), [a, b], split="all", progress=False)
    assert _without_times(got["models"]["old"]) == _without_times(alone)
    assert _without_times(got["models"]["new"]) == _without_times(got["models"]["same"])
    rows = got["comparison"]
    assert [(r["data"], r["model"]) for r in rows] == [
        (d, m) for d in (str(a), str(b), "pooled") for m in ("old", "new", "same")
    ]
    old, new, same = rows[-3:]  # pooled
    assert old["found_rate"] == pytest.approx(7 / 8) and new["found_rate"] == 1.0
    # every found A is 5 mm off (gross), every B exact
    assert (old["landmark_gross"], old["landmarks"], old["landmark_gross_rate"]) == (7, 14, 0.5)
    assert (new["landmark_gross"], new["landmarks"]) == (8, 16)
    assert old["false_positive_rate"] == 0.0 and old["landmark_mm_median"] == pytest.approx(2.5)
    assert {k: v for k, v in new.items() if k != "model"} == {k: v for k, v in same.items() if k != "model"}
    assert got["models"]["old"]["pooled"]["landmark_gross_rate"] == 0.5
    records = [json.loads(line) for line in per_sample.read_text().splitlines()]
    assert [(r["model"], r["data"]) for r in records[:3]] == [
        ("old", str(a)),
        ("new", str(a)),
        ("same", str(a)),
    ]
    assert len(records) == 3 * 13
    # one set: each model's summary is evaluate's, and no pooled rows
    one = evaluate_models(
        {"x": _KnownErrors(b, miss=set()), "y": _KnownErrors(b, miss={0})}, [b], split="all", progress=False
    )
    assert one["models"]["x"]["data"] == str(b) and [r["data"] for r in one["comparison"]] == [str(b)] * 2
    table = comparison_markdown(rows).splitlines()
    assert len(table) == 2 + 9 and table[0].startswith("| data set | model |")
    assert table[2].startswith(
        "| a | old | 6 | 3 | 83.3% | 0.0% | 5/10 | 50.00% | 2.50 |"
    )  # names below tmp_path
    assert table[-3].startswith("| pooled | old | 8 | 5 | 87.5% | 0.0% | 7/14 | 50.00% | 2.50 |")


def test_evaluate_command_compares_labelled_models(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    a = write_dataset(tmp_path / "a", 3, size=64, seed=3, negative_every=3)
    b = write_dataset(tmp_path / "b", 2, size=64, seed=5, negative_every=2)
    model = tmp_path / "m.pt"
    save_model(model, empty_net(), extra={})
    args = ["evaluate", "--split", "all", "--device", "cpu", "--no-progress", "--data", str(a)]
    md = tmp_path / "docs" / "table.md"
    main(
        [*args, "--data", str(b), "--model", f"old={model}", "--model", f"new={model}", "--markdown", str(md)]
    )
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert list(summary) == ["models", "comparison"] and list(summary["models"]) == ["old", "new"]
    old, new = summary["models"]["old"], summary["models"]["new"]
    assert old["pooled"]["samples"] == 5 and old["pooled"]["model"] == str(model)
    assert _without_times(old) == _without_times(new)
    assert [(r["data"], r["model"]) for r in summary["comparison"]] == [
        (d, m) for d in (str(a), str(b), "pooled") for m in ("old", "new")
    ]
    assert "old" in captured.err and "new" in captured.err and "pooled" in captured.err  # the table
    lines = md.read_text().splitlines()
    assert len(lines) == 2 + 6 and all(line.startswith("| ") for line in lines[2:])
    # one model: the summary as before (no comparison), the Markdown table still written
    main([*args, "--model", str(model), "--markdown", str(md)])
    captured = capsys.readouterr()
    single = json.loads(captured.out)
    assert single["data"] == str(a) and "comparison" not in single and "models" not in single
    assert single["landmark_gross_rate"] is None  # nothing found: no landmark scored
    assert md.read_text().splitlines()[2] == "| a | m | 2 | 1 | 0.0% | 0.0% | 0/0 | n/a | n/a | n/a | 0.000 |"
    assert captured.err == ""  # the table is printed for several models only
    with pytest.raises(SystemExit) as exc:  # two models under one label
        main([*args, "--model", str(model), "--model", str(model)])
    assert exc.value.code == 2 and "labelled 'm'" in capsys.readouterr().err


def test_model_labels(tmp_path: Path) -> None:
    odd = tmp_path / "lr=0.1.pt"  # a file whose name holds "=" is taken as a file
    odd.write_text("")
    assert _model_files([]) == {"shipped": None}
    assert _model_files(["shipped", "new=x/new.pt", "x/old.pt", str(odd)]) == {
        "shipped": None,
        "new": Path("x/new.pt"),
        "old": Path("x/old.pt"),
        "lr=0.1": odd,
    }
    assert _model_files(["ref=shipped", "shipped"]) == {"ref": None, "shipped": None}
    for values in (["a.pt", "b/a.pt"], ["=a.pt"], ["a="], ["shipped", "shipped"]):
        with pytest.raises(InputError):
            _model_files(values)


def test_evaluate_refuses_an_unwritable_output_before_scoring(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = write_dataset(tmp_path / "d", 2, size=48, seed=1)
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    for option in ("--out", "--per-sample", "--markdown"):
        with pytest.raises(SystemExit) as exc:
            main(
                [
                    "evaluate",
                    "--data",
                    str(data),
                    "--split",
                    "all",
                    "--no-progress",
                    option,
                    str(blocker / "x.json"),
                ]
            )
        assert exc.value.code == 2
        out, err = capsys.readouterr()
        assert out == ""  # no summary: nothing was scored
        assert (
            err.strip().startswith(f"error: {blocker / 'x.json'}: cannot write here")
            and "\n" not in err.strip()
        )
    # a run that fails after the check (no such data set) leaves no empty output file behind
    target = tmp_path / "new" / "summary.json"
    with pytest.raises(SystemExit):
        main(["evaluate", "--data", str(tmp_path / "missing"), "--no-progress", "--out", str(target)])
    assert not target.exists()


def _camera_64(pixel_spacing_mm: float | None = 0.5) -> dict:
    """A 64² camera 1000 mm from the world origin, looking along +z (fx = fy = 1000 px)."""
    cam = {
        "rows": 64,
        "cols": 64,
        "K": [[1000.0, 0.0, 32.0], [0.0, 1000.0, 32.0], [0.0, 0.0, 1.0]],
        "camera_from_world": [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 1000.0], [0, 0, 0, 1.0]],
    }
    if pixel_spacing_mm is not None:
        cam["pixel_spacing_mm"] = pixel_spacing_mm
    return cam


#: CM base frames (world_from_cm) and their shaft's projected length by hand for 50 and 100 mm shafts
#: (_camera_64, 0.5 mm pixels): across the view (cm z → world x, A at x = 10: u 42 → −8 or −58, 50 or
#: 100 px); along the view (0 mm); tilted 36.87° from the view axis (ends (−30, 0, 960) and
#: (−60, 0, 920): Δu = 1000·30/960 = 31.25 px and 1000·60/920 = 65.217 px)
_SHAFT_POSES = [
    ([[0.0, 0, 1, 10], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], 25.0, 50.0),
    ([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], 0.0, 0.0),
    ([[0.8, 0, 0.6, 0], [0, 1, 0, 0], [-0.6, 0, 0.8, 0], [0, 0, 0, 1]], 15.625, 0.5 * 60000 / 920),
]


@pytest.mark.parametrize(("world_from_cm", "expected_50_mm", "expected_100_mm"), _SHAFT_POSES)
def test_projected_shaft_length_by_hand(
    world_from_cm: list, expected_50_mm: float, expected_100_mm: float
) -> None:
    rec = {"id": 0, "camera": _camera_64(), "world_from_cm": world_from_cm}
    assert projected_shaft_mm(rec, 50.0) == pytest.approx(expected_50_mm, abs=1e-9)
    assert projected_shaft_mm(rec, 100.0) == pytest.approx(expected_100_mm, abs=1e-9)


def test_projected_shaft_length_is_none_where_unknown() -> None:
    pose = _SHAFT_POSES[0][0]
    assert projected_shaft_mm({"camera": None, "world_from_cm": pose}, 50.0) is None
    assert projected_shaft_mm({"camera": _camera_64(), "world_from_cm": None}, 50.0) is None
    assert projected_shaft_mm({"camera": _camera_64(None), "world_from_cm": pose}, 50.0) is None
    assert projected_shaft_mm({"camera": _camera_64(), "world_from_cm": pose}, 0.0) is None
    assert projected_shaft_mm({"camera": {"rows": 64}, "world_from_cm": pose}, 50.0) is None


def test_evaluate_splits_positives_by_projected_shaft(tmp_path: Path) -> None:
    data = write_dataset(tmp_path / "d", 6, size=64, seed=4, negative_every=3)
    records = read_manifest(data)
    for i, rec in enumerate(records):
        rec["camera"] = _camera_64()
        rec["world_from_cm"] = _SHAFT_POSES[i % 2][0]
    (data / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    # a 200 mm shaft: the first pose projects 100 mm (the last class), the second still 0 mm
    (data / "dataset.json").write_text(json.dumps({"spec": {"shaft_length_mm": 200.0}}))
    per_sample = tmp_path / "rows.jsonl"
    summary = evaluate(
        _KnownErrors(data, miss=set()), data, split="all", progress=False, per_sample=per_sample
    )
    rows = [json.loads(line) for line in per_sample.read_text().splitlines()]
    pos = [r for r in rows if r["positive"]]
    assert [r["shaft_mm"] for r in pos] == pytest.approx([100.0, 0.0, 0.0, 100.0])
    classes = summary["by_projected_shaft"]
    assert [c["shaft_mm"] for c in classes] == [[0.0, 30.0], [30.0, 60.0], [60.0, None]]
    assert [c["positives"] for c in classes] == [2, 0, 2]
    # _KnownErrors puts every A 5 mm off (a gross error) and every B on the truth
    assert [c["landmark_gross"] for c in classes] == [2, 0, 2]
    assert classes[0]["landmark_mm_mean"] == pytest.approx(2.5)
    # each positive's view class follows from its own A–B distance and shaft angle (the shaft seen
    # along the view has no direction: no angle), and the summary groups them in VIEW_KINDS order
    assert [r["shaft_angle_deg"] is None for r in pos] == [False, True, True, False]
    assert all(r["view"] == view_kind(r["ab_mm"], r["shaft_angle_deg"]) for r in pos)
    views = summary["by_view"]
    assert [v["view"] for v in views] == list(VIEW_KINDS)
    for v in views:
        inside = [r for r in pos if r["view"] == v["view"]]
        assert v["positives"] == len(inside) and v["landmark_gross"] == len(inside)
    # by angle: the two views with a shaft direction, in the class of their own angle
    angles = summary["by_shaft_angle"]
    assert [c["shaft_angle_deg"] for c in angles] == [[0.0, 35.0], [35.0, 55.0], [55.0, 90.0], [90.0, None]]
    with_angle = [r["shaft_angle_deg"] for r in pos if r["shaft_angle_deg"] is not None]
    assert with_angle == pytest.approx([78.4, 132.8], abs=0.1)  # the synthetic set's two B's
    assert [c["positives"] for c in angles] == [0, 0, 1, 1]
    assert [c["landmark_gross"] for c in angles] == [0, 0, 1, 1]


# the shaft of _SHAFT_POSES[0] runs from A at (42, 32) to (−8, 32) px (along −u); B placed by hand
@pytest.mark.parametrize(
    ("b_px", "expected_deg"),
    [((62.0, 32.0), 180.0), ((22.0, 32.0), 0.0), ((42.0, 52.0), 90.0), ((42.0 - 20.0 * 3**0.5, 52.0), 30.0)],
)
def test_shaft_angle_by_hand(b_px: tuple[float, float], expected_deg: float) -> None:
    rec = {"id": 0, "camera": _camera_64(), "world_from_cm": _SHAFT_POSES[0][0]}
    landmarks = np.array([[42.0, 32.0], b_px])
    assert shaft_angle_deg(rec, landmarks, 50.0) == pytest.approx(expected_deg, abs=1e-6)


def test_shaft_angle_is_none_without_a_direction() -> None:
    landmarks = np.array([[42.0, 32.0], [62.0, 32.0]])
    along = {"id": 0, "camera": _camera_64(), "world_from_cm": _SHAFT_POSES[1][0]}
    assert shaft_angle_deg(along, landmarks, 50.0) is None  # the shaft projects to a point
    across = {"id": 0, "camera": _camera_64(), "world_from_cm": _SHAFT_POSES[0][0]}
    assert shaft_angle_deg(across, landmarks[[0, 0]], 50.0) is None  # A = B: no chord
    assert shaft_angle_deg({"id": 0, "camera": None, "world_from_cm": None}, landmarks, 50.0) is None


def test_view_kinds() -> None:
    assert view_kind(10.0, 180.0) == "end-on"  # end-on wins over any angle
    assert view_kind(10.0, 5.0) == "end-on"
    assert view_kind(17.0, 180.0) == "clear"  # the end-on bound is exclusive
    assert view_kind(30.0, OVER_SHAFT_MAX_DEG - 1.0) == "over-shaft"
    assert view_kind(30.0, OVER_SHAFT_MAX_DEG) == "clear"
    assert view_kind(30.0, None) == "clear"  # shaft unknown: not taken as over it
    assert view_kind(None, 5.0) is None  # no pixel spacing: no class


def test_shaft_length_of_a_data_set(tmp_path: Path) -> None:
    assert shaft_length_of(tmp_path) == 50.0  # no dataset.json: the default of every older set
    (tmp_path / "dataset.json").write_text(json.dumps({"spec": {"shaft_length_mm": 0.0}}))
    assert shaft_length_of(tmp_path) == 0.0  # the bare CM
    (tmp_path / "dataset.json").write_text(json.dumps({"spec": {"shaft_length_mm": 300}}))
    assert shaft_length_of(tmp_path) == 300.0
    (tmp_path / "dataset.json").write_text("{not json")
    assert shaft_length_of(tmp_path) == 50.0


def test_landmarks_are_grouped_by_their_own_confidence() -> None:
    rows = [
        {"found": True, "confidence": [0.1, 0.5], "landmark_mm": [6.0, 0.2]},
        {"found": True, "confidence": [0.3, 0.45], "landmark_mm": [1.0, 0.4]},
        {"found": True, "confidence": [0.2, 0.9], "landmark_mm": [4.0, 0.3]},  # 0.2: the middle class
        {"found": False, "confidence": [0.05, 0.05], "landmark_mm": None},  # a miss has no landmarks
    ]
    unsure, middling, sure = _confidence_classes(rows, (0.2, 0.4, np.inf))
    assert unsure == {
        "confidence": [0.0, 0.2],
        "landmarks": 1,
        "landmark_mm_mean": 6.0,
        "landmark_mm_median": 6.0,
        "landmark_gross": 1,
    }
    assert middling["confidence"] == [0.2, 0.4] and middling["landmarks"] == 2
    assert middling["landmark_mm_mean"] == pytest.approx(2.5) and middling["landmark_gross"] == 1
    assert sure["confidence"] == [0.4, None] and sure["landmarks"] == 3
    assert sure["landmark_mm_median"] == pytest.approx(0.3) and sure["landmark_gross"] == 0
    empty = _confidence_classes([], (0.5, np.inf))
    assert [c["landmarks"] for c in empty] == [0, 0] and empty[0]["landmark_mm_mean"] is None
