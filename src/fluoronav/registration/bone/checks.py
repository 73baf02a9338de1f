"""Whether a bone registration can be trusted in a view: per-view diagnostics, verdicts, the mirror.

Two measures per view, computable without the truth, from one DRR of the registered bone at a working
resolution (:attr:`BoneCheckConfig.image_px`, the registration's excess-μ volume): ``edge_ncc``, the gradient
NCC of the image and the DRR on the DRR's dilated outline (near 1 where the registered outline lies on the
bone, lower where it settled beside it), and ``grad_ncc``, the gradient NCC over the whole used image (how
much of the image's structure the bone explains; independent of the registration's levels, so one bound serves
every preset). A view whose pelvis fails is registered once more on its left–right mirrored image at a coarse
level (:attr:`BoneCheckConfig.mirror_level`): where the mirror fits clearly better and passes, the view is
named as mirrored (the detector's orientation is wrong). The thresholds are :class:`BoneCheckConfig`;
docs/validation.md ("Per-view bone checks") gives the data they rest on.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch

from fluoronav.anatomy.volume import Volume
from fluoronav.errors import RegistrationRefused
from fluoronav.registration.bone.levels import bone_excess_mu, box_downsample
from fluoronav.registration.bone.presets import BoneRegistrationConfig
from fluoronav.registration.bone.register import BoneRegistrationResult, register_pelvis_per_view
from fluoronav.registration.bone.views import BoneView
from fluoronav.registration.similarity import edge_ncc, grad_ncc
from fluoronav.rendering.ct import CTRenderer

log = logging.getLogger(__name__)

__all__ = [
    "BoneCheckConfig",
    "BoneVerdict",
    "BoneViewDiagnostics",
    "bone_view_diagnostics",
    "judge_bone_view",
    "judge_pelvis_views",
    "mirrored_view",
    "pelvis_mirror_diagnosis",
    "register_femur_checked",
]


@dataclass(frozen=True)
class BoneCheckConfig:
    """Thresholds of the per-view checks of a bone registration.

    Attributes:
        min_edge_ncc: a view's gradient NCC (−1 … 1) on the registered bone's outline must reach
            this. Correct registrations of simulated views sit well above, mirrored views, views of
            another scene and views with a wrong camera well below (docs/validation.md).
        min_grad_ncc: a view's gradient NCC (−1 … 1) of the whole image and the registered bone's
            DRR must reach this; None (the default): recorded, not judged. Correct pelvis
            registrations of 768² verification views, centred on the hip, reach as low as mirrored
            views do, so it does not separate them (docs/validation.md).
        min_femur_edge_ncc: as ``min_edge_ncc``, for the femur's outline in each view after the
            femur registration (a smaller bone, partly over the pelvis: a lower bound).
        mirror_margin: a failed view is named as mirrored where its mirrored image passes and its
            edge NCC exceeds the image's by at least this.
        min_views: views whose bones must pass for the femur and the CM to be registered.
        image_px: the working image side (px) of the checks' DRRs (the image binned to it).
        voxel_mm: the voxel size (mm) of the checks' DRR volume (box-downsampled).
        edge_dilate_px: the outline's dilation (working px).
        mirror_level: index into the pelvis registration's levels of the one level the mirror
            diagnosis runs (the coarse one: it need only find the basin).
    """

    min_edge_ncc: float = 0.5
    min_grad_ncc: float | None = None
    min_femur_edge_ncc: float = 0.4
    mirror_margin: float = 0.15
    min_views: int = 2
    image_px: int = 96
    voxel_mm: float = 2.0
    edge_dilate_px: int = 1
    mirror_level: int = 0


@dataclass(frozen=True)
class BoneViewDiagnostics:
    """One view's agreement with a registered bone: ``edge_ncc`` and ``grad_ncc`` (module docstring)."""

    edge_ncc: float
    grad_ncc: float

    def to_dict(self) -> dict[str, float]:
        return {"edge_ncc": self.edge_ncc, "grad_ncc": self.grad_ncc}


@dataclass(frozen=True)
class BoneVerdict:
    """A view's bone checks: ``passed``, and the failed ``check`` with its one-line ``detail`` otherwise."""

    view: str
    passed: bool
    check: str = ""
    detail: str = ""


def bone_view_diagnostics(
    views: Sequence[BoneView],
    volume: Volume,
    label: str,
    camera_from_bone: np.ndarray,
    config: BoneCheckConfig,
) -> list[BoneViewDiagnostics]:
    """Per view: the registered bone's edge NCC and gradient NCC against the image.

    Args:
        views: the images and their cameras (intrinsics; the pose is ``camera_from_bone``).
        volume: labelled CT.
        label: the bone's label ("pelvis", "femur_left", ...).
        camera_from_bone: (V, 4, 4) the registered bone seen from each view (the CT's copy of the
            bone placed by it).
        config: the working resolution and the outline's dilation.
    """
    mu, world_from_index = bone_excess_mu(volume, [label])
    spacing = float(np.linalg.norm(world_from_index[:3, :3], axis=0).min())
    vf = max(1, int(np.floor(config.voxel_mm / spacing + 1e-6)))
    renderer = CTRenderer.from_tensor(*box_downsample(torch.from_numpy(mu), world_from_index, vf))
    T = np.asarray(camera_from_bone, np.float64).reshape(-1, 4, 4)
    out = []
    for v, pose in zip(views, T, strict=True):
        f = max(1, round(v.camera.cols / config.image_px))
        cam = v.camera.downsample(f)
        binned, used = v.binned(f)
        image = torch.as_tensor(binned)
        use = None if used is None else torch.as_tensor(used)
        drr = renderer.render_poses(cam.K, pose, cam.rows, cam.cols)[0].to(torch.float64).numpy()
        whole = float(grad_ncc(image, torch.as_tensor(drr)[None], mask=use)[0])
        out.append(
            BoneViewDiagnostics(
                edge_ncc=edge_ncc(image, drr, mask=use, dilate_px=config.edge_dilate_px),
                grad_ncc=1.0 - whole if np.isfinite(whole) else 0.0,
            )
        )
    return out


def judge_bone_view(
    name: str,
    bone: str,
    diagnostics: BoneViewDiagnostics,
    *,
    min_edge_ncc: float,
    min_grad_ncc: float | None = None,
) -> BoneVerdict:
    """Does the registered ``bone`` agree with view ``name``? (its edge NCC against ``min_edge_ncc``,
    its gradient NCC against ``min_grad_ncc``; None: not judged, as for a bone that explains little
    of the image, the femur)."""
    d = diagnostics
    if d.edge_ncc < min_edge_ncc:
        return BoneVerdict(
            name,
            False,
            "edge_ncc",
            f"the registered {bone}'s outline matches view {name} with NCC {d.edge_ncc:.2f} "
            f"(at least {min_edge_ncc:.2f})",
        )
    if min_grad_ncc is not None and d.grad_ncc < min_grad_ncc:
        return BoneVerdict(
            name,
            False,
            "grad_ncc",
            f"the registered {bone} explains view {name}'s edges with NCC {d.grad_ncc:.2f} "
            f"(at least {min_grad_ncc:.2f})",
        )
    return BoneVerdict(name, True)


def mirrored_view(view: BoneView) -> BoneView:
    """The view with its image (and mask) mirrored left–right and the same camera."""
    mask = None if view.mask is None else np.ascontiguousarray(np.asarray(view.mask)[:, ::-1])
    return BoneView(np.ascontiguousarray(np.asarray(view.image)[:, ::-1]), view.camera, mask)


def pelvis_mirror_diagnosis(
    view: BoneView,
    volume: Volume,
    diagnostics: BoneViewDiagnostics,
    *,
    initial_world_from_patient: np.ndarray,
    pelvis: BoneRegistrationConfig,
    config: BoneCheckConfig,
    seed: int,
) -> tuple[bool, BoneViewDiagnostics]:
    """Does the view's mirrored image fit the pelvis clearly better? (a coarse pelvis registration on
    it from the same start; see the module docstring).

    Returns:
        (mirrored, the mirrored image's diagnostics).
    """
    level = pelvis.levels[min(config.mirror_level, len(pelvis.levels) - 1)]
    flipped = mirrored_view(view)
    (res,) = register_pelvis_per_view(
        [flipped],
        volume,
        initial_world_from_patient=initial_world_from_patient,
        config=replace(pelvis, levels=(level,), starts=(), keep=1),
        seed=seed,
    )
    (d,) = bone_view_diagnostics([flipped], volume, "pelvis", res.camera_from_bone, config)
    ok = judge_bone_view(
        "", "pelvis", d, min_edge_ncc=config.min_edge_ncc, min_grad_ncc=config.min_grad_ncc
    ).passed
    return ok and d.edge_ncc >= diagnostics.edge_ncc + config.mirror_margin, d


def judge_pelvis_views(
    views: Sequence[BoneView],
    volume: Volume,
    pelvis: Sequence[BoneRegistrationResult],
    names: Sequence[str],
    config: BoneCheckConfig,
    *,
    initial_world_from_patient: np.ndarray,
    pelvis_config: BoneRegistrationConfig,
    seed: int,
    record: dict[str, dict[str, Any]],
) -> tuple[list[int], dict[str, str]]:
    """Each view's pelvis registration checked; a failed view diagnosed for a mirrored image.

    Args:
        views, pelvis, names: the views, their pelvis registrations and their names.
        volume: labelled CT.
        config: thresholds.
        initial_world_from_patient: (4, 4) or (V, 4, 4) the registrations' start (the mirror's).
        pelvis_config: the pelvis registration's levels (the mirror runs one of them).
        seed: the pelvis registration's seed (view k's is ``seed + 101 k``, the mirror's too).
        record: per view name, filled in place with ``edge_ncc``, ``grad_ncc`` and, where the view
            failed, ``check``, ``detail`` and ``mirrored_edge_ncc``.

    Returns:
        The indices of the views that passed, and the failed views' reasons (name → one line).

    Raises:
        RegistrationRefused: (stage "pelvis") fewer than ``min_views`` views passed (every view
            where fewer were given), naming the first view that failed.
    """
    W0 = np.asarray(initial_world_from_patient, np.float64)
    starts = np.broadcast_to(W0, (len(views), 4, 4)) if W0.ndim == 2 else W0
    kept: list[int] = []
    failed: list[BoneVerdict] = []
    poses = np.stack([r.camera_from_bone[0] for r in pelvis])
    diagnostics = bone_view_diagnostics(views, volume, "pelvis", poses, config)
    for k, (name, v, d) in enumerate(zip(names, views, diagnostics, strict=True)):
        record.setdefault(name, {}).update(d.to_dict())
        verdict = judge_bone_view(
            name, "pelvis", d, min_edge_ncc=config.min_edge_ncc, min_grad_ncc=config.min_grad_ncc
        )
        if verdict.passed:
            kept.append(k)
            continue
        mirrored, dm = pelvis_mirror_diagnosis(
            v,
            volume,
            d,
            initial_world_from_patient=starts[k],
            pelvis=pelvis_config,
            config=config,
            seed=seed + 101 * k,
        )
        if mirrored:
            verdict = BoneVerdict(
                name,
                False,
                "mirrored",
                f"view {name} looks mirrored left–right: check the detector orientation",
            )
        record[name].update(check=verdict.check, detail=verdict.detail, mirrored_edge_ncc=dm.edge_ncc)
        log.warning("pelvis: view %s left out (%s: %s)", name, verdict.check, verdict.detail)
        failed.append(verdict)
    left_out = {f.view: f"{f.check}: {f.detail}" for f in failed}
    if failed and len(kept) < min(config.min_views, len(views)):
        raise RegistrationRefused("pelvis", failed[0].check, failed[0].detail, failed[0].view)
    return kept, left_out


def register_femur_checked(
    views: Sequence[BoneView],
    names: Sequence[str],
    register: Callable[[Sequence[BoneView]], BoneRegistrationResult],
    volume: Volume,
    side: str,
    config: BoneCheckConfig,
    record: dict[str, Any],
) -> tuple[BoneRegistrationResult, list[int]]:
    """The femur registered (``register(views)``) and checked in each view (its outline's edge NCC);
    views that fail are left out and the femur registered again without them while enough remain.

    Args:
        views, names: the femur's views (in the registration's frame) and their names.
        register: registers the femur to the given views.
        volume, side: labelled CT and the femur's side.
        config: thresholds (``min_femur_edge_ncc``, ``min_views``).
        record: filled in place: ``views`` (name → ``edge_ncc``) and, where views were left out,
            ``left_out`` (name → why).

    Returns:
        The femur registration that passed and the indices of its views.

    Raises:
        RegistrationRefused: (stage "femur") fewer than ``min_views`` views passed (every view
            where fewer were given).
    """
    kept = list(range(len(views)))
    need = min(config.min_views, len(views))
    left_out: dict[str, str] = {}
    while True:
        femur = register([views[k] for k in kept])
        diags = bone_view_diagnostics(
            [views[k] for k in kept], volume, f"femur_{side}", femur.camera_from_bone, config
        )
        record["views"] = {names[k]: {"edge_ncc": d.edge_ncc} for k, d in zip(kept, diags, strict=True)}
        verdicts = [
            judge_bone_view(names[k], "femur", d, min_edge_ncc=config.min_femur_edge_ncc)
            for k, d in zip(kept, diags, strict=True)
        ]
        failed = [(k, v) for k, v in zip(kept, verdicts, strict=True) if not v.passed]
        if not failed:
            break
        for _, v in failed:
            left_out[v.view] = f"{v.check}: {v.detail}"
            log.warning("femur: view %s left out (%s: %s)", v.view, v.check, v.detail)
        if len(kept) - len(failed) < need:
            record["left_out"] = left_out
            raise RegistrationRefused("femur", failed[0][1].check, failed[0][1].detail, failed[0][1].view)
        kept = [k for k in kept if k not in {f for f, _ in failed}]
    if left_out:
        record["left_out"] = left_out
    return femur, kept
