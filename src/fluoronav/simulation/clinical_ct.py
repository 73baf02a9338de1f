"""The case's CT as a clinical scan of a finer patient volume (:class:`~fluoronav.simulation.world.CTWorld`).

Steps, each off when its magnitude is zero (or None), in this order: (1) partial volume, the patient
box-averaged onto a coarser grid of ``ct_spacing_mm`` offset by a random fraction of a CT voxel (exact
overlaps, separable per axis: HU × volume is kept; labels by nearest neighbour); (2) scale, HU × (1 ±
``hu_scale_error``); (3) noise, Gaussian white noise smoothed by a 0.7-voxel Gaussian (as a reconstruction
kernel correlates it) and rescaled to SD ``hu_noise_sd``; (4) label boundaries, each bone's boundary moved
along its normal by a smooth random field of SD ``label_boundary_voxels`` (a voxel claimed by two bones goes
to the nearer one; the field fades to zero around the landmarks). The geometry (direction, LPS world frame)
and the landmarks (world points) are the patient's. Memory: the partial volume works on slabs of the patient,
the label step on each bone's bounding box.
"""

from __future__ import annotations

import logging
import math

import numpy as np
from scipy import ndimage

from fluoronav.anatomy.volume import Volume
from fluoronav.simulation.world import CTWorld

__all__ = ["clinical_ct", "partial_volume", "perturb_labels"]

logger = logging.getLogger(__name__)

#: Gaussian σ (CT voxels) of the noise's correlation.
NOISE_CORRELATION_VOXELS = 0.7
#: Slab thickness (patient voxels along z) of the partial-volume pass: bounds its temporaries.
_SLAB = 64


def _box_weights(
    n_fine: int, first_edge: float, ratio: float, n_coarse: int
) -> tuple[np.ndarray, np.ndarray]:
    """Overlap weights of coarse cells over fine voxels along one axis.

    Fine voxel ``i`` covers ``[i − ½, i + ½]`` (fine index units); coarse cell ``k`` covers
    ``[first_edge + k·ratio, first_edge + (k+1)·ratio]``. Returns ``(index (m, n_coarse),
    weight (m, n_coarse))``: each coarse value is ``Σ_m weight[m] · fine[index[m]]`` (the weights of
    a cell sum to one).
    """
    lo = first_edge + ratio * np.arange(n_coarse)
    hi = lo + ratio
    start = np.floor(lo + 0.5).astype(np.int64)
    m = math.ceil(ratio) + 1
    idx = start[None, :] + np.arange(m)[:, None]
    overlap = np.minimum(hi[None, :], idx + 0.5) - np.maximum(lo[None, :], idx - 0.5)
    w = np.clip(overlap, 0.0, None) / ratio
    return np.clip(idx, 0, n_fine - 1), w.astype(np.float32)


def _average_axis(data: np.ndarray, axis: int, index: np.ndarray, weight: np.ndarray) -> np.ndarray:
    shape = [1] * data.ndim
    shape[axis] = -1
    out = np.zeros([*data.shape[:axis], index.shape[1], *data.shape[axis + 1 :]], dtype=np.float32)
    for idx, w in zip(index, weight, strict=True):
        out += np.take(data, idx, axis=axis) * w.reshape(shape)
    return out


def partial_volume(
    patient: Volume, ct_spacing_mm: tuple[float, float, float], offset_fraction: np.ndarray
) -> Volume:
    """Box-average a volume onto a coarser grid inside its field of view.

    Args:
        patient: the fine volume (HU), any direction.
        ct_spacing_mm: (x, y, z) CT voxel size, mm; each at least the patient's.
        offset_fraction: (3,) offset of the CT grid's outer corner from the patient's, as a fraction
            of a CT voxel per axis (x, y, z), in [0, 1).

    Returns:
        the CT (float32 HU) on a grid of ``ct_spacing_mm`` in the patient's direction, as many
        whole CT voxels as fit inside the patient; labels by nearest neighbour; the patient's label
        names, landmarks and name.
    """
    fine = np.asarray(patient.spacing_mm, dtype=np.float64)
    ratio = np.asarray(ct_spacing_mm, dtype=np.float64) / fine
    if np.any(ratio < 1.0 - 1e-9):
        raise ValueError(f"CT spacing {ct_spacing_mm} is finer than the patient's {patient.spacing_mm}")
    first = -0.5 + np.asarray(offset_fraction, dtype=np.float64) * ratio  # fine index units
    n_fine = np.asarray(patient.shape_xyz)
    n_ct = np.floor((n_fine - 0.5 - first) / ratio + 1e-9).astype(int)
    if np.any(n_ct < 1):
        raise ValueError("the CT grid does not fit inside the patient volume")
    (ix, wx), (iy, wy), (iz, wz) = (
        _box_weights(int(n_fine[a]), float(first[a]), float(ratio[a]), int(n_ct[a])) for a in range(3)
    )
    # x and y on slabs of z (bounded temporaries), then z on the in-plane-reduced volume
    plane = np.empty((patient.data.shape[0], n_ct[1], n_ct[0]), dtype=np.float32)
    for z0 in range(0, patient.data.shape[0], _SLAB):
        slab = np.asarray(patient.data[z0 : z0 + _SLAB], dtype=np.float32)
        plane[z0 : z0 + _SLAB] = _average_axis(_average_axis(slab, 2, ix, wx), 1, iy, wy)
    data = _average_axis(plane, 0, iz, wz)
    del plane

    centre_idx = first + 0.5 * ratio  # fine index of CT voxel (0, 0, 0)'s centre, (x, y, z)
    origin = patient.world_from_index @ np.append(centre_idx, 1.0)
    labels = None
    if patient.labels is not None:
        nearest = [
            np.clip(
                np.floor(centre_idx[a] + ratio[a] * np.arange(n_ct[a]) + 0.5).astype(int), 0, n_fine[a] - 1
            )
            for a in range(3)
        ]
        labels = patient.labels[np.ix_(nearest[2], nearest[1], nearest[0])]
    return Volume(
        data=data,
        spacing_mm=(float(ct_spacing_mm[0]), float(ct_spacing_mm[1]), float(ct_spacing_mm[2])),
        origin_mm=(float(origin[0]), float(origin[1]), float(origin[2])),
        direction=patient.direction,
        labels=labels,
        label_names=dict(patient.label_names),
        landmarks_world={k: np.array(v, dtype=np.float64) for k, v in patient.landmarks_world.items()},
        name=patient.name,
    )


def _correlated_noise(shape: tuple[int, ...], sd: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian noise of standard deviation ``sd`` smoothed by a Gaussian of NOISE_CORRELATION_VOXELS."""
    white = rng.standard_normal(shape, dtype=np.float32)
    smooth = ndimage.gaussian_filter(white, NOISE_CORRELATION_VOXELS, mode="wrap")
    # the filter's variance gain: the squared norm of its (separable) kernel
    delta = np.zeros(33)
    delta[16] = 1.0
    k = ndimage.gaussian_filter1d(delta, NOISE_CORRELATION_VOXELS, mode="constant")
    gain = float(np.sum(k**2)) ** len(shape)
    return smooth * np.float32(sd / math.sqrt(gain))


def _smooth_field(shape: tuple[int, ...], sigma_vox: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A smooth Gaussian random field of about unit SD on a grid, float32, correlation σ ``sigma_vox``.

    Drawn on a grid of σ/2 steps, smoothed there by 2 steps and interpolated linearly: a wide
    Gaussian filter on the full grid would cost ~σ operations per voxel and axis.
    """
    step = np.maximum(np.asarray(sigma_vox, dtype=np.float64) / 2.0, 1.0)
    coarse_shape = tuple(math.ceil((n - 1) / s) + 2 for n, s in zip(shape, step, strict=True))
    coarse = ndimage.gaussian_filter(rng.standard_normal(coarse_shape), 2.0, mode="wrap")
    coarse /= max(float(coarse.std()), 1e-12)
    axes = [np.arange(n, dtype=np.float64) / s for n, s in zip(shape, step, strict=True)]
    out = np.empty(shape, dtype=np.float32)
    for k, zk in enumerate(axes[0]):  # plane by plane: the coordinate arrays stay 2D
        yy, xx = np.meshgrid(axes[1], axes[2], indexing="ij")
        out[k] = ndimage.map_coordinates(coarse, [np.full_like(yy, zk), yy, xx], order=1)
    return out


def _landmark_taper(volume: Volume, radius_mm: float) -> np.ndarray:
    """(nz, ny, nx) weight that is 0 at the landmarks and rises smoothly to 1 at ``radius_mm``."""
    taper = np.ones(volume.data.shape, dtype=np.float32)
    spacing = np.asarray(volume.spacing_mm)
    for p in volume.landmarks_world.values():
        idx = (volume.index_from_world @ np.append(np.asarray(p, dtype=np.float64), 1.0))[:3]
        lo = np.maximum(np.floor(idx - radius_mm / spacing).astype(int), 0)
        hi = np.minimum(np.ceil(idx + radius_mm / spacing).astype(int) + 1, volume.shape_xyz)
        if np.any(hi <= lo):
            continue  # outside the volume
        axes = [(np.arange(lo[a], hi[a]) - idx[a]) * spacing[a] for a in range(3)]
        r = np.sqrt(axes[2][:, None, None] ** 2 + axes[1][None, :, None] ** 2 + axes[0][None, None, :] ** 2)
        t = np.clip(r / radius_mm, 0.0, 1.0)
        box = (slice(lo[2], hi[2]), slice(lo[1], hi[1]), slice(lo[0], hi[0]))
        taper[box] = np.minimum(taper[box], (t * t * (3.0 - 2.0 * t)).astype(np.float32))
    return taper


def _signed_distance_mm(mask: np.ndarray, spacing_zyx: tuple[float, float, float]) -> np.ndarray:
    """Signed distance (mm) to a mask's boundary: negative inside, positive outside (voxel centres).

    Voxel-centre distances are moved by half the smallest voxel towards the boundary, which lies
    between the centres; a zero displacement keeps the mask exactly.
    """
    half = 0.5 * min(spacing_zyx)
    outside = ndimage.distance_transform_edt(~mask, sampling=spacing_zyx)
    inside = ndimage.distance_transform_edt(mask, sampling=spacing_zyx)
    return np.where(mask, half - inside, outside - half).astype(np.float32)


def perturb_labels(volume: Volume, cfg: CTWorld, rng: np.random.Generator) -> np.ndarray:
    """Labels with each bone's boundary moved by a smooth field of SD ``label_boundary_voxels`` voxels.

    Returns:
        (nz, ny, nx) label map of the volume's dtype: disjoint by construction (each voxel one value),
        unchanged within a few SDs of every landmark.
    """
    assert volume.labels is not None
    spacing = np.asarray(volume.spacing_mm, dtype=np.float64)
    voxel_mm = float(spacing.mean())
    sd_mm = cfg.label_boundary_voxels * voxel_mm
    spacing_zyx = (float(spacing[2]), float(spacing[1]), float(spacing[0]))
    field = _smooth_field(volume.data.shape, cfg.label_smoothness_mm / spacing[::-1], rng)
    shift = field * np.float32(sd_mm) * _landmark_taper(volume, 4.0 * sd_mm + 2.0 * voxel_mm)
    reach = float(np.abs(shift).max()) + 2.0 * voxel_mm  # no boundary moves further
    margin = np.ceil(reach / spacing[::-1]).astype(int) + 1
    best = np.full(volume.data.shape, np.inf, dtype=np.float32)  # smallest (distance − shift) so far
    out = np.zeros_like(volume.labels)
    for value in sorted(int(v) for v in np.unique(volume.labels) if v != 0):
        mask = volume.labels == value
        where = np.argwhere(mask)
        lo = np.maximum(where.min(axis=0) - margin, 0)
        hi = np.minimum(where.max(axis=0) + margin + 1, mask.shape)
        box = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
        d = _signed_distance_mm(mask[box], spacing_zyx) - shift[box]
        claim = (d < 0) & (d < best[box])
        best[box] = np.where(claim, d, best[box])
        out[box][claim] = value
    return out


def clinical_ct(patient: Volume, cfg: CTWorld, rng: np.random.Generator) -> Volume:
    """The case's CT of a patient volume: partial volume, HU scale, noise and label boundaries.

    Args:
        patient: the volume the images are rendered from (HU, with labels and landmarks).
        cfg: the CT errors; ``patient_spacing_mm`` is not used here (it says how to build the patient).
        rng: draws, in this order and only for the steps that are on: the grid offset (3 uniforms),
            the scale sign (1 uniform), the noise, the boundary field.

    Returns:
        ``patient`` itself when every step is off, else a new volume (float32 HU) in the same world
        frame with the same landmarks, label names and name.
    """
    move_labels = cfg.label_boundary_voxels > 0 and patient.labels is not None
    if cfg.ct_spacing_mm is None and cfg.hu_noise_sd <= 0 and cfg.hu_scale_error <= 0 and not move_labels:
        return patient
    ct = patient
    if cfg.ct_spacing_mm is not None:
        ct = partial_volume(patient, cfg.ct_spacing_mm, rng.uniform(0.0, 1.0, 3))
    data = ct.data if ct is not patient else np.array(patient.data, dtype=np.float32)
    if cfg.hu_scale_error > 0:
        sign = 1.0 if rng.uniform() < 0.5 else -1.0
        data *= np.float32(1.0 + sign * cfg.hu_scale_error)
    if cfg.hu_noise_sd > 0:
        data += _correlated_noise(data.shape, cfg.hu_noise_sd, rng)
    ct = ct.replace(data=data)
    if move_labels:
        ct = ct.replace(labels=perturb_labels(ct, cfg, rng))
    logger.debug("clinical CT %s: shape %s spacing %s", ct.name, ct.data.shape, ct.spacing_mm)
    return ct
