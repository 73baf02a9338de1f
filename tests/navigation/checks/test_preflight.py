"""Pre-registration checks: the plan, labels and landmarks, and images of a small phantom case.

The case: the hip phantom at 2.5 mm, the demo's plan (the CM tip on the left entry landmark, its
axis towards the femoral head), three physics-simulated 128² views with the CM (AP, orbits +20° and
−15° about the femoral head), three verification views after the CM moved 8 mm and the C-arm slid,
and cameras whose ``camera_from_ct`` is the truth moved by a few mm and degrees (a rough initial
pose). Every test of a fault checks the finding of its own check, so it fails when that check is
removed; the good case passes every check.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fluoronav.anatomy.phantom import hip_phantom
from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError
from fluoronav.geometry.camera import Camera
from fluoronav.geometry.carm import carm_camera, centre_on, orbit_camera
from fluoronav.manipulator.config import CMConfig
from fluoronav.manipulator.robot import UR10
from fluoronav.navigation.case.model import NavigationCase, VerificationViews
from fluoronav.navigation.case.view import CaseView
from fluoronav.navigation.checks.preflight import (
    LabelDistance,
    PreflightConfig,
    PreflightFinding,
    PreflightInputError,
    check_intensities,
    check_labels,
    check_plan,
    check_views,
    insertion_limit_mm,
    preflight,
    raise_for_input,
)
from fluoronav.navigation.planning import Plan, neck_entry_plan
from fluoronav.simulation.scene import Scene, cm_pose_along
from fluoronav.simulation.xray import SimulationConfig, XraySimulator

SIZE = 128
CFG = PreflightConfig()


def _rough(camera: Camera, head: np.ndarray) -> Camera:
    """The camera with the CT moved 4 mm and 3° about the femoral head: an initial pose."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(np.radians([2.0, -1.5, 1.5])).as_matrix()
    T[:3, 3] = head - T[:3, :3] @ head + np.array([3.0, -2.0, 2.0])
    return camera.with_pose(camera.camera_from_world @ T)


@pytest.fixture(scope="module")
def case() -> NavigationCase:
    volume = hip_phantom(seed=0, spacing_mm=2.5, texture=False)
    head = volume.landmarks_world["femoral_head_left"]
    entry = volume.landmarks_world["entry_left"]
    plan = neck_entry_plan(entry, head)
    sim = XraySimulator(volume, config=SimulationConfig(image_size=SIZE))
    cp = np.array([2.0, 1.0, 0.0, -1.0, 0.0])

    def views(iso: np.ndarray, cm_back_mm: float, prefix: str, seed: int) -> tuple[CaseView, ...]:
        ap = centre_on(carm_camera(isocenter_world=head, source_to_isocenter_mm=450.0), iso)
        cams = [ap] + [orbit_camera(ap, angle_deg=a, isocenter_world=iso) for a in (20.0, -15.0)]
        cm = cm_pose_along(entry - cm_back_mm * plan.direction_world, plan.direction_world, 0.3)
        out = []
        for k, (cam, name) in enumerate(zip(cams, ("AP", "orbit +20", "orbit -15"), strict=True)):
            im = sim.simulate(Scene(camera=cam, world_from_cm=cm, control_points_deg=cp), seed=seed + k)
            out.append(CaseView(f"{prefix}{name}", im.image, _rough(im.camera, head)))
        return tuple(out)

    return NavigationCase(
        volume=volume,
        plan=plan,
        side="left",
        cm_config=CMConfig(),
        fbg_control_points_deg=cp,
        robot=UR10,
        joints_deg=np.zeros(6),
        ee_from_cm=np.eye(4),
        views=views(head, 40.0, "", 0),
        verification=VerificationViews(
            np.zeros(6), views(head + np.array([8.0, 0.0, -6.0]), 32.0, "after ", 10)
        ),
    )


def _checks(findings: list[PreflightFinding]) -> list[str]:
    return [f.check for f in findings]


def _one(findings: list[PreflightFinding], check: str, subject: str | None = None) -> PreflightFinding:
    hits = [f for f in findings if f.check == check and subject in (None, f.subject)]
    assert len(hits) == 1, findings
    assert "\n" not in hits[0].reason and hits[0].reason.startswith(hits[0].subject)
    return hits[0]


# ----- the good case -----------------------------------------------------------------------------
def test_the_phantom_case_passes_every_check(case: NavigationCase) -> None:
    assert preflight(case, CFG) == []


# ----- distances ---------------------------------------------------------------------------------
def test_label_distance_is_signed_and_metric_near_and_far() -> None:
    """A ball of radius 20 mm on a 2 mm grid: the distance to its surface within half a voxel near
    the surface inside and outside and 100 mm away (beyond the crop); at the centre (the distance
    field's ridge, cut by the interpolation, on the voxels' staircase) within 1.5 voxels."""
    n, h = 40, 2.0
    origin = -0.5 * h * (n - 1)
    ax = origin + h * np.arange(n)
    Z, Y, X = np.meshgrid(ax, ax, ax, indexing="ij")
    labels = (X**2 + Y**2 + Z**2 <= 20.0**2).astype(np.uint8)
    vol = Volume(
        np.zeros(labels.shape, np.float32), (h, h, h), (origin,) * 3, labels=labels, label_names={1: "ball"}
    )
    d = LabelDistance(vol, "ball", pad_mm=5.0)
    pts = np.array([[0.0, 15.0, 0.0], [0.0, -11.0, 9.0], [23.0, 0.0, 0.0], [0.0, 0.0, 120.0]])
    np.testing.assert_allclose(d(pts), [-5.0, np.hypot(11.0, 9.0) - 20.0, 3.0, 100.0], atol=0.5 * h)
    assert -20.0 - h < float(d(np.zeros(3))) < -20.0 + 1.5 * h


# ----- the plan ----------------------------------------------------------------------------------
def test_a_target_300_mm_inward_is_refused(case: NavigationCase) -> None:
    p = case.plan
    plan = dataclasses.replace(p, entry_point_world_mm=p.entry_point_world_mm + 300.0 * p.direction_world)
    f = _one(check_plan(plan, case.volume, "left", case.cm_config, CFG), "target_in_femur")
    assert f.kind == "plan" and f.subject == "plan 'entry'"
    assert "outside the femur_left label" in f.reason and "at most 3 mm" in f.reason
    assert float(f.reason.split("lies ")[1].split(" mm")[0]) > 100.0
    assert check_plan(case.plan, case.volume, "left", case.cm_config, CFG) == []


def test_an_entry_30_mm_off_the_bone_is_refused(case: NavigationCase) -> None:
    """The entry 30 mm back along the direction, the target kept on the bone (depth 30 mm)."""
    p = case.plan
    plan = dataclasses.replace(
        p, entry_point_world_mm=p.entry_point_world_mm - 30.0 * p.direction_world, insertion_depth_mm=30.0
    )
    findings = check_plan(plan, case.volume, "left", case.cm_config, CFG)
    assert _checks(findings) == ["entry_on_surface"]
    assert "outside the femur_left label's surface (at most 5 mm either side)" in findings[0].reason
    assert float(findings[0].reason.split("lies ")[1].split(" mm")[0]) > 25.0


def test_an_insertion_beyond_the_cm_is_refused(case: NavigationCase) -> None:
    reach = insertion_limit_mm(case.cm_config, CFG)
    assert reach == case.cm_config.tip_z_mm == 31.0
    ok = dataclasses.replace(case.plan, insertion_depth_mm=20.0)
    assert check_plan(ok, case.volume, "left", case.cm_config, CFG) == []
    deep = dataclasses.replace(case.plan, insertion_depth_mm=40.0)  # still inside the neck
    f = _one(check_plan(deep, case.volume, "left", case.cm_config, CFG), "insertion_depth")
    assert _checks(check_plan(deep, case.volume, "left", case.cm_config, CFG)) == ["insertion_depth"]
    assert "40 mm" in f.reason and "31 mm" in f.reason
    # a site's own limit below the CM's reach
    site = dataclasses.replace(CFG, max_insertion_depth_mm=10.0)
    assert insertion_limit_mm(case.cm_config, site) == 10.0
    assert _checks(check_plan(ok, case.volume, "left", case.cm_config, site)) == ["insertion_depth"]


def test_a_direction_out_of_the_bone_is_refused(case: NavigationCase) -> None:
    plan = dataclasses.replace(case.plan, direction_world=-case.plan.direction_world)
    f = _one(check_plan(plan, case.volume, "left", case.cm_config, CFG), "direction_into_femur")
    assert "points out of the femur_left label" in f.reason


def test_control_points_beyond_the_cm_are_refused(case: NavigationCase) -> None:
    plan = dataclasses.replace(case.plan, control_points_deg=np.array([0.0, 0.0, 12.0, 0.0, 0.0]))
    f = _one(check_plan(plan, case.volume, "left", case.cm_config, CFG), "control_points")
    assert "control point 2 is 12°" in f.reason


# ----- labels and landmarks ----------------------------------------------------------------------
def test_swapped_pelvis_and_femur_labels_are_bad_input(case: NavigationCase) -> None:
    vol = case.volume.replace(label_names={1: "femur_left", 2: "pelvis", 3: "femur_right"})
    assert check_labels(case.volume, "left", CFG) == []
    f = _one(check_labels(vol, "left", CFG), "landmark_in_femur", "landmark 'femoral_head_left'")
    assert f.kind == "input"
    assert f.reason.endswith(
        "lies in the 'pelvis' label, not in 'femur_left': are the pelvis and femur labels swapped?"
    )
    # the whole preflight stops at the labels: no plan finding measured against the wrong label
    findings = preflight(dataclasses.replace(case, volume=vol), CFG)
    assert {x.kind for x in findings} == {"input"} and "landmark_in_femur" in _checks(findings)


def test_a_moved_head_landmark_is_bad_input(case: NavigationCase) -> None:
    marks = dict(case.volume.landmarks_world)
    marks["femoral_head_left"] = marks["femoral_head_left"] + np.array([0.0, -60.0, 0.0])  # anterior
    f = _one(check_labels(case.volume.replace(landmarks_world=marks), "left", CFG), "landmark_in_femur")
    assert "outside the femur_left label" in f.reason and "LPS or RAS" in f.reason


def test_an_entry_landmark_off_the_bone_is_bad_input(case: NavigationCase) -> None:
    marks = dict(case.volume.landmarks_world)
    marks["entry_left"] = marks["entry_left"] + np.array([0.0, -25.0, 0.0])  # anterior, in soft tissue
    f = _one(check_labels(case.volume.replace(landmarks_world=marks), "left", CFG), "landmark_in_femur")
    assert f.subject == "landmark 'entry_left'"


def test_implausible_label_volumes_are_bad_input(case: NavigationCase) -> None:
    """The label map read with 0.5 mm instead of 2.5 mm voxels: 125× too small."""
    vol = case.volume.replace(spacing_mm=(0.5, 0.5, 0.5))
    findings = [f for f in check_labels(vol, "left", CFG) if f.check == "label_volume"]
    assert [f.subject for f in findings] == ["label 'pelvis'", "label 'femur_left'"]
    assert "plausible for a pelvis" in findings[0].reason


# ----- the images --------------------------------------------------------------------------------
def _with_view(case: NavigationCase, k: int, **changes: object) -> tuple[CaseView, ...]:
    views = list(case.views)
    views[k] = dataclasses.replace(views[k], **changes)  # type: ignore[arg-type]
    return tuple(views)


def test_a_view_given_twice_is_bad_input(case: NavigationCase) -> None:
    assert check_views(case.views, case.verification, CFG) == []
    views = _with_view(case, 1, image=case.views[0].image.copy())
    f = _one(check_views(views, case.verification, CFG), "identical_views")
    assert f.subject == "view 'orbit +20'" and "as view 'AP'" in f.reason


def test_verification_images_that_are_the_first_ones_are_bad_input(case: NavigationCase) -> None:
    assert case.verification is not None
    again = tuple(
        dataclasses.replace(v, image=w.image.copy())
        for v, w in zip(case.verification.views, case.views, strict=True)
    )
    findings = check_views(case.views, VerificationViews(case.verification.joints_deg, again), CFG)
    assert _checks(findings) == ["verification_repeats_views"] * 3
    assert "after the robot moved" in findings[0].reason


@pytest.mark.parametrize("pixel_spacing", [True, False])
def test_a_tenth_of_the_focal_length_is_bad_input(case: NavigationCase, pixel_spacing: bool) -> None:
    cam = case.views[2].camera
    K = cam.K.copy()
    K[0, 0] *= 0.1
    K[1, 1] *= 0.1
    bad = Camera(
        cam.rows, cam.cols, K, cam.camera_from_world, cam.pixel_spacing_mm if pixel_spacing else None
    )
    f = _one(check_views(_with_view(case, 2, camera=bad), None, CFG), "intrinsics")
    assert f.subject == "view 'orbit -15'" and "focal length" in f.reason
    # in mm where the pixel spacing is known, as the detector's span over its distance where not
    assert ("source-to-detector distance of 102 mm" in f.reason) == pixel_spacing
    assert ("times as wide" in f.reason) != pixel_spacing


def test_a_principal_point_off_the_image_is_bad_input(case: NavigationCase) -> None:
    cam = case.views[0].camera
    K = cam.K.copy()
    K[0, 2] = cam.cols + 40.0
    f = _one(
        check_views(
            _with_view(case, 0, camera=Camera(cam.rows, cam.cols, K, cam.camera_from_world)), None, CFG
        ),
        "intrinsics",
    )
    assert "principal point" in f.reason


def test_an_inverted_image_is_bad_input(case: NavigationCase) -> None:
    assert check_intensities(case.views, case.volume, CFG) == []
    im = case.views[1].image
    views = _with_view(case, 1, image=(im.max() + im.min() - im).astype(np.float32))
    f = _one(check_intensities(views, case.volume, CFG), "inverted_image")
    assert f.subject == "view 'orbit +20'" and "MONOCHROME1" in f.reason
    # any increasing grey-level map passes
    views = _with_view(case, 1, image=np.sqrt(im - im.min() + 0.1).astype(np.float32))
    assert check_intensities(views, case.volume, CFG) == []


def test_mirrored_images_are_told_from_inverted_ones(case: NavigationCase) -> None:
    """A mirrored image correlates negatively with the DRR too; its mirror explains it better than
    its inverse, so it is not called inverted. One mirrored view is left to the bones' per-view
    checks; every view mirrored is the detector's orientation, bad input naming it."""
    one = _with_view(case, 1, image=np.ascontiguousarray(case.views[1].image[:, ::-1]))
    assert check_intensities(one, case.volume, CFG) == []
    every = tuple(dataclasses.replace(v, image=np.ascontiguousarray(v.image[:, ::-1])) for v in case.views)
    f = _one(check_intensities(every, case.volume, CFG), "mirrored_images")
    assert f.subject == "all 3 views" and "detector orientation" in f.reason
    # an inverted view is still called inverted: its inverse explains it better than its mirror
    im = case.views[1].image
    views = _with_view(case, 1, image=(im.max() + im.min() - im).astype(np.float32))
    assert _checks(check_intensities(views, case.volume, CFG)) == ["inverted_image"]


# ----- exits -------------------------------------------------------------------------------------
def test_input_findings_raise_an_input_error_and_plan_findings_do_not() -> None:
    plan = PreflightFinding("plan", "plan 'x'", "plan 'x': the target lies far outside", "target_in_femur")
    raise_for_input([plan], "case.json")
    bad = [
        PreflightFinding("input", "view 'a'", "view 'a' looks inverted", "inverted_image"),
        PreflightFinding("input", "view 'b'", "view 'b' looks inverted", "inverted_image"),
    ]
    with pytest.raises(
        InputError, match=r"^case\.json: view 'a' looks inverted \(and 1 more input problem"
    ) as exc:
        raise_for_input([plan, *bad], "case.json")
    assert (
        isinstance(exc.value, PreflightInputError) and exc.value.check == "inverted_image"
    )  # the first finding's check, for whoever counts them


def test_a_plan_finding_comes_after_the_input_findings(case: NavigationCase) -> None:
    p = case.plan
    far = Plan(p.target_name, p.entry_point_world_mm + 300.0 * p.direction_world, p.direction_world)
    views = _with_view(case, 1, image=case.views[0].image.copy())
    findings = preflight(dataclasses.replace(case, plan=far, views=views), CFG)
    kinds = [f.kind for f in findings]
    assert kinds == sorted(kinds) and kinds[0] == "input" and kinds[-1] == "plan"


def test_the_bench_times_the_whole_preflight_and_its_cross_checks(case: NavigationCase) -> None:
    from fluoronav.bench.navigation import preflight_times

    times = preflight_times(case, repeats=1)
    assert set(times) == {"preflight_s", "preflight_cross_checks_s"}
    assert all(np.isfinite(v) and v > 0.0 for v in times.values())
