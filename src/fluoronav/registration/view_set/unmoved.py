"""Whether the anatomy stayed where an earlier image of the same C-arm position showed it
(:func:`unmoved_ncc`): the check that lets a verification whose C-arm did not move keep the first
registration's cameras and femur instead of registering the bones again.

Two images of the same C-arm position differ in their quantum noise, in the instrument (which the
masks leave out) and, if the patient or the C-arm moved, in where the bones' edges lie. Their
gradient NCC over the pixels both images use, at a working resolution that averages the noise
away, tells the two apart: docs/validation.md gives the figures the threshold
(:attr:`~fluoronav.registration.view_set.settings.ViewSetSettings.min_unmoved_ncc`) was set on.
"""

from __future__ import annotations

import numpy as np
import torch

from fluoronav.registration.bone import BoneView
from fluoronav.registration.similarity import grad_ncc
from fluoronav.registration.view_set.bones import ViewSetBones
from fluoronav.registration.view_set.register import ViewSetRegistration
from fluoronav.registration.view_set.views import FluoroView, bone_views

__all__ = ["unmoved_bones", "unmoved_ncc"]


def unmoved_ncc(before: BoneView, after: BoneView, *, image_px: int = 128) -> float:
    """Gradient NCC (−1 … 1) of two images of one C-arm position over the pixels both use (their
    instruments left out), binned to about ``image_px`` pixels a side.

    Raises:
        ValueError: the images differ in size.
    """
    if np.shape(before.image) != np.shape(after.image):
        raise ValueError(f"images of {np.shape(before.image)} and {np.shape(after.image)} pixels")
    f = max(1, round(before.camera.cols / image_px))
    a, use_a = before.binned(f)
    b, use_b = after.binned(f)
    use = None
    if use_a is not None or use_b is not None:
        ones = np.ones(a.shape, bool)
        use = torch.as_tensor((ones if use_a is None else use_a) & (ones if use_b is None else use_b))
    cost = float(grad_ncc(torch.as_tensor(a), torch.as_tensor(b)[None], mask=use)[0])
    return 1.0 - cost


def unmoved_bones(
    views: list[FluoroView], earlier: ViewSetRegistration, same_as: list[int], *, min_ncc: float
) -> tuple[ViewSetBones | None, dict[str, float]]:
    """The earlier registration's bones for views taken from its C-arm positions, where no view's
    anatomy moved.

    Args:
        views: the later views.
        earlier: the earlier registration of the same anatomy.
        same_as: for each later view, the index (into ``earlier.views``) of the view taken from the
            same C-arm position.
        min_ncc: each pair's :func:`unmoved_ncc` must reach this.

    Returns:
        The earlier bones for these views (its pelvis results and cameras, its femur), or None where
        a pair's images disagree (the patient or the C-arm moved: register the bones again); and
        each later view's NCC by name.
    """
    before = bone_views([earlier.views[i] for i in same_as])
    after = bone_views(views)
    ncc = {v.name: unmoved_ncc(b, a) for v, b, a in zip(views, before, after, strict=True)}
    if min(ncc.values()) < min_ncc:
        return None, ncc
    bones = ViewSetBones(
        pelvis=tuple(earlier.pelvis[i] for i in same_as),
        cameras=tuple(
            v.camera.with_pose(earlier.cameras_ct[i].camera_from_world)
            for v, i in zip(views, same_as, strict=True)
        ),
        femur=earlier.femur,
    )
    return bones, ncc
