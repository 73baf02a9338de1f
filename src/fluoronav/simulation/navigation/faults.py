"""Input faults injected into a simulated navigation case (``fluoronav study navigation --fault``).

Each fault of :data:`FAULTS` is one way a user's inputs can be wrong (an image mirrored or
inverted, a wrong focal length, swapped labels, a plan in soft tissue, a hand-eye matrix or joint
readings that lie, verification images taken before the move). The navigation must, for each,
leave the faulty view out and land within 2 mm of the plan, or refuse naming the fault; it must
never command the robot from a registration more than 2 mm off. :class:`Fault` says what a fault
does and which outcomes handle it (:attr:`Fault.handled_by`: a check name, or ``"stage:check"``
where the name alone is ambiguous; one view's ``detection_or_kinematics`` names the kinematics
among two causes); the functions here apply the case-level faults (pure: a new case). The faults
that need other images, and the hand-eye fault, are driven by the loop from the :class:`Fault` fields.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import numpy as np

from fluoronav.anatomy.volume import Volume
from fluoronav.errors import InputError
from fluoronav.geometry.camera import Camera
from fluoronav.navigation.case.model import NavigationCase, VerificationViews
from fluoronav.navigation.case.view import CaseView
from fluoronav.navigation.planning import Plan

__all__ = [
    "FAULTS",
    "LANDING_MM",
    "VIEW_BLAMING_CHECKS",
    "Fault",
    "Outcome",
    "apply_case_fault",
    "apply_first_fault",
    "apply_verification_fault",
    "deepen_plan",
    "fault_outcome",
    "get_fault",
    "invert_image",
    "mirror_view",
    "names_fault",
    "offset_fbg_reading",
    "offset_joint_reading",
    "scale_ct",
    "scale_focal_length",
    "swap_labels",
    "view_without_cm",
]

#: where a fault is applied: the first views, the verification, the case's CT or plan, or the
#: simulated scene's settings (the hand-eye matrix)
Where = Literal["none", "first_views", "verification", "case", "scene"]


@dataclass(frozen=True)
class Fault:
    """One input fault and what handling it means.

    Attributes:
        name: the ``--fault`` name.
        description: what is done to the simulated case, in one line.
        where: what it changes (:data:`Where`).
        handled_by: the refusal checks that name it (``"check"`` or ``"stage:check"``).
        leave_out_counts: a run that leaves the faulty view out (``view_index``) and lands within
            2 mm of the plan handles it.
        landing_counts: any run with status ok that lands within 2 mm handles it (a navigation that
            corrects the fault's effect, e.g. the verification's corrective move).
        view_index: the first view the fault changes (into ``case.views``); None: none or all.
        mirror: flip the images of ``view_index`` (None: every first view) left-right.
        invert: every first view's image → max − image (MONOCHROME1 read as MONOCHROME2).
        focal_scale: the case's camera of ``view_index`` has its focal length scaled by this.
        without_cm: the image of ``view_index`` is simulated without the CM.
        verify_joint_offset_deg: (joint index, degrees) added to the verification's joint reading.
        verify_images_before_move: the verification images show the CM where it was before the move.
        swap_labels: the pelvis and the case side's femur labels exchanged.
        plan_deeper_mm: the plan's target moved this far along its insertion direction.
        handeye_error_mm: the hand-eye matrix's translation error (mm) unless the study gives one.
        mirror_labels: the label map flipped left-right (the CT and the landmarks unchanged).
        shift_labels_mm: the label map shifted this far along the CT's first axis (x).
        fbg_beyond_deg: the FBG reading's first control point set this far beyond the CM's bend.
        plan_other_femur: the plan moved by the vector between the femoral heads (the case's
            ``side`` unchanged), as a plan made on the other femur.
        fbg_offset_deg: added to every control point of the FBG reading (a sensor whose calibration
            was lost), alternately + and − where ``fbg_alternate`` (a reading of another shape);
            kept within the CM's range.
        ct_scale: the CT's spacing read this many times the true one, its labels, landmarks and plan
            made in that frame (a wrong spacing or unit in the file).
        other_patient: the image of ``view_index`` is another patient's (the next phantom seed), the CM
            and the C-arm where they are.
    """

    name: str
    description: str
    where: Where
    handled_by: tuple[str, ...] = ()
    leave_out_counts: bool = False
    landing_counts: bool = False
    view_index: int | None = None
    mirror: bool = False
    invert: bool = False
    focal_scale: float | None = None
    without_cm: bool = False
    verify_joint_offset_deg: tuple[int, float] | None = None
    verify_images_before_move: bool = False
    swap_labels: bool = False
    plan_deeper_mm: float | None = None
    handeye_error_mm: float | None = None
    mirror_labels: bool = False
    shift_labels_mm: float | None = None
    fbg_beyond_deg: float | None = None
    plan_other_femur: bool = False
    fbg_offset_deg: float | None = None
    fbg_alternate: bool = False
    ct_scale: float | None = None
    other_patient: bool = False


#: the fault catalogue, by name (``none``: the baseline)
FAULTS: dict[str, Fault] = {
    f.name: f
    for f in (
        Fault("none", "no fault (the baseline)", "none", landing_counts=True),
        Fault(
            "mirror_one",
            "the second first view's image flipped left-right, its camera unchanged",
            "first_views",
            handled_by=("mirrored",),
            leave_out_counts=True,
            view_index=1,
            mirror=True,
        ),
        Fault(
            "mirror_all",
            "every first view's image flipped left-right, the cameras unchanged",
            "first_views",
            handled_by=("mirrored", "mirrored_images"),
            mirror=True,
        ),
        Fault(
            "focal_10pct",
            "the second first view's camera has a 10 % longer focal length than its image was made with",
            "first_views",
            handled_by=("intrinsics",),
            leave_out_counts=True,
            view_index=1,
            focal_scale=1.1,
        ),
        Fault(
            "verify_joints_3deg",
            "the verification's joint 2 reading 3° off; the robot is at the commanded joints",
            "verification",
            handled_by=("joint_readings", "kinematics_disagree", "detection_or_kinematics"),
            verify_joint_offset_deg=(1, 3.0),
        ),
        Fault(
            "handeye_10mm",
            "the case's hand-eye matrix is the truth moved by 10 mm",
            "scene",
            handled_by=("kinematics_disagree", "detection_or_kinematics"),
            landing_counts=True,
            handeye_error_mm=10.0,
        ),
        Fault(
            "verify_no_move",
            "the verification images show the CM where it was before the move",
            "verification",
            handled_by=("kinematics_disagree", "detection_or_kinematics"),
            verify_images_before_move=True,
        ),
        Fault(
            "view_without_cm",
            "the second first view simulated without the CM",
            "first_views",
            handled_by=("views_with_cm", "cm:landmark_residual", "cm:edge_ncc"),
            leave_out_counts=True,
            view_index=1,
            without_cm=True,
        ),
        Fault(
            "labels_swapped",
            "the case's pelvis and femur labels exchanged",
            "case",
            handled_by=("label_volume", "landmark_in_femur"),
            swap_labels=True,
        ),
        Fault(
            "plan_inward_300",
            "the plan's target moved 300 mm deeper along its insertion direction",
            "case",
            handled_by=("target_in_femur", "insertion_depth"),
            plan_deeper_mm=300.0,
        ),
        Fault(
            "labels_mirrored",
            "the case's label map flipped left-right against its CT and landmarks",
            "case",
            handled_by=("labels_mirrored", "labels_on_bone", "landmark_in_femur"),
            mirror_labels=True,
        ),
        Fault(
            "labels_shifted_5mm",
            "the case's label map shifted 5 mm along the CT's x axis",
            "case",
            handled_by=("labels_on_bone",),
            shift_labels_mm=5.0,
        ),
        Fault(
            "fbg_beyond_range",
            "the FBG reading's first control point 2° beyond the CM's bend",
            "case",
            handled_by=("fbg_range",),
            fbg_beyond_deg=2.0,
        ),
        Fault(
            "plan_other_femur",
            "the plan made on the other femur, the case's side unchanged",
            "case",
            handled_by=("plan_side",),
            plan_other_femur=True,
        ),
        Fault(
            "fbg_bent_3deg",
            "the FBG reading 3° off at every control point (its calibration lost)",
            "case",
            handled_by=("fbg_reading",),
            fbg_offset_deg=3.0,
        ),
        Fault(
            "fbg_other_shape",
            "the FBG reading of another shape: its control points 5° off, alternately + and −",
            "case",
            handled_by=("fbg_reading",),
            fbg_offset_deg=5.0,
            fbg_alternate=True,
        ),
        Fault(
            "ct_spacing_110",
            "the CT's spacing read 10 % too large, its labels, landmarks and plan made in that frame",
            "case",
            handled_by=("ct_scale",),
            ct_scale=1.1,
        ),
        Fault(
            "ct_spacing_090",
            "the CT's spacing read 10 % too small, its labels, landmarks and plan made in that frame",
            "case",
            handled_by=("ct_scale",),
            ct_scale=0.9,
        ),
        Fault(
            "view_other_patient",
            "the second first view's image is another patient's, with the CM and the C-arm where they are",
            "first_views",
            handled_by=("pelvis:edge_ncc", "femur:edge_ncc", "cm:odd_view"),
            leave_out_counts=True,
            view_index=1,
            other_patient=True,
        ),
        Fault(
            "inverted",
            "every first view's intensities inverted (MONOCHROME1 read as MONOCHROME2)",
            "first_views",
            handled_by=("inverted_image",),
            invert=True,
        ),
    )
}


def get_fault(name: str | None) -> Fault | None:
    """The catalogue's fault ``name``; None for None.

    Raises:
        InputError: an unknown name (``--fault``), listing the known ones.
    """
    if name is None:
        return None
    if name not in FAULTS:
        raise InputError("--fault", f"unknown fault {name!r}; one of: {', '.join(FAULTS)}")
    return FAULTS[name]


#: refusal checks that blame one view as the cause (not only as the worst fitted)
VIEW_BLAMING_CHECKS = ("odd_view",)


def names_fault(fault: Fault, stage: str, check: str) -> bool:
    """Whether a refusal at ``stage`` with ``check`` names ``fault`` (:attr:`Fault.handled_by`)."""
    return check in fault.handled_by or f"{stage}:{check}" in fault.handled_by


# ----- one view, one camera, one volume, one plan ------------------------------------------------
def mirror_view(view: CaseView) -> CaseView:
    """The view with its image flipped left-right and the same camera; given landmarks (u → cols − 1 − u)
    and mask flipped with it (what a user would give with the flipped image)."""
    cols = view.image.shape[1]
    lm = None
    if view.landmarks_px is not None:
        lm = np.asarray(view.landmarks_px, np.float64).copy()
        lm[:, 0] = cols - 1 - lm[:, 0]
    mask = None if view.mask is None else np.fliplr(view.mask).copy()
    return dataclasses.replace(view, image=np.fliplr(view.image).copy(), landmarks_px=lm, mask=mask)


def invert_image(view: CaseView) -> CaseView:
    """The view with its image → max − image (a MONOCHROME1 image read as MONOCHROME2)."""
    image = np.asarray(view.image)
    return dataclasses.replace(view, image=(image.max() - image).astype(image.dtype))


def scale_focal_length(camera: Camera, factor: float) -> Camera:
    """The camera with its focal lengths (fx, fy) scaled by ``factor``: the source-to-detector
    distance ``factor`` times longer at the same pixel spacing and principal point."""
    K = np.asarray(camera.K, np.float64).copy()
    K[0, 0] *= factor
    K[1, 1] *= factor
    return Camera(camera.rows, camera.cols, K, camera.camera_from_world, camera.pixel_spacing_mm)


def swap_labels(volume: Volume, a: str, b: str) -> Volume:
    """A copy of ``volume`` whose label map has the voxels of labels ``a`` and ``b`` exchanged (the
    names stay with their values: what was ``a`` is now read as ``b``)."""
    va, vb = volume.label_value(a), volume.label_value(b)
    if volume.labels is None or va is None or vb is None:
        raise ValueError(f"the volume has no labels {a!r} and {b!r} to swap")
    labels = volume.labels.copy()
    labels[volume.labels == va] = vb
    labels[volume.labels == vb] = va
    return volume.replace(labels=labels)


def mirror_labels(volume: Volume) -> Volume:
    """A copy of ``volume`` whose label map is flipped along the x index axis (left-right)."""
    if volume.labels is None:
        raise ValueError("the volume has no labels to mirror")
    return volume.replace(labels=np.ascontiguousarray(volume.labels[:, :, ::-1]))


def shift_labels(volume: Volume, mm: float) -> Volume:
    """A copy of ``volume`` whose label map is moved ``mm`` along the x index axis (whole voxels,
    background shifted in)."""
    if volume.labels is None:
        raise ValueError("the volume has no labels to shift")
    k = round(mm / float(volume.spacing_mm[0]))
    labels = np.zeros_like(volume.labels)
    if k >= 0:
        labels[:, :, k:] = volume.labels[:, :, : labels.shape[2] - k]
    else:
        labels[:, :, :k] = volume.labels[:, :, -k:]
    return volume.replace(labels=labels)


def fbg_beyond_range(
    reading_deg: np.ndarray | None, n: int, max_bend_deg: float, beyond_deg: float
) -> np.ndarray:
    """The FBG reading (straight where None) with its first control point ``beyond_deg`` past
    ``max_bend_deg``."""
    q = np.zeros(n) if reading_deg is None else np.asarray(reading_deg, np.float64).copy()
    q[0] = max_bend_deg + beyond_deg
    return q


def offset_fbg_reading(
    reading_deg: np.ndarray | None, n: int, offset_deg: float, *, alternate: bool, limit_deg: float
) -> np.ndarray:
    """The FBG reading (straight where None) with ``offset_deg`` added to each control point
    (alternately + and − where ``alternate``), within ±``limit_deg``; where the limit takes part of a
    point's offset, the point goes the other way instead."""
    q = np.zeros(n) if reading_deg is None else np.asarray(reading_deg, np.float64).copy()
    sign = np.where(np.arange(n) % 2 == 1, -1.0, 1.0) if alternate else np.ones(n)
    moved = q + sign * offset_deg
    other = q - sign * offset_deg
    return np.where(np.abs(moved) <= limit_deg, moved, np.clip(other, -limit_deg, limit_deg))


def scale_ct(case: NavigationCase, factor: float) -> NavigationCase:
    """``case`` with its CT's spacing read ``factor`` times the true one: every point made in the CT's
    frame (landmarks, the plan's entry and depth) scaled about the CT's origin with it, each view's
    initial camera moved with the femoral-head landmark (its isocentre)."""
    vol = case.volume
    origin = np.asarray(vol.origin_mm, np.float64)

    def scaled(p: np.ndarray) -> np.ndarray:
        return origin + factor * (np.asarray(p, np.float64) - origin)

    landmarks = {k: scaled(v) for k, v in vol.landmarks_world.items()}
    volume = vol.replace(spacing_mm=tuple(factor * s for s in vol.spacing_mm), landmarks_world=landmarks)
    plan = dataclasses.replace(
        case.plan,
        entry_point_world_mm=scaled(case.plan.entry_point_world_mm),
        insertion_depth_mm=factor * float(case.plan.insertion_depth_mm),
    )
    head = vol.landmarks_world.get(f"femoral_head_{case.side}")
    shift = np.zeros(3) if head is None else scaled(head) - np.asarray(head, np.float64)

    def moved(v: CaseView) -> CaseView:
        c = v.camera
        camera_from_ct = np.asarray(c.camera_from_world, np.float64).copy()
        camera_from_ct[:3, 3] -= camera_from_ct[:3, :3] @ shift
        return dataclasses.replace(v, camera=Camera(c.rows, c.cols, c.K, camera_from_ct, c.pixel_spacing_mm))

    verification = case.verification
    if verification is not None:
        verification = dataclasses.replace(verification, views=tuple(moved(v) for v in verification.views))
    return dataclasses.replace(
        case,
        volume=volume,
        plan=plan,
        views=tuple(moved(v) for v in case.views),
        verification=verification,
    )


def plan_on_other_femur(plan: Plan, volume: Volume, side: str) -> Plan:
    """The plan moved by the vector from the ``side`` femur label's centroid to the other one's."""
    other = "right" if side == "left" else "left"
    values = [volume.label_value(f"femur_{s}") for s in (side, other)]
    if volume.labels is None or None in values:
        raise ValueError("the volume has no labels of both femurs")
    here, there = (np.argwhere(volume.labels == v)[:, ::-1].mean(axis=0) for v in values)  # (i, j, k)
    shift = volume.world_from_index[:3, :3] @ (there - here)
    return dataclasses.replace(
        plan, entry_point_world_mm=np.asarray(plan.entry_point_world_mm, np.float64) + shift
    )


def deepen_plan(plan: Plan, mm: float) -> Plan:
    """The plan with its target ``mm`` further along its own insertion direction (the entry kept)."""
    return dataclasses.replace(plan, insertion_depth_mm=float(plan.insertion_depth_mm) + float(mm))


def offset_joint_reading(verification: VerificationViews, joint: int, deg: float) -> VerificationViews:
    """The verification with ``deg`` added to joint ``joint``'s reading (0-based)."""
    q = np.asarray(verification.joints_deg, np.float64).copy()
    q[joint] += deg
    return dataclasses.replace(verification, joints_deg=q)


def view_without_cm(view: CaseView, image: np.ndarray) -> CaseView:
    """The view with ``image`` (made without the CM) and no given landmarks or mask."""
    return dataclasses.replace(view, image=np.asarray(image, np.float32), landmarks_px=None, mask=None)


# ----- a case --------------------------------------------------------------------------------------
def _indices(fault: Fault, n: int) -> list[int]:
    return list(range(n)) if fault.view_index is None else [fault.view_index]


def apply_first_fault(case: NavigationCase, fault: Fault | None) -> NavigationCase:
    """``case`` with the fault's changes to its first views (mirror, invert, focal length); the
    image without the CM is :func:`view_without_cm`, made by the simulation."""
    if fault is None or not (fault.mirror or fault.invert or fault.focal_scale is not None):
        return case
    views = list(case.views)
    for k in _indices(fault, len(views)):
        v = views[k]
        if fault.mirror:
            v = mirror_view(v)
        if fault.invert:
            v = invert_image(v)
        if fault.focal_scale is not None:
            v = dataclasses.replace(v, camera=scale_focal_length(v.camera, fault.focal_scale))
        views[k] = v
    return dataclasses.replace(case, views=tuple(views))


def apply_case_fault(case: NavigationCase, fault: Fault | None) -> NavigationCase:
    """``case`` with the fault's changes to its CT labels or its plan."""
    if fault is None or fault.where != "case":
        return case
    if fault.swap_labels:
        case = dataclasses.replace(case, volume=swap_labels(case.volume, "pelvis", f"femur_{case.side}"))
    if fault.plan_deeper_mm is not None:
        case = dataclasses.replace(case, plan=deepen_plan(case.plan, fault.plan_deeper_mm))
    if fault.mirror_labels:
        case = dataclasses.replace(case, volume=mirror_labels(case.volume))
    if fault.shift_labels_mm is not None:
        case = dataclasses.replace(case, volume=shift_labels(case.volume, fault.shift_labels_mm))
    if fault.fbg_beyond_deg is not None:
        n = case.cm_config.n_control_points
        q = fbg_beyond_range(
            case.fbg_control_points_deg, n, case.cm_config.max_bend_deg, fault.fbg_beyond_deg
        )
        case = dataclasses.replace(case, fbg_control_points_deg=q)
    if fault.plan_other_femur:
        case = dataclasses.replace(case, plan=plan_on_other_femur(case.plan, case.volume, case.side))
    if fault.fbg_offset_deg is not None:
        cmc = case.cm_config
        q = offset_fbg_reading(
            case.fbg_control_points_deg,
            cmc.n_control_points,
            fault.fbg_offset_deg,
            alternate=fault.fbg_alternate,
            limit_deg=max(abs(r) for r in cmc.control_point_range_deg),
        )
        case = dataclasses.replace(case, fbg_control_points_deg=q)
    if fault.ct_scale is not None:
        case = scale_ct(case, fault.ct_scale)
    return case


def apply_verification_fault(case: NavigationCase, fault: Fault | None) -> NavigationCase:
    """``case`` with the fault's changes to its verification's joint readings (the images taken
    before the move are made by the simulation)."""
    if fault is None or fault.verify_joint_offset_deg is None or case.verification is None:
        return case
    joint, deg = fault.verify_joint_offset_deg
    return dataclasses.replace(case, verification=offset_joint_reading(case.verification, joint, deg))


# ----- outcomes ------------------------------------------------------------------------------------
#: a navigation lands when its final true tip is within this of the plan; a robot command from a
#: first registration whose CM tip is further than this from the truth is unsafe
LANDING_MM = 2.0

Outcome = Literal["landed", "refused_named", "refused_other", "unsafe", "failed"]


def fault_outcome(
    fault: Fault,
    *,
    status: str,
    stage: str = "",
    check: str = "",
    final_tip_mm: float | None = None,
    first_tip_mm: float | None = None,
    commanded: bool = False,
    left_out: tuple[str, ...] = (),
    faulty_view: str | None = None,
    refused_view: str = "",
) -> tuple[Outcome, bool]:
    """What a run with ``fault`` ended as, and whether that handled the fault.

    Args:
        fault: the injected fault.
        status: the run's status: ``"ok"``, ``"refused"``, ``"input_error"`` or ``"failed"``.
        stage, check: the refusal's stage and check (refused or input error).
        final_tip_mm: the true tip's distance to the plan after the last move (mm).
        first_tip_mm: the first registration's CM tip error against the truth (mm).
        commanded: the robot carried out the first command.
        left_out: the views the navigation left out; faulty_view: the view the fault changed.
        refused_view: the view the refusal names ("" for none); a check that blames one view
            (:data:`VIEW_BLAMING_CHECKS`) names the fault only where it is the faulty view.

    Returns:
        (outcome, handled). ``"unsafe"``: a first command from a registration more than
        :data:`LANDING_MM` off (whatever the verification said after it), or status ok with the
        final tip more than :data:`LANDING_MM` from the plan; ``"landed"``: status ok otherwise;
        ``"refused_named"`` / ``"refused_other"``: a refusal or input error whose check does or does
        not name the fault (:attr:`Fault.handled_by`); ``"failed"``: the run crashed or cannot be judged.
    """
    if status == "failed":
        return "failed", False
    if commanded and first_tip_mm is not None and not first_tip_mm <= LANDING_MM:
        return "unsafe", False
    if status == "ok":
        if final_tip_mm is None or not np.isfinite(final_tip_mm):
            return "failed", False
        if final_tip_mm > LANDING_MM:
            return "unsafe", False
        left = faulty_view is not None and faulty_view in left_out
        return "landed", fault.landing_counts or (fault.leave_out_counts and left)
    blames_other = check in VIEW_BLAMING_CHECKS and faulty_view is not None and refused_view != faulty_view
    if names_fault(fault, stage, check) and not blames_other:
        return "refused_named", True
    return "refused_other", False
