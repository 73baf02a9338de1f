"""Data sets with domain randomisation and distractor metal: recorded per sample, the scene's draws
unchanged, the labels moved with the image, nothing drawn where it is off."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from fluoronav.simulation.dataset import DatasetSpec, simulate_dataset
from fluoronav.simulation.distractors import DISTRACTORS_REALISTIC
from fluoronav.simulation.randomisation import RANDOMISATION_REALISTIC, apply_image_record
from fluoronav.simulation.sample_variation import SampleVariation

PLAIN = DatasetSpec(n_phantoms=1, image_size=64, seed=8080, phantom_spacing_mm=2.0)
VARIED = dataclasses.replace(
    PLAIN,
    variation=SampleVariation(
        randomisation=RANDOMISATION_REALISTIC, distractors=DISTRACTORS_REALISTIC, p_distractors=1.0
    ),
)
N = 4


def _load(d: Path) -> list[tuple[dict, dict[str, np.ndarray]]]:
    rows = sorted(
        (json.loads(line) for line in (d / "manifest.jsonl").read_text().splitlines()), key=lambda r: r["id"]
    )
    out = []
    for row in rows:
        with np.load(d / row["file"]) as z:
            out.append((row, {k: z[k] for k in z.files}))
    return out


@pytest.fixture(scope="module")
def pair(tmp_path_factory: pytest.TempPathFactory) -> tuple[list, list]:
    plain, varied = tmp_path_factory.mktemp("plain"), tmp_path_factory.mktemp("varied")
    simulate_dataset(plain, N, PLAIN, workers=0, contact_sheet_png=False)
    simulate_dataset(varied, N, VARIED, workers=0, contact_sheet_png=False)
    return _load(plain), _load(varied)


def test_the_variation_leaves_the_scenes_draws_and_is_recorded(pair: tuple[list, list]) -> None:
    """Same scenes (poses, control points) as without the variation; every row records its draws,
    each with distractor metal (p = 1); the plain set records none."""
    for (p_row, _), (v_row, _) in zip(*pair, strict=True):
        assert v_row["world_from_cm"] == p_row["world_from_cm"]
        assert v_row["control_points_deg"] == p_row["control_points_deg"]
        assert "variation" not in p_row
        record = v_row["variation"]
        assert set(record) >= {"physics", "beam_filters", "distractors", "image"}
        assert record["physics"]["kvp"] >= 60.0 and len(record["distractors"]) >= 1


def test_the_labels_follow_the_image(pair: tuple[list, list]) -> None:
    """Replaying the image record on the plain sample's labels gives the varied sample's (rotation,
    transpose, window), and the stored image's shape is the row's."""
    for (_, p_arr), (v_row, v_arr) in zip(*pair, strict=True):
        lm = p_arr["landmarks_px"] if np.all(np.isfinite(p_arr["landmarks_px"])) else None
        _, mask, moved = apply_image_record(p_arr["image"], p_arr["mask"], lm, v_row["variation"]["image"])
        assert np.array_equal(mask, v_arr["mask"])
        assert v_arr["image"].shape == (v_row["rows"], v_row["cols"])
        if moved is not None and np.all(np.isfinite(moved)):
            assert np.allclose(moved, v_arr["landmarks_px"])


def test_the_varied_images_differ_and_the_transposed_have_no_camera(pair: tuple[list, list]) -> None:
    for (_, p_arr), (v_row, v_arr) in zip(*pair, strict=True):
        assert p_arr["image"].shape != v_arr["image"].shape or not np.array_equal(
            p_arr["image"], v_arr["image"]
        )
        assert (v_row["camera"] is None) == bool(v_row["variation"]["image"].get("transpose"))
