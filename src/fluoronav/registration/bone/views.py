"""The images of a bone registration (:class:`BoneView`), with the instrument left out.

A view's ``mask`` leaves the CM and its shaft out of the similarity (their metal edges pulled the
bones, e.g. a femur 10 mm off in depth); the masked pixels are filled from their surroundings first.
Several images of one static view (the multiple-CM workflow) become one
:func:`static_view_composite`: each image's instrument filled from the others.
"""

from __future__ import annotations

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
    metal instrument the bone DRR does not contain). A working (binned) pixel is used when at least
    half of it is, and is the mean of its used pixels; the others are filled from the used ones
    (:func:`~fluoronav.registration.bone.fill.harmonic_fill`) at the working resolution
    (:meth:`binned`), so the instrument's edge does not reach the used pixels through the filters.
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

    def binned(self, factor: int) -> tuple[np.ndarray, np.ndarray | None]:
        """The working image binned by ``factor`` (float64, (H // factor, W // factor)) and which of
        its pixels the similarity uses (None without a mask); computed once per factor.

        Notes:
            Binning first and filling at the working resolution gives the used pixels the mean of
            their used pixels only (no filled value is mixed into them), and the harmonic fill a
            system ``factor²`` times smaller than at the detector's resolution.
        """
        cache: dict[int, tuple[np.ndarray, np.ndarray | None]] = self.__dict__.setdefault("_binned", {})
        if factor not in cache:
            cache[factor] = _bin_and_fill(np.asarray(self.image, np.float64), self.mask, factor)
        return cache[factor]

    def with_camera(self, camera: Camera) -> BoneView:
        """The same image and mask seen through ``camera`` (another pose), sharing the binned and
        filled images computed so far (they depend on the image and the mask only)."""
        out = BoneView(self.image, camera, self.mask)
        if "_binned" in self.__dict__:
            out.__dict__["_binned"] = self.__dict__["_binned"]
        return out


def _bin_and_fill(
    image: np.ndarray, mask: np.ndarray | None, factor: int
) -> tuple[np.ndarray, np.ndarray | None]:
    """:meth:`BoneView.binned`."""
    f = int(factor)
    H, W = (image.shape[0] // f) * f, (image.shape[1] // f) * f

    def bin_(x: np.ndarray) -> np.ndarray:
        return x[:H, :W].reshape(H // f, f, W // f, f).mean(axis=(1, 3))

    if mask is None:
        return bin_(image), None
    valid = np.asarray(mask, dtype=np.float64)
    frac = bin_(valid)
    mean = np.divide(bin_(image * valid), frac, out=np.zeros_like(frac), where=frac > 0)
    use = frac >= 0.5
    return harmonic_fill(mean, ~use), use


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
