"""Data sets: contract checks, crash + resume, worker-count independence, negatives, contact sheet."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

import fluoronav.simulation.dataset as ds
from fluoronav.errors import InputError
from fluoronav.simulation.dataset import DatasetSpec, simulate_dataset
from fluoronav.simulation.dataset_check import check_dataset

SPEC = DatasetSpec(n_phantoms=2, image_size=96, seed=424242, phantom_spacing_mm=2.0)


def _files(d: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((d / "samples").glob("*.npz"))}


def _rows(d: Path) -> dict[int, dict]:
    rows = [json.loads(line) for line in (d / "manifest.jsonl").read_text().splitlines()]
    assert len(rows) == len({r["id"] for r in rows})  # each sample exactly once
    return {r["id"]: r for r in rows}


def _arrays(d: Path) -> dict[str, dict[str, np.ndarray]]:
    out = {}
    for p in sorted((d / "samples").glob("*.npz")):
        with np.load(p) as z:
            out[p.name] = {k: z[k] for k in z.files}
    return out


def _assert_same_samples(a: Path, b: Path) -> None:
    assert _rows(a) == _rows(b)
    xa, xb = _arrays(a), _arrays(b)
    assert xa.keys() == xb.keys()
    for name in xa:
        for key in xa[name]:
            np.testing.assert_array_equal(xa[name][key], xb[name][key])


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("ref")
    simulate_dataset(d, 5, SPEC, workers=0)
    return d


def test_dataset_passes_the_contract_checks(reference: Path) -> None:
    assert check_dataset(reference, n=5) == []
    meta = json.loads((reference / "dataset.json").read_text())
    row = _rows(reference)[0]
    # documented storage resolution: 1536² detector binned to 96², spacing scaled accordingly
    assert meta["storage"]["rows"] == row["rows"] == 96
    assert row["pixel_spacing_mm"] == pytest.approx(0.194 * 1536 / 96)
    assert meta["storage"]["photons_per_pixel"] == pytest.approx(5000.0 * 16**2)  # 16×16 binned
    assert row["camera"]["K"][0][0] == pytest.approx(meta["sdd_mm"] / row["pixel_spacing_mm"])
    assert (reference / "contact_sheet.png").stat().st_size > 1000
    assert {r["ct"] for r in _rows(reference).values()} <= {"phantom-424242000", "phantom-424242001"}


def test_contract_checks_catch_defects(reference: Path, tmp_path: Path) -> None:
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(reference, bad)
    rows = _rows(bad)
    rows[1]["landmarks_px"] = [[-50.0, 3.0], [4.0, 5.0]]
    del rows[2]["camera"]
    (bad / "manifest.jsonl").write_text("".join(json.dumps(rows[i]) + "\n" for i in sorted(rows)))
    problems = check_dataset(bad, n=6)
    assert any("ids" in p for p in problems)
    assert any("sample 1" in p for p in problems) and any("sample 2: missing" in p for p in problems)


def test_killed_run_resumes_to_identical_samples(
    reference: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "crash"
    real = ds._make_sample
    done: list[int] = []

    def crash_after_two(sample_id: int, seed: int, **kw: object) -> dict:
        if len(done) == 2:
            raise KeyboardInterrupt  # the process is killed mid-run
        done.append(sample_id)
        return real(sample_id, seed, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(ds, "_make_sample", crash_after_two)
    with pytest.raises(KeyboardInterrupt):
        simulate_dataset(out, 5, SPEC, workers=0)
    assert len(_rows(out)) == 2
    # a torn manifest line and a stray temporary file, as a kill during a write leaves them
    with open(out / "manifest.jsonl", "a") as fh:
        fh.write('{"id": 2, "file": "samp')
    (out / "samples" / "000002.tmp.npz").write_bytes(b"partial")
    monkeypatch.setattr(ds, "_make_sample", real)
    new = simulate_dataset(out, 5, SPEC, workers=0)
    assert sorted(r["id"] for r in new) == [2, 3, 4]
    _assert_same_samples(out, reference)
    assert simulate_dataset(out, 5, SPEC, workers=0) == []  # nothing left to do


def test_rerun_with_other_settings_is_refused(reference: Path) -> None:
    with pytest.raises(InputError):
        simulate_dataset(
            reference, 5, DatasetSpec(n_phantoms=2, image_size=96, seed=1, phantom_spacing_mm=2.0), workers=0
        )


def test_unseen_seed_negatives(tmp_path: Path) -> None:
    spec = DatasetSpec(n_phantoms=1, image_size=64, seed=987_654_321, with_cm=False, phantom_spacing_mm=2.0)
    simulate_dataset(tmp_path, 3, spec, workers=0, contact_sheet_png=False)
    assert check_dataset(tmp_path, n=3) == []
    for r in _rows(tmp_path).values():
        assert r["landmarks_px"] is None and r["has_cm"] is False
    assert not (tmp_path / "contact_sheet.png").exists()


@pytest.mark.slow
def test_same_seed_same_samples_with_two_workers(reference: Path, tmp_path: Path) -> None:
    simulate_dataset(tmp_path, 5, SPEC, workers=2)
    _assert_same_samples(tmp_path, reference)


def test_foreshortened_data_set(tmp_path: Path) -> None:
    spec = DatasetSpec(n_phantoms=1, image_size=64, seed=31, phantom_spacing_mm=2.0, max_projected_ab_mm=20.0)
    simulate_dataset(tmp_path, 3, spec, workers=0, contact_sheet_png=False)
    assert check_dataset(tmp_path, n=3) == []
    for r in _rows(tmp_path).values():
        ab = np.linalg.norm(np.subtract(*r["landmarks_px"])) * r["pixel_spacing_mm"]
        assert ab <= 20.0 + 1e-6
    meta = json.loads((tmp_path / "dataset.json").read_text())
    assert meta["spec"]["max_projected_ab_mm"] == 20.0
    # a data set written before the option existed resumes (its spec lacks the key: the default)
    old = tmp_path / "old"
    simulate_dataset(old, 1, dataclasses.replace(spec, max_projected_ab_mm=None), workers=0)
    m = json.loads((old / "dataset.json").read_text())
    del m["spec"]["max_projected_ab_mm"]
    (old / "dataset.json").write_text(json.dumps(m))
    assert simulate_dataset(old, 1, dataclasses.replace(spec, max_projected_ab_mm=None), workers=0) == []
    with pytest.raises(InputError):  # but not with the option switched on
        simulate_dataset(old, 1, spec, workers=0)


def test_shaft_length_reaches_the_images(tmp_path: Path) -> None:
    spec = DatasetSpec(n_phantoms=1, image_size=64, seed=77, phantom_spacing_mm=2.0)
    long_spec = dataclasses.replace(spec, shaft_length_mm=250.0)
    simulate_dataset(tmp_path / "short", 2, spec, workers=0, contact_sheet_png=False)
    simulate_dataset(tmp_path / "long", 2, long_spec, workers=0, contact_sheet_png=False)
    assert json.loads((tmp_path / "long" / "dataset.json").read_text())["spec"]["shaft_length_mm"] == 250.0
    short, long = _rows(tmp_path / "short"), _rows(tmp_path / "long")
    extra = []
    for key, row in short.items():
        # the same scenes and labels (the shaft is not the CM); more metal where the longer shaft
        # is in the field (it may run out of the field next to the CM)
        assert row["landmarks_px"] == long[key]["landmarks_px"]
        a = np.load(tmp_path / "short" / row["file"])
        b = np.load(tmp_path / "long" / long[key]["file"])
        assert np.array_equal(a["mask"], b["mask"])
        extra.append(float(b["image"].sum()) - float(a["image"].sum()))
    assert min(extra) >= 0.0 and max(extra) > 10.0
    with pytest.raises(InputError):  # a data set directory keeps its shaft
        simulate_dataset(tmp_path / "short", 2, long_spec, workers=0)
    with pytest.raises(ValueError, match="shaft_length_mm"):
        DatasetSpec(shaft_length_mm=-1.0)
