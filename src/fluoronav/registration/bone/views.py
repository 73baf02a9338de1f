"""The images of a bone registration (:class:`BoneView`), with the instrument left out.

A view's ``mask`` leaves the CM and its shaft out of the similarity (their metal edges pulled the
bones, e.g. a femur 10 mm off in depth); the masked pixels are filled from their surroundings first.
Several images of one static view (the multiple-CM workflow) become one
:func:`static_view_composite`: each image's instrument filled from the others.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fluoronav.geometry.camera import Camera
from fluoronav.registration.bone.fill import harmonic_fill

__all__ = ["BoneView", "static_view_composite", "views_from_images"]


@dataclass(frozen=True, eq=False)
class BoneView:
    """One X-ray: image (H, W) float (−ln(I/I0) or any monotone intensity) and its camera.

    ``mask``: optional (H, W) bool, True on the pixels the similarity may use (e.g. False on a
    metal instrument the bone DRR does not contain). The masked pixels are filled from the others
    (:func:`~fluoronav.registration.bone.fill.harmonic_fill`) before binning, so the instrument's edge
    does not reach the used pixels through the filters; a working pixel is used when at least half
    of it is.
    """

    image: np.ndarray
    camera: Camera
    mask: np.ndarray | None = None

    def __post_init__(self) -> None:
        img = np.asarray(self.image)
        if img.shape != (self.camera.rows, self.camera.cols):
            raise ValueError(
                f"image shape {img.shape} does not match camera {self.camera.rows}x{self.camera.cols}"
            )
        if self.mask is not None and np.shape(self.mask) != img.shape:
            raise ValueError(f"mask shape {np.shape(self.mask)} does not match image {img.shape}")

    @functools.cached_property
    def filled_image(self) -> np.ndarray:
        """The image with its masked pixels filled (:func:`harmonic_fill`); computed once per view,
        shared by the pelvis and femur registrations of the view."""
        if self.mask is None:
            return np.asarray(self.image)
        return harmonic_fill(self.image, ~np.asarray(self.mask, dtype=bool))


def views_from_images(
    images: Sequence[object], instruments: Sequence[np.ndarray | None] | None = None
) -> list[BoneView]:
    """BoneViews from objects with ``image`` and ``camera`` (e.g. ``SimulatedImage``).

    ``instruments``: per image, (H, W) bool True on instrument pixels (the CM and its shaft,
    :func:`fluoronav.detection.instrument.instrument_mask`) or None; those pixels are left out of
    the bone similarity.
    """
    masks = list(instruments) if instruments is not None else [None] * len(images)
    if len(masks) != len(images):
        raise ValueError(f"{len(masks)} instrument masks for {len(images)} images")
    return [
        BoneView(
            np.asarray(im.image, dtype=np.float32),  # type: ignore[attr-defined]
            im.camera,  # type: ignore[attr-defined]
            None if m is None else ~np.asarray(m, dtype=bool),
        )
        for im, m in zip(images, masks, strict=True)
    ]


def static_view_composite(views: Sequence[BoneView]) -> BoneView:
    """One view from several images of one static C-arm view (the multiple-CM workflow: the
    anatomy is still, the instrument moves): per pixel the mean of the images whose mask uses it, so
    the instrument of one image is filled from the others and the noise averages down; the mask
    keeps the pixels no image could fill. Views without a mask are left out (their instrument was
    not found), unless no view has one (then the first view).

    Raises:
        ValueError: no views, or the views' cameras differ.
    """
    if not views:
        raise ValueError("no views given")
    cam = views[0].camera
    for v in views[1:]:
        if not (
            np.allclose(v.camera.K, cam.K) and np.allclose(v.camera.camera_from_world, cam.camera_from_world)
        ):
            raise ValueError("a static-view composite needs one camera for all images")
    masked = [v for v in views if v.mask is not None]
    if not masked:
        return views[0]
    w = np.stack([np.asarray(v.mask, dtype=np.float64) for v in masked])
    img = np.stack([np.asarray(v.image, dtype=np.float64) for v in masked])
    n = w.sum(axis=0)
    mean = (w * img).sum(axis=0) / np.maximum(n, 1.0)
    return BoneView(np.where(n > 0, mean, img.mean(axis=0)).astype(np.float32), cam, n > 0)
