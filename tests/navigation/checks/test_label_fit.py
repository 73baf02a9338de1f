"""The preflight's CT ↔ labels pairing check: the bone labels sit on the CT's bone.

The hip phantom at 2.5 mm (the preflight tests' spacing). Seed 0 is left–right symmetric, so a
mirrored label map fits its bone as well as the true one and only the landmarks tell (the landmark
check names the mirror); the mirrored right femur of seed 3 lies 11.4° from its left one, of seed
206 4.8°, of seed 170 0.7° (too symmetric to tell). Each fault must be named by its own check,
naming the labels and the pairing fault it looks like.
"""

from __future__ import annotations

import numpy as np
import pytest

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.navigation.checks.label_fit import bone_fit, check_label_fit, sample_ct
from fluoronav.navigation.checks.preflight import PreflightConfig, PreflightFinding, check_labels

CFG = PreflightConfig()


@pytest.fixture(scope="module")
def phantoms() -> dict[int, Volume]:
    return {seed: hip_phantom(seed=seed, spacing_mm=2.5, texture=False) for seed in (0, 1, 3, 170, 206)}


def _one(findings: list[PreflightFinding], check: str = "labels_on_bone") -> PreflightFinding:
    assert len(findings) == 1, findings
    f = findings[0]
    assert f.kind == "input" and f.check == check and f.subject == "'labels'"
    assert "\n" not in f.reason
    if check == "labels_on_bone":
        assert "do not sit on the CT's bone" in f.reason
    return f


def _mirrored_labels(v: Volume) -> Volume:
    assert v.labels is not None
    return v.replace(labels=v.labels[:, :, ::-1].copy())


def test_each_phantoms_own_labels_sit_on_its_bone(phantoms: dict[int, Volume]) -> None:
    for seed, v in phantoms.items():
        s = sample_ct(v, CFG.contrast_voxel_mm)
        for value in (1, 2, 3):
            fit = bone_fit(s.hu, s.labels, value)
            assert fit is not None and fit.contrast > 0.75 and fit.mean_contrast > 0.6, (seed, value, fit)
        assert check_label_fit(v, "left", CFG) == []
        assert check_label_fit(v, "right", CFG) == []


@pytest.mark.parametrize(("axis", "shift", "moved"), [(2, 2, "-5, +0, +0 mm"), (0, -2, "+0, +0, +5 mm")])
def test_labels_shifted_5_mm_are_named_with_the_shift_back(
    phantoms: dict[int, Volume], axis: int, shift: int, moved: str
) -> None:
    v = phantoms[0]
    assert v.labels is not None
    labels = np.roll(v.labels, shift, axis=axis)  # 2 voxels of 2.5 mm
    f = _one(check_label_fit(v.replace(labels=labels), "left", CFG))
    assert "shifted?" in f.reason and f"moved by {moved}" in f.reason, f.reason


@pytest.mark.parametrize("seed", [3, 206])
def test_a_mirrored_label_map_of_an_asymmetric_anatomy_is_named_mirrored(
    phantoms: dict[int, Volume], seed: int
) -> None:
    v = phantoms[seed]
    f = _one(check_label_fit(_mirrored_labels(v), "left", CFG), "labels_mirrored")
    assert "fit the CT's bone better mirrored left–right" in f.reason and "mirror_margin" in f.reason
    # the CT mirrored against its labels and landmarks (a mirrored patient): the same finding
    f = _one(check_label_fit(v.replace(data=v.data[:, :, ::-1].copy()), "left", CFG), "labels_mirrored")
    assert "mirrored" in f.reason


def test_a_nearly_symmetric_anatomy_mirrored_is_not_told(phantoms: dict[int, Volume]) -> None:
    """Seed 170's femurs differ by 0.7°: mirrored, its labels fit as well (docs/validation.md)."""
    assert check_label_fit(_mirrored_labels(phantoms[170]), "left", CFG) == []


def test_a_mirrored_label_map_of_a_symmetric_anatomy_is_told_by_its_landmarks(
    phantoms: dict[int, Volume],
) -> None:
    """Seed 0 is symmetric: the mirrored labels fit the bone, the landmarks do not fit the labels."""
    mirrored = _mirrored_labels(phantoms[0])
    assert check_label_fit(mirrored, "left", CFG) == []
    found = check_labels(mirrored, "left", CFG)
    assert found[0].check == "landmark_in_femur"
    assert "lies in the 'femur_right' label" in found[0].reason and "mirrored left–right" in found[0].reason


def test_labels_of_another_ct_are_named(phantoms: dict[int, Volume]) -> None:
    v, other = phantoms[0], phantoms[1]
    f = _one(check_label_fit(v.replace(labels=other.labels), "left", CFG))
    assert "from another CT?" in f.reason and "min_bone_contrast" in f.reason
