"""Input faults (``study navigation --fault``): each changes exactly what it names, and the outcomes."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import numpy as np
import pytest

from fluoronav.errors import InputError
from fluoronav.navigation.case.model import CaseView, NavigationCase, VerificationViews
from fluoronav.simulation.navigation.faults import (
    FAULTS,
    apply_case_fault,
    apply_first_fault,
    apply_verification_fault,
    fault_outcome,
    get_fault,
    mirror_view,
    names_fault,
    view_without_cm,
)


@pytest.fixture
def case(make_no_cm_case: Callable[..., NavigationCase]) -> NavigationCase:
    return make_no_cm_case(n_views=3, size=64)


def _same_view(a: CaseView, b: CaseView) -> None:
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.camera.K, b.camera.K)
    np.testing.assert_array_equal(a.camera.camera_from_world, b.camera.camera_from_world)


def test_mirror_one_flips_the_second_view_only_and_keeps_its_camera(case: NavigationCase) -> None:
    out = apply_first_fault(case, FAULTS["mirror_one"])
    np.testing.assert_array_equal(out.views[1].image, np.fliplr(case.views[1].image))
    assert not np.array_equal(out.views[1].image, case.views[1].image)
    np.testing.assert_array_equal(out.views[1].camera.K, case.views[1].camera.K)
    for k in (0, 2):
        _same_view(out.views[k], case.views[k])
    assert out.volume is case.volume and out.plan is case.plan


def test_mirror_all_flips_every_view(case: NavigationCase) -> None:
    out = apply_first_fault(case, FAULTS["mirror_all"])
    for a, b in zip(out.views, case.views, strict=True):
        np.testing.assert_array_equal(a.image, np.fliplr(b.image))


def test_a_mirrored_view_flips_its_given_landmarks_and_mask(case: NavigationCase) -> None:
    mask = np.zeros((64, 64), bool)
    mask[10:20, 3:8] = True
    v = dataclasses.replace(case.views[0], landmarks_px=np.array([[3.0, 10.0], [7.0, 19.0]]), mask=mask)
    m = mirror_view(v)
    assert m.landmarks_px is not None and m.mask is not None
    np.testing.assert_allclose(m.landmarks_px, [[60.0, 10.0], [56.0, 19.0]])
    np.testing.assert_array_equal(m.mask, np.fliplr(mask))


def test_focal_10pct_scales_the_second_cameras_focal_length_only(case: NavigationCase) -> None:
    out = apply_first_fault(case, FAULTS["focal_10pct"])
    before, after = case.views[1].camera, out.views[1].camera
    np.testing.assert_allclose(after.K[[0, 1], [0, 1]], 1.1 * before.K[[0, 1], [0, 1]])
    np.testing.assert_array_equal(after.K[:2, 2], before.K[:2, 2])
    assert after.pixel_spacing_mm == before.pixel_spacing_mm
    assert before.sdd_mm is not None and after.sdd_mm == pytest.approx(1.1 * before.sdd_mm)
    np.testing.assert_array_equal(after.camera_from_world, before.camera_from_world)
    np.testing.assert_array_equal(out.views[1].image, case.views[1].image)
    for k in (0, 2):
        _same_view(out.views[k], case.views[k])


def test_inverted_turns_every_image_into_its_max_minus_it(case: NavigationCase) -> None:
    out = apply_first_fault(case, FAULTS["inverted"])
    for a, b in zip(out.views, case.views, strict=True):
        np.testing.assert_allclose(a.image, b.image.max() - b.image)
        assert a.image.dtype == b.image.dtype


def test_labels_swapped_exchanges_pelvis_and_femur_voxels(case: NavigationCase) -> None:
    out = apply_case_fault(case, FAULTS["labels_swapped"])
    vol, new = case.volume, out.volume
    assert vol.labels is not None and new.labels is not None
    pelvis, femur = vol.label_value("pelvis"), vol.label_value("femur_left")
    np.testing.assert_array_equal(new.labels == femur, vol.labels == pelvis)
    np.testing.assert_array_equal(new.labels == pelvis, vol.labels == femur)
    np.testing.assert_array_equal(new.labels == 0, vol.labels == 0)
    assert new.label_names == vol.label_names and new.data is vol.data
    assert (vol.labels == pelvis).sum() != (new.labels == pelvis).sum()  # the input untouched


def test_plan_inward_300_moves_the_target_300_mm_along_its_direction(case: NavigationCase) -> None:
    out = apply_case_fault(case, FAULTS["plan_inward_300"])
    p0, p1 = case.plan, out.plan
    np.testing.assert_allclose(p1.tip_target_world_mm - p0.tip_target_world_mm, 300.0 * p0.direction_world)
    np.testing.assert_array_equal(p1.entry_point_world_mm, p0.entry_point_world_mm)
    np.testing.assert_array_equal(p1.direction_world, p0.direction_world)


def test_verify_joints_3deg_offsets_joint_2_of_the_verification_reading(case: NavigationCase) -> None:
    q = np.array([1.0, -80.0, 85.0, -95.0, -90.0, 3.0])
    with_ver = dataclasses.replace(case, verification=VerificationViews(q, case.views))
    out = apply_verification_fault(with_ver, FAULTS["verify_joints_3deg"])
    assert out.verification is not None
    np.testing.assert_allclose(out.verification.joints_deg - q, [0.0, 3.0, 0.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(out.joints_deg, case.joints_deg)  # the first reading as it was


def test_view_without_cm_drops_the_given_landmarks(case: NavigationCase) -> None:
    v = dataclasses.replace(case.views[1], landmarks_px=np.zeros((2, 2)), mask=np.ones((64, 64), bool))
    bare = np.full((64, 64), 0.25)
    out = view_without_cm(v, bare)
    assert out.landmarks_px is None and out.mask is None and out.image.dtype == np.float32
    np.testing.assert_array_equal(out.image, bare)


def test_faults_leave_other_parts_alone(case: NavigationCase) -> None:
    for name in ("none", "handeye_10mm", "verify_no_move", "view_without_cm"):
        f = FAULTS[name]
        assert apply_case_fault(apply_first_fault(case, f), f) is case
    assert apply_first_fault(case, FAULTS["plan_inward_300"]) is case


def test_unknown_fault_name_is_an_input_error() -> None:
    with pytest.raises(InputError, match=r"unknown fault 'mirror_three'.*mirror_one"):
        get_fault("mirror_three")
    assert get_fault(None) is None and get_fault("inverted") is FAULTS["inverted"]


def test_every_fault_but_the_baseline_is_named_by_some_check() -> None:
    assert len(FAULTS) == 20
    assert all(f.handled_by for n, f in FAULTS.items() if n != "none")
    assert FAULTS["handeye_10mm"].handeye_error_mm == 10.0 and FAULTS["handeye_10mm"].landing_counts


def test_outcomes_name_the_fault_or_not() -> None:
    mirror = FAULTS["mirror_one"]
    assert fault_outcome(mirror, status="refused", stage="pelvis", check="mirrored") == (
        "refused_named",
        True,
    )
    assert fault_outcome(mirror, status="refused", stage="cm", check="edge_ncc") == ("refused_other", False)
    cm_less = FAULTS["view_without_cm"]
    assert fault_outcome(cm_less, status="refused", stage="cm", check="edge_ncc")[0] == "refused_named"
    assert fault_outcome(cm_less, status="refused", stage="pelvis", check="edge_ncc")[0] == "refused_other"
    assert fault_outcome(FAULTS["inverted"], status="input_error", check="inverted_image")[1]
    landed = functools.partial(fault_outcome, status="ok", final_tip_mm=0.8, first_tip_mm=0.5, commanded=True)
    assert landed(mirror, left_out=("orbit +20",), faulty_view="orbit +20") == ("landed", True)
    assert landed(mirror, left_out=(), faulty_view="orbit +20") == ("landed", False)
    assert landed(FAULTS["handeye_10mm"]) == ("landed", True)
    assert landed(mirror, final_tip_mm=2.5) == ("unsafe", False)
    # a first command from a registration 3 mm off is unsafe, whatever the verification said after it
    assert fault_outcome(
        FAULTS["verify_no_move"],
        status="refused",
        check="kinematics_disagree",
        first_tip_mm=3.0,
        commanded=True,
    ) == ("unsafe", False)
    assert fault_outcome(mirror, status="failed") == ("failed", False)
    # a check that blames one view names the fault only where that view is the faulty one
    other = functools.partial(fault_outcome, FAULTS["view_other_patient"], status="refused", stage="cm")
    assert other(check="odd_view", faulty_view="orbit +20", refused_view="orbit +20")[0] == "refused_named"
    assert other(check="odd_view", faulty_view="orbit +20", refused_view="AP")[0] == "refused_other"


def test_the_preflight_names_swapped_labels_and_a_plan_in_soft_tissue(case: NavigationCase) -> None:
    from fluoronav.navigation.checks.preflight import PreflightInputError, preflight, raise_for_input

    raise_for_input(preflight(case), "case.json")  # the case itself is good input
    swapped = apply_case_fault(case, FAULTS["labels_swapped"])
    with pytest.raises(PreflightInputError) as exc:
        raise_for_input(preflight(swapped), "case.json")
    assert exc.value.check in FAULTS["labels_swapped"].handled_by
    deep = apply_case_fault(case, FAULTS["plan_inward_300"])
    plan_checks = {f.check for f in preflight(deep) if f.kind == "plan"}
    assert plan_checks and plan_checks <= set(FAULTS["plan_inward_300"].handled_by)


@pytest.fixture
def phantom_case(case: NavigationCase) -> NavigationCase:
    """The small case on the hip phantom of seed 3 (its femurs 11° from mirror images), the plan from
    the left entry landmark to the left femoral head."""
    from fluoronav.anatomy.phantom import hip_phantom
    from fluoronav.navigation.planning import Plan

    volume = hip_phantom(seed=3, spacing_mm=2.5, texture=False)
    entry, head = volume.landmarks_world["entry_left"], volume.landmarks_world["femoral_head_left"]
    direction = (head - entry) / np.linalg.norm(head - entry)
    return dataclasses.replace(case, volume=volume, plan=Plan("entry_left", entry, direction))


@pytest.mark.parametrize(
    "name", ["labels_mirrored", "labels_shifted_5mm", "fbg_beyond_range", "plan_other_femur"]
)
def test_the_shared_input_faults_are_named_by_the_preflight(phantom_case: NavigationCase, name: str) -> None:
    """Each fault of an input every view shares is named by the preflight check it is for; the clean
    case passes the same checks."""
    from fluoronav.navigation.checks.preflight import preflight

    def named(c: NavigationCase) -> list[str]:
        return [
            f.check
            for f in preflight(c)
            if f.kind != "note" and names_fault(FAULTS[name], "preflight", f.check)
        ]

    assert named(phantom_case) == []
    out = apply_case_fault(phantom_case, FAULTS[name])
    assert out is not phantom_case and named(out), [(f.check, f.reason) for f in preflight(out)]


def test_fbg_faults_move_every_control_point_within_the_cms_range(case: NavigationCase) -> None:
    """Bent: +3° at each point; another shape: ±5° alternately; a point the range would clip goes
    the other way by the full offset, so each point is off by exactly the fault's size."""
    reading = np.array([0.0, 1.0, -2.0, 6.0, -7.5])
    base = dataclasses.replace(case, fbg_control_points_deg=reading)
    bent = apply_case_fault(base, FAULTS["fbg_bent_3deg"]).fbg_control_points_deg
    other = apply_case_fault(base, FAULTS["fbg_other_shape"]).fbg_control_points_deg
    assert bent is not None and other is not None
    np.testing.assert_allclose(bent, [3.0, 4.0, 1.0, 3.0, -4.5])
    np.testing.assert_allclose(other, [5.0, -4.0, 3.0, 1.0, -2.5])
    assert np.all(np.abs(other) <= 7.9) and np.all(np.abs(bent) <= 7.9)
    assert np.array_equal(base.fbg_control_points_deg, reading)  # the case itself untouched


def test_a_ct_spacing_fault_scales_every_point_made_in_the_cts_frame(phantom_case: NavigationCase) -> None:
    """Spacing × 1.1: each voxel's world position, the landmarks and the plan's entry scale about the
    origin, the plan's depth with them; each view's initial camera keeps its offset from the head."""
    from fluoronav.geometry import se3

    c = dataclasses.replace(phantom_case, side="left")
    out = apply_case_fault(c, FAULTS["ct_spacing_110"])
    v0, v1 = c.volume, out.volume
    o = np.asarray(v0.origin_mm)
    np.testing.assert_allclose(v1.spacing_mm, 1.1 * np.asarray(v0.spacing_mm))
    ijk = np.array([10.0, 20.0, 5.0, 1.0])
    np.testing.assert_allclose(
        (v1.world_from_index @ ijk)[:3], o + 1.1 * ((v0.world_from_index @ ijk)[:3] - o)
    )
    for k, p in v0.landmarks_world.items():
        np.testing.assert_allclose(v1.landmarks_world[k], o + 1.1 * (p - o))
    np.testing.assert_allclose(out.plan.entry_point_world_mm, o + 1.1 * (c.plan.entry_point_world_mm - o))
    assert out.plan.insertion_depth_mm == pytest.approx(1.1 * c.plan.insertion_depth_mm)
    h0, h1 = v0.landmarks_world["femoral_head_left"], v1.landmarks_world["femoral_head_left"]
    for a, b in zip(c.views, out.views, strict=True):
        np.testing.assert_allclose(
            se3.apply(b.camera.camera_from_world, h1), se3.apply(a.camera.camera_from_world, h0), atol=1e-9
        )
    np.testing.assert_array_equal(v1.data, v0.data)
