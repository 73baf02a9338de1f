"""The procedural hip phantom: determinism, labels, landmarks, HU levels, geometry."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy import ndimage

from fluoronav.anatomy import Volume
from fluoronav.anatomy.phantom import DEFAULT_FOV_MM, hip_phantom

SIDES = (("left", 2), ("right", 3))


@pytest.fixture(scope="module")
def phantom() -> Volume:
    return hip_phantom(seed=0)


def _index(v: Volume, p: np.ndarray) -> tuple[int, int, int]:
    i, j, k = np.round((v.index_from_world @ np.append(p, 1.0))[:3]).astype(int)
    return int(k), int(j), int(i)


def test_geometry_and_labels(phantom: Volume) -> None:
    v = phantom
    assert v.data.shape == (240, 240, 344) and v.data.dtype == np.float32
    assert v.spacing_mm == (1.0, 1.0, 1.0)
    np.testing.assert_array_equal(v.direction, np.eye(3))
    np.testing.assert_allclose(v.center_world, 0.0, atol=0.5)
    extent = np.ptp(v.corners_world(), axis=0)
    np.testing.assert_allclose(extent, DEFAULT_FOV_MM, atol=1e-9)
    assert v.label_names == {1: "pelvis", 2: "femur_left", 3: "femur_right"}
    counts = np.bincount(v.labels.ravel(), minlength=4)
    assert counts[1] > 2e5 and counts[2] > 5e4 and counts[3] > 5e4 and counts.size == 4
    # +x = patient left in LPS: the left femur lies at positive x
    _, _, xl = np.nonzero(v.labels == 2)
    assert v.world_from_index[0, 3] + xl.mean() > 50.0
    _, _, xr = np.nonzero(v.labels == 3)
    assert v.world_from_index[0, 3] + xr.mean() < -50.0


def test_landmarks(phantom: Volume) -> None:
    v = phantom
    marks = v.landmarks_world
    for name in (
        "femoral_head_left",
        "femoral_head_right",
        "entry_left",
        "entry_right",
        "pelvis_center",
        "asis_left",
        "asis_right",
        "pubic_symphysis",
    ):
        assert marks[name].shape == (3,)
    for side, value in SIDES:
        head = marks[f"femoral_head_{side}"]
        assert v.labels[_index(v, head)] == value
        # the head is a ball of radius 22–25 mm: every voxel within 20 mm of its centre is femur
        k, j, i = _index(v, head)
        cube = v.labels[k - 20 : k + 21, j - 20 : j + 21, i - 20 : i + 21]
        r = np.sqrt(np.sum(np.square(np.mgrid[-20:21, -20:21, -20:21]), axis=0))
        assert np.all(cube[r <= 20.0] == value)
        assert np.any(cube[r <= 20.0 + 8.0] != value)  # and it is not much bigger than 25 mm
        # the acetabulum (pelvis) lies within ~12 mm beyond the head's surface, medially-superiorly
        up = head + np.array([-np.sign(head[0]) * 0.5, 0.0, 1.0]) / np.sqrt(1.25) * 30.0
        assert v.labels[_index(v, up)] == 1
        # entry point: on the lateral surface of the femur, lateral of the head
        entry = marks[f"entry_{side}"]
        assert abs(entry[0]) > abs(head[0]) + 40.0
        mask = v.labels == value
        k, j, i = _index(v, entry)
        box = (slice(k - 10, k + 11), slice(j - 10, j + 11), slice(i - 10, i + 11))
        inside = ndimage.distance_transform_edt(mask[box])
        outside = ndimage.distance_transform_edt(~mask[box])
        # signed distance of the nearest voxel centre to the label boundary, mm
        assert min(inside[10, 10, 10], outside[10, 10, 10]) <= 2.0
        # lateral of the entry is soft tissue, medial of it is bone
        lateral = entry + np.array([np.sign(entry[0]) * 4.0, 0.0, 0.0])
        medial = entry - np.array([np.sign(entry[0]) * 4.0, 0.0, 0.0])
        assert v.labels[_index(v, lateral)] == 0 and v.labels[_index(v, medial)] == value
    asis_l, asis_r = marks["asis_left"], marks["asis_right"]
    assert 200.0 < asis_l[0] - asis_r[0] < 280.0  # inter-ASIS distance of an adult pelvis
    assert marks["pubic_symphysis"][1] < marks["pelvis_center"][1]  # symphysis is anterior (−y)


def test_hu_levels(phantom: Volume) -> None:
    v = phantom
    assert v.data[0, 0, 0] == -1000.0  # air in the corner
    assert v.data.min() >= -1000.0 and v.data.max() < 2000.0
    # the left hip region (left femur's bounding box, with part of the pelvis) keeps the EDT cheap
    box = ndimage.find_objects(v.labels)[1]
    data, bone = v.data[box], v.labels[box] > 0
    depth = ndimage.distance_transform_edt(bone)
    cortical = data[(depth >= 1.0) & (depth <= 2.0)]
    cancellous = data[depth >= 6.0]
    body = data[~bone & (data > -200.0)]
    soft = np.median(body)
    assert 1200.0 < np.median(cortical) < 1800.0
    assert 200.0 < np.median(cancellous) < 400.0
    assert -150.0 < soft < 100.0
    assert np.median(cortical) > np.median(cancellous) > soft > -1000.0
    # the fat layer is about −100 HU and the muscle about 40 HU
    centre_row = v.data[120, 120]  # along x through the body centre, z = 0
    assert np.any(np.abs(centre_row + 100.0) < 1.0) and np.any(np.abs(centre_row - 40.0) < 1.0)


def test_deterministic_and_seed_dependent() -> None:
    a = hip_phantom(seed=3, spacing_mm=4.0)
    b = hip_phantom(seed=3, spacing_mm=4.0)
    c = hip_phantom(seed=4, spacing_mm=4.0)
    np.testing.assert_array_equal(a.data, b.data)
    np.testing.assert_array_equal(a.labels, b.labels)
    for k in a.landmarks_world:
        np.testing.assert_array_equal(a.landmarks_world[k], b.landmarks_world[k])
    assert not np.array_equal(a.labels, c.labels)
    moved = np.linalg.norm(a.landmarks_world["entry_left"] - c.landmarks_world["entry_left"])
    assert moved > 1.0
    assert a.name == "phantom-3"


def test_seeds_keep_anatomy_valid() -> None:
    for seed in (1, 2, 5, 13):
        v = hip_phantom(seed=seed, spacing_mm=2.0, texture=False)
        for side, value in SIDES:
            assert v.labels[_index(v, v.landmarks_world[f"femoral_head_{side}"])] == value
            entry = v.landmarks_world[f"entry_{side}"]
            # covered by soft tissue, not air, a few mm lateral of the entry point
            outside = entry + np.array([np.sign(entry[0]) * 4.0, 0.0, 0.0])
            assert v.data[_index(v, outside)] > -200.0


def test_shape_and_spacing_options() -> None:
    v = hip_phantom(seed=0, spacing_mm=2.5, shape=(40, 50, 60), texture=False)
    assert v.data.shape == (40, 50, 60) and v.spacing_mm == (2.5, 2.5, 2.5)
    np.testing.assert_allclose(v.center_world, 0.0, atol=1e-9)
    with pytest.raises(ValueError):
        hip_phantom(spacing_mm=0.0)


def benchmark_generation() -> dict[str, float]:
    """Rough wall time of the default phantom (not a test; run by hand)."""
    t = time.perf_counter()
    hip_phantom(seed=0)
    return {"hip_phantom_s": time.perf_counter() - t}
