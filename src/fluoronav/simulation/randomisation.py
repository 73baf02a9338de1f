"""Domain randomisation of the detector's training images at simulation time (after SyntheX).

Realistic simulation plus strong randomisation (Gao et al., Nature Machine Intelligence 2023): each sample
draws its spectrum, dose, blur and scatter (:func:`randomised_physics`), collimator blades and a wedge filter
(:func:`beam_filter_densities`: areal densities added before the physics), and its detector response, field
of view and orientation (:func:`randomise_image`: after the physics, the mask and landmarks moved with the
image). Each returns a JSON-ready record of its draws, from which the ``*_from_record`` functions rebuild
the sample without a generator. The default :class:`RandomisationConfig` (``RANDOMISATION_OFF``) draws
nothing and changes nothing; ``RANDOMISATION_REALISTIC`` switches every source on. Augmentation of stored
samples at training time is :mod:`fluoronav.detection.training.augment`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from fluoronav.device import resolve_device
from fluoronav.errors import InputError
from fluoronav.geometry.camera import Camera
from fluoronav.settings import setting
from fluoronav.simulation.materials import MM_PER_CM, get_material
from fluoronav.simulation.physics import XrayPhysics

__all__ = [
    "RANDOMISATION_OFF",
    "RANDOMISATION_PRESETS",
    "RANDOMISATION_REALISTIC",
    "RandomisationConfig",
    "apply_image_record",
    "beam_filter_densities",
    "beam_filters_from_record",
    "output_camera",
    "physics_from_record",
    "randomise_image",
    "randomised_physics",
]

FloatRange = tuple[float, float]
#: material of the collimator blades and the wedge filter (a copper-equivalent thickness)
FILTER_MATERIAL = "copper"
#: the smallest side of a detector window, stored pixels
MIN_WINDOW_PX = 16


@dataclass(frozen=True)
class RandomisationConfig:
    """What a training sample's simulation draws; every source is off by default.

    A ``bool`` switches a source on; a probability ``p_*`` of 0 switches an event off, and nothing
    is drawn for a source that is off. Ranges are drawn uniformly (``dose_factor_range``
    log-uniformly). Blur, glare and scatter widths are in detector pixels, as
    :class:`~fluoronav.simulation.physics.XrayPhysics` takes them before ``with_pixel_scale``; the
    image-side sizes are in stored pixels. The realistic preset's values are assumed, wide rather
    than measured (SyntheX randomises strongly).
    """

    # spectrum
    kvp: bool = setting(False, "draw the tube voltage")
    kvp_range: FloatRange = setting((60.0, 120.0), "tube voltage range", unit="kV", ge=60.0, le=120.0)
    filtration: bool = setting(False, "draw a tabulated filtration and added Al and Cu filters")
    filtrations: tuple[str, ...] = setting(("al2.5", "al2.5_cu0.1"), "tabulated total filtrations to draw")
    added_al_mm_range: FloatRange = setting((0.0, 3.0), "added aluminium filter", unit="mm", ge=0.0)
    added_cu_mm_range: FloatRange = setting((0.0, 0.3), "added copper filter", unit="mm", ge=0.0)
    # dose, detector noise, blur, scatter
    dose: bool = setting(False, "scale the flat-field photons per pixel (quantum noise)")
    dose_factor_range: FloatRange = setting((0.25, 4.0), "factor on photons_per_pixel", unit="1", gt=0.0)
    electronic_noise: bool = setting(False, "draw the read-out noise")
    electronic_noise_std_range: FloatRange = setting(
        (0.5, 4.0), "read-out noise std", unit="photons per detector pixel", ge=0.0
    )
    blur: bool = setting(False, "draw the detector PSF (Gaussian and glare tail)")
    blur_sigma_px_range: FloatRange = setting((0.3, 1.2), "Gaussian PSF std", unit="detector px", ge=0.0)
    glare_fraction_range: FloatRange = setting((0.0, 0.06), "glare tail weight", unit="1", ge=0.0, le=1.0)
    scatter: bool = setting(False, "draw the scatter")
    scatter_to_primary_range: FloatRange = setting(
        (0.05, 0.5), "scatter-to-primary ratio at the reference line integral", unit="1", ge=0.0
    )
    scatter_sigma_px_range: FloatRange = setting(
        (20.0, 80.0), "scatter kernel std", unit="detector px", gt=0.0
    )
    # beam filters (areal densities before the physics)
    p_collimation: float = setting(0.0, "probability of collimator blades", unit="1", ge=0.0, le=1.0)
    collimation_field_frac_range: FloatRange = setting(
        (0.5, 0.95), "open field side / image side", unit="1", gt=0.0, le=1.0
    )
    collimation_max_angle_deg: float = setting(20.0, "blades rotated within ± this", unit="deg", ge=0.0)
    collimation_cu_mm_range: FloatRange = setting((1.0, 5.0), "blade thickness (copper)", unit="mm", ge=0.0)
    collimation_margin_px: float = setting(8.0, "keep points stay this far inside the field", unit="px")
    p_wedge: float = setting(0.0, "probability of a wedge filter", unit="1", ge=0.0, le=1.0)
    wedge_cu_mm_range: FloatRange = setting(
        (0.2, 1.0), "wedge thickness at its thick edge", unit="mm", ge=0.0
    )
    wedge_width_frac_range: FloatRange = setting(
        (0.2, 0.5), "wedge ramp width / image extent along it", unit="1", gt=0.0, le=1.0
    )
    # detector response (after the physics)
    response: bool = setting(False, "draw the output's gamma, gain and offset")
    gamma_range: FloatRange = setting((0.7, 1.4), "gamma on |image| / max |image|", unit="1", gt=0.0)
    gain_range: FloatRange = setting((0.5, 2.0), "gain on the output", unit="1", gt=0.0)
    offset_range: FloatRange = setting((-0.5, 0.5), "offset added to the output", unit="image units")
    p_linear_output: float = setting(
        0.0, "probability of 1 − I/I0 instead of −ln(I/I0)", unit="1", ge=0, le=1
    )
    # field of view and orientation (after the physics)
    p_partial_fov: float = setting(
        0.0, "probability of a detector window that leaves one landmark out", unit="1", ge=0.0, le=1.0
    )
    partial_fov_side_frac_range: FloatRange = setting(
        (0.6, 0.9), "window side / image side", unit="1", gt=0.0, le=1.0
    )
    partial_fov_cut_range: FloatRange = setting(
        (0.25, 0.75), "window edge on A–B, fraction from the kept landmark", unit="1", gt=0.0, lt=1.0
    )
    partial_fov_min_ab_px: float = setting(16.0, "shorter A–B (end-on): a window anywhere", unit="px")
    out_of_view_landmarks: Literal["keep", "nan"] = setting(
        "keep", "a landmark outside the image keeps its coordinates (flagged) or becomes NaN"
    )
    p_rotate_180: float = setting(0.0, "probability of rotating the image by 180°", unit="1", ge=0.0, le=1.0)
    p_transpose: float = setting(0.0, "probability of transposing the image", unit="1", ge=0.0, le=1.0)

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name.endswith("_range") and not value[0] <= value[1]:
                raise ValueError(f"{f.name} must be (low, high) with low ≤ high, got {value}")
            if f.name.startswith("p_") and not 0.0 <= value <= 1.0:
                raise ValueError(f"{f.name} must be a probability in [0, 1], got {value}")
        if not 60.0 <= self.kvp_range[0] <= self.kvp_range[1] <= 120.0:
            raise ValueError(f"kvp_range must lie within the tabulated 60–120 kV, got {self.kvp_range}")
        if self.filtration and not self.filtrations:
            raise ValueError("filtrations must name at least one tabulated filtration")


#: nothing drawn, nothing changed (the default)
RANDOMISATION_OFF = RandomisationConfig()
#: every source on with wide, assumed ranges
RANDOMISATION_REALISTIC = RandomisationConfig(
    kvp=True,
    filtration=True,
    dose=True,
    electronic_noise=True,
    blur=True,
    scatter=True,
    p_collimation=0.5,
    p_wedge=0.25,
    response=True,
    p_linear_output=0.2,
    p_partial_fov=0.25,
    p_rotate_180=0.25,
    p_transpose=0.25,
)
#: the presets by name
RANDOMISATION_PRESETS: dict[str, RandomisationConfig] = {
    "off": RANDOMISATION_OFF,
    "realistic": RANDOMISATION_REALISTIC,
}


class _Draws:
    """Draws from a generator, each written into the record under its key."""

    def __init__(self, rng: np.random.Generator, record: dict[str, Any]) -> None:
        self.rng, self.record = rng, record

    def uniform(self, key: str, bounds: tuple[float, float]) -> float:
        value = float(self.rng.uniform(bounds[0], bounds[1]))
        self.record[key] = value
        return value

    def log_uniform(self, key: str, bounds: tuple[float, float]) -> float:
        value = float(np.exp(self.rng.uniform(np.log(bounds[0]), np.log(bounds[1]))))
        self.record[key] = value
        return value

    def pair(self, key: str, bounds: tuple[float, float]) -> tuple[float, float]:
        a, b = (float(x) for x in self.rng.uniform(bounds[0], bounds[1], size=2))
        self.record[key] = [a, b]
        return a, b

    def choice(self, key: str, options: tuple[str, ...]) -> str:
        value = options[int(self.rng.integers(len(options)))]
        self.record[key] = value
        return value

    def index(self, key: str, n: int) -> int:
        value = int(self.rng.integers(n))
        self.record[key] = value
        return value

    def event(self, key: str, p: float) -> bool:
        """True with probability ``p``; nothing drawn nor recorded when ``p`` is 0."""
        if p <= 0.0:
            return False
        value = bool(self.rng.random() < p)
        self.record[key] = value
        return value


# ----- physics ---------------------------------------------------------------------------------
def randomised_physics(
    physics: XrayPhysics, cfg: RandomisationConfig, rng: np.random.Generator
) -> tuple[XrayPhysics, dict[str, Any]]:
    """``physics`` with its spectrum, dose, read-out noise, PSF and scatter drawn by ``cfg``.

    Randomise the detector-pixel physics (``SimulationConfig.physics``), then scale it to the stored
    pixels with ``with_pixel_scale`` as the simulator does. Returns the physics and the record of
    the draws (:func:`physics_from_record` rebuilds the physics from it); with every source off,
    ``physics`` itself and an empty record.
    """
    record: dict[str, Any] = {}
    d = _Draws(rng, record)
    if cfg.kvp:
        d.uniform("kvp", cfg.kvp_range)
    if cfg.filtration:
        d.choice("filtration", cfg.filtrations)
        d.uniform("added_al_mm", cfg.added_al_mm_range)
        d.uniform("added_cu_mm", cfg.added_cu_mm_range)
    if cfg.dose:
        d.log_uniform("dose_factor", cfg.dose_factor_range)
    if cfg.electronic_noise:
        d.uniform("electronic_noise_std", cfg.electronic_noise_std_range)
    if cfg.blur:
        d.uniform("blur_sigma_px", cfg.blur_sigma_px_range)
        d.uniform("glare_fraction", cfg.glare_fraction_range)
    if cfg.scatter:
        d.uniform("scatter_to_primary", cfg.scatter_to_primary_range)
        d.uniform("scatter_sigma_px", cfg.scatter_sigma_px_range)
    return physics_from_record(physics, record), record


def physics_from_record(physics: XrayPhysics, record: dict[str, Any]) -> XrayPhysics:
    """``physics`` with the draws of a :func:`randomised_physics` record (keys it lacks are kept)."""
    if not record:
        return physics
    if physics.custom_spectrum is not None and ("kvp" in record or "filtration" in record):
        raise ValueError("the physics has a custom spectrum: its kVp and filtration cannot be drawn")
    changes: dict[str, Any] = {}
    if "kvp" in record:
        changes["kvp"] = float(record["kvp"])
    if "filtration" in record:
        changes["filtration"] = str(record["filtration"])
        extra: dict[str, float] = {}
        # the added filters sum with the physics' own extra filters of the same material
        for material, mm in (
            *physics.extra_filtration_mm,
            ("aluminium", float(record["added_al_mm"])),
            ("copper", float(record["added_cu_mm"])),
        ):
            extra[material] = extra.get(material, 0.0) + mm
        changes["extra_filtration_mm"] = tuple(extra.items())
    if "dose_factor" in record and physics.photons_per_pixel is not None:
        changes["photons_per_pixel"] = physics.photons_per_pixel * float(record["dose_factor"])
    for key in (
        "electronic_noise_std",
        "blur_sigma_px",
        "glare_fraction",
        "scatter_to_primary",
        "scatter_sigma_px",
    ):
        if key in record:
            changes[key] = float(record[key])
    return dataclasses.replace(physics, **changes)


# ----- beam filters ----------------------------------------------------------------------------
def beam_filter_densities(
    rows: int,
    cols: int,
    cfg: RandomisationConfig,
    rng: np.random.Generator,
    *,
    keep_points_px: np.ndarray | None = None,
    device: str | torch.device = "cpu",
) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Collimator blades and a wedge filter drawn by ``cfg``, as areal densities to add before the physics.

    The blades bound a rectangle rotated within ± ``collimation_max_angle_deg``; ``keep_points_px``
    (N, 2) (u, v), e.g. the CM's landmarks, stay ``collimation_margin_px`` inside it. The wedge's
    thickness ramps from 0 to its maximum towards one image edge (drawn direction). Both are
    copper (:data:`FILTER_MATERIAL`), so the physics gives their edges the scatter and blur of a
    real field.

    Returns:
        ``{FILTER_MATERIAL: (rows, cols) float32 g/cm²}`` (empty when nothing was drawn) and the
        record (:func:`beam_filters_from_record` rebuilds the densities from it).
    """
    record: dict[str, Any] = {}
    d = _Draws(rng, record)
    if d.event("collimation", cfg.p_collimation):
        angle = d.uniform(
            "collimation_angle_deg", (-cfg.collimation_max_angle_deg, cfg.collimation_max_angle_deg)
        )
        frac = d.pair("collimation_field_frac", cfg.collimation_field_frac_range)
        shift = d.pair("collimation_shift_frac", (-1.0, 1.0))
        d.uniform("collimation_cu_mm", cfg.collimation_cu_mm_range)
        centre, half = _collimation_field(
            rows, cols, angle, frac, shift, keep_points_px, cfg.collimation_margin_px
        )
        record["collimation_centre_px"] = centre
        record["collimation_half_sides_px"] = half
    if d.event("wedge", cfg.p_wedge):
        d.uniform("wedge_angle_deg", (0.0, 360.0))
        d.uniform("wedge_width_frac", cfg.wedge_width_frac_range)
        d.uniform("wedge_cu_mm", cfg.wedge_cu_mm_range)
    return beam_filters_from_record(rows, cols, record, device=device), record


def _collimation_field(
    rows: int,
    cols: int,
    angle_deg: float,
    frac: tuple[float, float],
    shift: tuple[float, float],
    keep_points_px: np.ndarray | None,
    margin_px: float,
) -> tuple[list[float], list[float]]:
    """Centre (u, v) and half sides (along the blades' two axes) of the open field, in pixels."""
    half = np.array([0.5 * frac[0] * cols, 0.5 * frac[1] * rows])
    room = np.maximum(np.array([0.5 * cols, 0.5 * rows]) - half, 0.0)
    centre = np.array([(cols - 1) / 2.0, (rows - 1) / 2.0]) + np.asarray(shift) * room
    a = math.radians(angle_deg)
    axes = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])  # rows: the field's axes
    if keep_points_px is not None and len(keep_points_px) > 0:
        s = (np.asarray(keep_points_px, np.float64).reshape(-1, 2) - centre) @ axes.T  # (N, 2)
        lo = np.minimum(-half, s.min(axis=0) - margin_px)
        hi = np.maximum(half, s.max(axis=0) + margin_px)
        centre = centre + ((lo + hi) / 2.0) @ axes  # widen the field to keep the points inside
        half = (hi - lo) / 2.0
    return [float(x) for x in centre], [float(x) for x in half]


def beam_filters_from_record(
    rows: int, cols: int, record: dict[str, Any], *, device: str | torch.device = "cpu"
) -> dict[str, torch.Tensor]:
    """The blade and wedge areal densities of a :func:`beam_filter_densities` record, (rows, cols) g/cm²."""
    dev = resolve_device(device)
    v, u = torch.meshgrid(
        torch.arange(rows, dtype=torch.float64, device=dev),
        torch.arange(cols, dtype=torch.float64, device=dev),
        indexing="ij",
    )
    thickness_mm = torch.zeros(rows, cols, dtype=torch.float64, device=dev)
    any_filter = False
    if record.get("collimation"):
        any_filter = True
        a = math.radians(float(record["collimation_angle_deg"]))
        cu, cv = record["collimation_centre_px"]
        s1 = (u - cu) * math.cos(a) + (v - cv) * math.sin(a)
        s2 = -(u - cu) * math.sin(a) + (v - cv) * math.cos(a)
        h1, h2 = record["collimation_half_sides_px"]
        # the fraction of each pixel behind a blade; crossed blade pairs stack at the corners
        behind = (s1.abs() - h1 + 0.5).clamp(0.0, 1.0) + (s2.abs() - h2 + 0.5).clamp(0.0, 1.0)
        thickness_mm += float(record["collimation_cu_mm"]) * behind
    if record.get("wedge"):
        any_filter = True
        a = math.radians(float(record["wedge_angle_deg"]))
        s = (u - (cols - 1) / 2.0) * math.cos(a) + (v - (rows - 1) / 2.0) * math.sin(a)
        extent = 0.5 * (cols * abs(math.cos(a)) + rows * abs(math.sin(a)))  # half the image along it
        width = float(record["wedge_width_frac"]) * 2.0 * extent
        ramp = ((s - (extent - width)) / width).clamp(0.0, 1.0)
        thickness_mm += float(record["wedge_cu_mm"]) * ramp
    if not any_filter:
        return {}
    rho = get_material(FILTER_MATERIAL).density_g_cm3
    return {FILTER_MATERIAL: (thickness_mm * (rho / MM_PER_CM)).to(torch.float32)}


# ----- the image -------------------------------------------------------------------------------
def randomise_image(
    image: np.ndarray,
    mask: np.ndarray,
    landmarks_px: np.ndarray | None,
    cfg: RandomisationConfig,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, dict[str, Any]]:
    """The detector response, field of view and orientation of a simulated image drawn by ``cfg``.

    In order: the output (``1 − I/I0`` instead of ``−ln(I/I0)``, then gamma, gain and offset; the
    input is ``XrayPhysics.apply``'s image with its default gain 1 and offset 0); a detector window
    (a crop) whose edge crosses A–B so that one landmark leaves the image (negatives and end-on CMs:
    a window of the same size anywhere); a rotation by 180°; a transpose. The mask and landmarks
    move with the image. A landmark outside the image keeps its coordinates, as the detector's
    training crops do, and is flagged in ``landmarks_in_image`` (``out_of_view_landmarks="nan"``: it
    becomes NaN; the training data set then reads the sample as a negative); a window with no mask
    pixel gives no landmarks (None).

    Args:
        image: (H, W) float image; mask: (H, W); landmarks_px: (2, 2) [[uA, vA], [uB, vB]] or None.
        cfg: the randomisation; rng: its generator.

    Returns:
        image, mask, landmarks (the inputs themselves when nothing was drawn) and the record
        (:func:`apply_image_record` replays it; ``pixel_affine`` (3, 3) maps input pixels to output
        pixels, :func:`output_camera` gives the output's camera).
    """
    record: dict[str, Any] = {}
    d = _Draws(rng, record)
    d.event("linear_output", cfg.p_linear_output)
    if cfg.response:
        d.uniform("output_gamma", cfg.gamma_range)
        d.uniform("output_gain", cfg.gain_range)
        d.uniform("output_offset", cfg.offset_range)
    rows, cols = image.shape
    if d.event("partial_fov", cfg.p_partial_fov):
        side = d.pair("window_side_frac", cfg.partial_fov_side_frac_range)
        cut = d.index("window_cut_landmark", 2)
        t = d.uniform("window_cut_frac", cfg.partial_fov_cut_range)
        pos = d.pair("window_position_frac", (0.0, 1.0))
        window = _window(rows, cols, landmarks_px, side, cut, t, pos, cfg.partial_fov_min_ab_px)
        record["window_px"] = list(window)
        if landmarks_px is not None:
            x0, y0, x1, y1 = window
            record["window_has_cm"] = bool(np.any(mask[y0:y1, x0:x1]))
    rotate, transpose = d.event("rotate_180", cfg.p_rotate_180), d.event("transpose", cfg.p_transpose)
    if "window_px" in record or rotate or transpose:
        record["pixel_affine"] = _pixel_affine(rows, cols, record).tolist()
    if "window_px" in record and landmarks_px is not None and record["window_has_cm"]:
        x0, y0, x1, y1 = record["window_px"]
        lm = np.asarray(landmarks_px, np.float64) - [x0, y0]
        inside = np.all((lm >= -0.5) & (lm <= np.array([x1 - x0, y1 - y0]) - 0.5), axis=1)
        record["landmarks_in_image"] = [bool(x) for x in inside]
        if cfg.out_of_view_landmarks == "nan":
            record["landmarks_nan"] = [not bool(x) for x in inside]
    out = apply_image_record(image, mask, landmarks_px, record)
    return (*out, record)


def _window(
    rows: int,
    cols: int,
    landmarks_px: np.ndarray | None,
    side_frac: tuple[float, float],
    cut: int,
    t: float,
    pos: tuple[float, float],
    min_ab_px: float,
) -> tuple[int, int, int, int]:
    """Window (x0, y0, x1, y1) (pixel edges, x1/y1 exclusive) whose edge crosses A–B at ``t`` from the
    kept landmark, leaving landmark ``cut`` out; anywhere (at ``pos``) without landmarks or end-on."""
    n = (cols, rows)
    side = [min(max(round(f * m), MIN_WINDOW_PX), m) for f, m in zip(side_frac, n, strict=True)]
    lm = None if landmarks_px is None else np.asarray(landmarks_px, np.float64).reshape(2, 2)
    if lm is None or not np.all(np.isfinite(lm)) or float(np.hypot(*(lm[1] - lm[0]))) < min_ab_px:
        starts = [round(p * (m - s)) for p, m, s in zip(pos, n, side, strict=True)]
        return starts[0], starts[1], starts[0] + side[0], starts[1] + side[1]
    kept, gone = lm[1 - cut], lm[cut]
    delta = gone - kept
    a = 0 if abs(delta[0]) >= abs(delta[1]) else 1  # cut across the axis A–B runs along most
    edge = kept[a] + t * delta[a]
    margin = 2
    lo_hi = [0, 0, 0, 0]  # x0, x1, y0, y1
    if delta[a] > 0:
        hi = int(np.clip(math.floor(edge + 0.5), 1, n[a]))
        lo = int(np.clip(min(hi - side[a], math.floor(kept[a]) - margin), 0, hi - 1))
    else:
        lo = int(np.clip(math.floor(edge + 0.5), 0, n[a] - 1))
        hi = int(np.clip(max(lo + side[a], math.ceil(kept[a]) + margin + 1), lo + 1, n[a]))
    lo_hi[2 * a : 2 * a + 2] = [lo, hi]
    b = 1 - a  # across: any position that keeps the kept landmark inside
    first = max(0, math.ceil(kept[b]) + margin + 1 - side[b])
    last = min(n[b] - side[b], math.floor(kept[b]) - margin)
    start = (
        first + round(pos[b] * (last - first)) if last >= first else int(np.clip(first, 0, n[b] - side[b]))
    )
    lo_hi[2 * b : 2 * b + 2] = [start, start + side[b]]
    return lo_hi[0], lo_hi[2], lo_hi[1], lo_hi[3]


def _pixel_affine(rows: int, cols: int, record: dict[str, Any]) -> np.ndarray:
    """(3, 3) map of input pixels (u, v, 1) to output pixels for a record's window, rotation, transpose."""
    M = np.eye(3)
    h, w = rows, cols
    if "window_px" in record:
        x0, y0, x1, y1 = record["window_px"]
        M = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]]) @ M
        h, w = y1 - y0, x1 - x0
    if record.get("rotate_180"):
        M = np.array([[-1.0, 0.0, w - 1.0], [0.0, -1.0, h - 1.0], [0.0, 0.0, 1.0]]) @ M
    if record.get("transpose"):
        M = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) @ M
    return M


def apply_image_record(
    image: np.ndarray, mask: np.ndarray, landmarks_px: np.ndarray | None, record: dict[str, Any]
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Replay a :func:`randomise_image` record (no draws): (image, mask, landmarks (2, 2) or None).

    An empty record returns the inputs themselves.
    """
    img, msk, lm = image, mask, landmarks_px
    if record.get("linear_output") or "output_gamma" in record:
        v = np.asarray(image, np.float64)
        if record.get("linear_output"):
            v = -np.expm1(-v)  # 1 − I/I0: linear in the intensity, attenuation still bright
        if "output_gamma" in record:
            scale = float(np.abs(v).max())
            if scale > 0:
                v = scale * np.sign(v) * (np.abs(v) / scale) ** float(record["output_gamma"])
            v = float(record["output_gain"]) * v + float(record["output_offset"])
        img = v.astype(image.dtype)
    if "window_px" in record:
        x0, y0, x1, y1 = record["window_px"]
        img, msk = img[y0:y1, x0:x1], msk[y0:y1, x0:x1]
        if lm is not None:
            lm = np.asarray(lm, np.float64) - [x0, y0] if record.get("window_has_cm", True) else None
    if record.get("rotate_180"):
        h, w = img.shape
        img, msk = img[::-1, ::-1], msk[::-1, ::-1]
        lm = None if lm is None else np.array([w - 1.0, h - 1.0]) - np.asarray(lm, np.float64)
    if record.get("transpose"):
        img, msk = img.T, msk.T
        lm = None if lm is None else np.asarray(lm, np.float64)[:, ::-1]
    if lm is not None and any(record.get("landmarks_nan", ())):
        lm = np.array(lm, np.float64)
        lm[np.asarray(record["landmarks_nan"], bool)] = np.nan
    if img is not image:
        img, msk = np.ascontiguousarray(img), np.ascontiguousarray(msk)
    if lm is not None and lm is not landmarks_px:
        lm = np.ascontiguousarray(lm)
    return img, msk, lm


def output_camera(camera: Camera, record: dict[str, Any]) -> Camera:
    """The camera of :func:`randomise_image`'s output image, given the input image's ``camera``.

    A window crops the camera; a rotation by 180° turns it about its axis (principal point mirrored).
    A transposed image is a mirror image, which no camera (rigid pose, positive focal lengths) gives:
    raises :class:`~fluoronav.errors.InputError` (map points with the record's ``pixel_affine``).
    """
    if record.get("transpose"):
        raise InputError("randomisation", "a transposed image has no camera; map points with pixel_affine")
    out = camera
    if "window_px" in record:
        x0, y0, x1, y1 = record["window_px"]
        out = out.crop(row0=y0, col0=x0, rows=y1 - y0, cols=x1 - x0)
    if record.get("rotate_180"):
        K = out.K.copy()
        K[0, 2] = out.cols - 1.0 - K[0, 2]
        K[1, 2] = out.rows - 1.0 - K[1, 2]
        pose = np.diag([-1.0, -1.0, 1.0, 1.0]) @ out.camera_from_world
        out = Camera(out.rows, out.cols, K, pose, out.pixel_spacing_mm)
    return out
