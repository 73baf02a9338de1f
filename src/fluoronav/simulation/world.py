"""The simulated world of a navigation study: how far the inputs the method is given are from the truth.

In the ideal world (:data:`IDEAL`, the default) the X-ray images are rendered from the very CT the
registration uses, the case's cameras are the imaging cameras, the FBG reading is almost exact and the patient
keeps still. :data:`REALISTIC` switches on one source of error per input, each a sub-config that is off when
its magnitudes are zero (or None): :class:`CTWorld` (a clinical CT of a finer patient,
:mod:`fluoronav.simulation.clinical_ct`), :class:`CArmWorld` (calibration error, :func:`case_camera`, and
detector flex, :func:`flexed_camera`), :class:`FBGWorld` (noise and bias, :func:`fbg_reading`) and
:class:`MotionWorld` (:func:`patient_motion`). Every function takes a ``np.random.Generator`` and returns its
input unchanged when its source is off, so the ideal world draws nothing and changes nothing. The magnitudes
and where they come from: docs/simulation.md ("Simulated worlds").
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from fluoronav.errors import InputError, read_json_object
from fluoronav.geometry.camera import CIOS_FUSION, Camera
from fluoronav.simulation.instrument import BuiltCM, InstrumentWorld, spline_fit_control_points_deg

__all__ = [
    "IDEAL",
    "REALISTIC",
    "CArmWorld",
    "CTWorld",
    "FBGWorld",
    "MotionWorld",
    "World",
    "case_camera",
    "case_fbg_reading",
    "fbg_reading",
    "flexed_camera",
    "load_world",
    "patient_motion",
]


@dataclass(frozen=True)
class CTWorld:
    """The case's CT is not the patient the images are rendered from (all off by default).

    Attributes:
        patient_spacing_mm: isotropic voxel size (mm) of the "patient", the procedural phantom the
            X-ray images are rendered from (``hip_phantom(seed=, spacing_mm=)``), finer than the CT;
            None = the images are rendered from the case's CT itself. Realistic 0.5 mm: twice as fine
            as the paper's CT in-plane and fine enough that the 0.8 mm CT grid averages ≥ 1.6 patient
            voxels per axis (a 688 × 480 × 480 volume).
        ct_spacing_mm: (x, y, z) voxel size of the case's CT, mm; None = the CT is on the patient's
            grid. Realistic (0.8, 0.8, 1.5): assumed, a routine pelvic protocol (512² matrix over a
            ~40 cm field of view, 1.5 mm slices); coarser in z than the paper's 1.0 × 1.0 × 0.5 mm
            CT (Gao et al., IEEE TBME 2022), which had thin slices.
        hu_noise_sd: standard deviation of the CT's noise, HU (slightly correlated: white noise
            smoothed by a Gaussian of 0.7 voxel, rescaled to this SD). Realistic 15 HU: assumed, the
            order of routine-dose abdominopelvic CT; Christianson, Winslow, Frush and Samei (AJR,
            "Automated technique to measure noise in clinical CT examinations") find the median noise
            level varies by 15–35 % across scanner models, so one value is only a typical one.
        hu_scale_error: relative error of the CT number scale: HU × (1 ± e), sign drawn per CT.
            Realistic 0.03: assumed; water is held to ±5 HU by QC, but bone HU depends on the kVp, the
            filter and the scanner by a few per cent.
        label_boundary_voxels: standard deviation of the label boundaries' displacement, in CT
            voxels (the mean of ``ct_spacing_mm`` sets the millimetres): a smooth random field
            dilates each bone in some places and erodes it in others, as an automatic segmentation's
            error. Realistic 1.0: assumed, pessimistic; a learned segmentation of lower-extremity
            bones reports a mean surface distance of 0.26 ± 0.12 mm (PMC9790725), older or
            cross-site ones are coarser.
        label_smoothness_mm: correlation length (Gaussian σ) of that field, mm. Realistic 10 mm:
            assumed (segmentation errors extend over a few centimetres of a surface).
    """

    patient_spacing_mm: float | None = None
    ct_spacing_mm: tuple[float, float, float] | None = None
    hu_noise_sd: float = 0.0
    hu_scale_error: float = 0.0
    label_boundary_voxels: float = 0.0
    label_smoothness_mm: float = 10.0

    @property
    def enabled(self) -> bool:
        """Whether the case's CT differs from the patient at all."""
        return bool(
            self.patient_spacing_mm is not None
            or self.ct_spacing_mm is not None
            or self.hu_noise_sd > 0
            or self.hu_scale_error > 0
            or self.label_boundary_voxels > 0
        )


@dataclass(frozen=True)
class CArmWorld:
    """The case's cameras are not the imaging cameras (all off by default).

    Attributes:
        sdd_error_sd_frac: relative SD of the case's source-to-detector distance (focal length)
            error. Realistic 0.005 (≈ 5 mm of 1020 mm): assumed; Jain, Kon, Zhou and Fichtinger
            (MICCAI 2005, "C-arm calibration – is it really necessary?") show that a focal spot
            mis-calibrated by as much as 50 mm still tracks to 0.5 mm, so a few mm is a calibrated
            C-arm's plausible residual.
        principal_point_error_sd_px: SD of the case's principal point error per coordinate, in
            full-detector pixels (``detector_pixel_mm`` each). Realistic 3 px (≈ 0.6 mm): assumed;
            the piercing point of a mobile C-arm wanders by up to 15.8 mm over its orbit but is
            reproducible to < 0.16 mm (Daly et al., Med Phys 35(5), 2008), so a calibration taken
            at another angle or day errs by a few pixels.
        flex_detector_shift_mm: in-plane detector shift of each image's geometry from the nominal
            one, mm (exactly this length, random direction per view), as gantry flex moves it; the
            case keeps the nominal geometry. Realistic 1.0 mm: assumed; Daly et al. (Med Phys 2008)
            measure flex departures of the piercing point up to 15.8 mm over a full orbit (the
            views here span ~35°), Fahrig and Holdsworth (Med Phys 27(1), 2000) a gantry motion
            reproducible to ~0.1 mm, so an uncorrected flex of ~1 mm between nearby angles.
        detector_pixel_mm: full-detector pixel pitch the pixel magnitudes refer to (CIOS Fusion).
    """

    sdd_error_sd_frac: float = 0.0
    principal_point_error_sd_px: float = 0.0
    flex_detector_shift_mm: float = 0.0
    detector_pixel_mm: float = CIOS_FUSION.pixel_spacing_mm

    @property
    def enabled(self) -> bool:
        """Whether any C-arm error is on."""
        return bool(
            self.sdd_error_sd_frac > 0
            or self.principal_point_error_sd_px > 0
            or self.flex_detector_shift_mm > 0
        )


@dataclass(frozen=True)
class FBGWorld:
    """The FBG reading of the CM's control points (``fbg_control_points_deg``) (off by default).

    Attributes:
        noise_sd_deg: SD of independent Gaussian noise on each of the control points, degrees.
        bias_deg: a bias of exactly this size, the same sign on every control point (a curvature
            calibration offset; the sign is drawn per reading), degrees.
        stated_sigma_deg: the accuracy the case states for its reading (the case's
            ``fbg_sigma_deg``), one standard deviation per control point, degrees; None: the
            reading's true RMS error, ``hypot(noise_sd_deg, bias_deg)`` (an honest sensor). A value
            below that makes a sensor that claims more than it delivers (a lost calibration).

    Notes:
        Realistic 0.06° noise and 0.06° bias: chosen so that the CM tip error they imply
        (:class:`~fluoronav.manipulator.kinematics.CMKinematics`, ``tip_cm``, over control points
        U(−5°, 5°)) is that reported for FBG shape sensing of this CM: tip error 0.50 ± 0.18 mm
        (Sefati et al., IEEE/ASME TMECH 2021), below the maximum distal-end errors in free bending of
        0.78 mm (data-driven) to 2.45 mm (model-based) (Sefati et al., IEEE Sensors J 2021); the test
        ``test_realistic_fbg_tip_error_in_literature_range`` measures it. Apply it to the true control
        points in place of the paper's simulated reading, truth + U(−0.5°, 0.5°) (Gao et al., IEEE
        TBME 2022), which implies a tip error about twice that reported.
    """

    noise_sd_deg: float = 0.0
    bias_deg: float = 0.0
    stated_sigma_deg: float | None = None

    def __post_init__(self) -> None:
        if self.stated_sigma_deg is not None and not self.stated_sigma_deg > 0:
            raise ValueError(f"stated_sigma_deg must be positive, got {self.stated_sigma_deg}")

    @property
    def enabled(self) -> bool:
        """Whether the FBG reading has any error."""
        return bool(self.noise_sd_deg > 0 or self.bias_deg > 0)

    def stated_sigma(self) -> float | None:
        """The accuracy the case states (``stated_sigma_deg``, or the honest RMS error); None when
        the source is off (the ideal world's case states none)."""
        if not self.enabled:
            return None
        if self.stated_sigma_deg is not None:
            return float(self.stated_sigma_deg)
        return math.hypot(self.noise_sd_deg, self.bias_deg)


@dataclass(frozen=True)
class MotionWorld:
    """Rigid motion of the patient (pelvis and femurs together) (off by default).

    Attributes:
        between_sets_mm, between_sets_deg: translation (mm) and rotation about a random axis through
            the pelvis centre (degrees), each of exactly this size, between the first image set and
            the verification images. Realistic 1.0 mm / 0.5°: assumed (a fixed, draped patient
            nudged while the robot works; no measurement was found).
        within_set_mm, within_set_deg: the same between the views of one set (each view moved from
            the set's pose). Realistic 0.3 mm / 0.1°: assumed (breathing and table vibration over
            the tens of seconds of a C-arm reorientation).
    """

    between_sets_mm: float = 0.0
    between_sets_deg: float = 0.0
    within_set_mm: float = 0.0
    within_set_deg: float = 0.0

    @property
    def enabled(self) -> bool:
        """Whether the patient moves at all."""
        return bool(
            self.between_sets_mm > 0
            or self.between_sets_deg > 0
            or self.within_set_mm > 0
            or self.within_set_deg > 0
        )


@dataclass(frozen=True)
class World:
    """The simulated world of a navigation study: one switchable source of error per input.

    Attributes:
        name: the preset's name, or the JSON file's stem.
        ct, carm, fbg, motion, instrument: the sources (see their classes); defaults are all off.
    """

    name: str = "ideal"
    ct: CTWorld = field(default_factory=CTWorld)
    carm: CArmWorld = field(default_factory=CArmWorld)
    fbg: FBGWorld = field(default_factory=FBGWorld)
    motion: MotionWorld = field(default_factory=MotionWorld)
    instrument: InstrumentWorld = field(default_factory=InstrumentWorld)

    @property
    def is_ideal(self) -> bool:
        """True when every source is off (the studies' world before worlds existed)."""
        return not (
            self.ct.enabled
            or self.carm.enabled
            or self.fbg.enabled
            or self.motion.enabled
            or self.instrument.enabled
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (the name and every magnitude), for results.json; :func:`load_world` reads it."""
        d: dict[str, Any] = {"name": self.name}
        for key in _SECTIONS:
            sub = dataclasses.asdict(getattr(self, key))
            d[key] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in sub.items()}
        return d


_SECTIONS: dict[str, type] = {
    "ct": CTWorld,
    "carm": CArmWorld,
    "fbg": FBGWorld,
    "motion": MotionWorld,
    "instrument": InstrumentWorld,
}

#: Every source off: the images are rendered from the case's CT with the case's cameras.
IDEAL = World(name="ideal")

#: Every source on at the magnitudes documented on each field.
REALISTIC = World(
    name="realistic",
    ct=CTWorld(
        patient_spacing_mm=0.5,
        ct_spacing_mm=(0.8, 0.8, 1.5),
        hu_noise_sd=15.0,
        hu_scale_error=0.03,
        label_boundary_voxels=1.0,
    ),
    carm=CArmWorld(sdd_error_sd_frac=0.005, principal_point_error_sd_px=3.0, flex_detector_shift_mm=1.0),
    fbg=FBGWorld(noise_sd_deg=0.06, bias_deg=0.06),
    motion=MotionWorld(between_sets_mm=1.0, between_sets_deg=0.5, within_set_mm=0.3, within_set_deg=0.1),
    instrument=InstrumentWorld.realistic(),
)

_PRESETS = {"ideal": IDEAL, "realistic": REALISTIC}


def _parse_section(cls: type, value: object, key: str, source: str) -> Any:
    if not isinstance(value, dict):
        raise InputError(source, f"{key} must be a JSON object")
    allowed = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(value) - set(allowed))
    if unknown:
        raise InputError(source, f"{key}: unknown field(s) {unknown}; allowed: {sorted(allowed)}")
    kwargs: dict[str, Any] = {}
    for name, v in value.items():
        if v is None:
            if "None" not in str(allowed[name].type):
                raise InputError(source, f"{key}.{name} cannot be null")
            kwargs[name] = None
        elif name == "ct_spacing_mm":
            if not isinstance(v, list) or len(v) != 3 or not all(_is_number(x) and x > 0 for x in v):
                raise InputError(source, f"{key}.{name} must be three positive numbers or null")
            kwargs[name] = tuple(float(x) for x in v)
        elif not _is_number(v) or v < 0:
            raise InputError(source, f"{key}.{name} must be a non-negative number")
        else:
            kwargs[name] = float(v)
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:  # a field's own constraint (FBGWorld.stated_sigma_deg)
        raise InputError(source, f"{key}: {exc}") from None


def _is_number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def load_world(name_or_path: str) -> World:
    """A preset by name (``"ideal"``, ``"realistic"``) or a world read from a JSON file.

    The file holds an object with an optional ``name`` and any of the sections ``ct``, ``carm``,
    ``fbg`` and ``motion``, each with any subset of its fields. Unspecified fields take the
    :data:`IDEAL` values (off), so ``{"fbg": {"noise_sd_deg": 0.5}}`` is that one source alone; start
    from ``REALISTIC.to_dict()`` to vary a realistic world. The name defaults to the file's stem.

    Raises:
        InputError: an unknown preset, a missing or unreadable file, invalid JSON, an unknown section
            or field, or a value of the wrong type (one line naming the file).
    """
    if name_or_path in _PRESETS:
        return _PRESETS[name_or_path]
    path = Path(name_or_path)
    if path.suffix.lower() != ".json" and not path.exists():
        raise InputError(name_or_path, f"unknown world; use one of {sorted(_PRESETS)} or a JSON file")
    d = read_json_object(path, what="world file")
    source = str(path)
    unknown = sorted(set(d) - {"name", *_SECTIONS})
    if unknown:
        raise InputError(source, f"unknown key(s) {unknown}; allowed: {['name', *_SECTIONS]}")
    name = d.get("name", path.stem)
    if not isinstance(name, str) or not name.strip():
        raise InputError(source, "name must be a non-empty string")
    sections = {key: _parse_section(cls, d[key], key, source) for key, cls in _SECTIONS.items() if key in d}
    return World(name=name, **sections)


# ---------------------------------------------------------------------------------------------
# C-arm, FBG and motion errors
# ---------------------------------------------------------------------------------------------


def _pixels_per_detector_px(camera: Camera, cfg: CArmWorld) -> float:
    """This camera's pixels per full-detector pixel (a binned camera has fewer)."""
    if camera.pixel_spacing_mm is None:
        return 1.0
    return cfg.detector_pixel_mm / camera.pixel_spacing_mm


def case_camera(imaging: Camera, cfg: CArmWorld, rng: np.random.Generator) -> Camera:
    """The camera the case records for an image: the imaging camera with a calibration error.

    The focal length (source-to-detector distance) is scaled by ``1 + N(0, sdd_error_sd_frac)`` and
    the principal point moved by ``N(0, principal_point_error_sd_px)`` full-detector pixels per
    coordinate; the pose, the image size and the pixel spacing are kept.

    Args:
        imaging: the camera the image was taken with.
        cfg: the C-arm errors.
        rng: draws 3 normals when either error is on, nothing otherwise.

    Returns:
        ``imaging`` itself when both errors are off, else a new camera.
    """
    if cfg.sdd_error_sd_frac <= 0 and cfg.principal_point_error_sd_px <= 0:
        return imaging
    scale = 1.0 + cfg.sdd_error_sd_frac * rng.standard_normal()
    dpp = cfg.principal_point_error_sd_px * _pixels_per_detector_px(imaging, cfg) * rng.standard_normal(2)
    K = imaging.K.copy()
    K[0, 0] *= scale
    K[1, 1] *= scale
    K[:2, 2] += dpp
    return Camera(imaging.rows, imaging.cols, K, imaging.camera_from_world, imaging.pixel_spacing_mm)


def flexed_camera(nominal: Camera, cfg: CArmWorld, rng: np.random.Generator) -> Camera:
    """The camera an image is really taken with: the nominal one with its detector flexed in plane.

    The detector moves by exactly ``flex_detector_shift_mm`` in a uniformly random in-plane
    direction, the source stays, so every projection moves by that shift the other way on the
    panel: the principal point moves by ``−shift / pixel pitch``.

    Args:
        nominal: the camera of the nominal (calibrated) geometry.
        cfg: the C-arm errors.
        rng: draws one uniform when the flex is on, nothing otherwise.

    Returns:
        ``nominal`` itself when the flex is off, else a new camera.
    """
    if cfg.flex_detector_shift_mm <= 0:
        return nominal
    pitch_mm = nominal.pixel_spacing_mm if nominal.pixel_spacing_mm is not None else cfg.detector_pixel_mm
    angle = rng.uniform(0.0, 2.0 * math.pi)
    shift_px = cfg.flex_detector_shift_mm / pitch_mm * np.array([math.cos(angle), math.sin(angle)])
    K = nominal.K.copy()
    K[:2, 2] -= shift_px
    return Camera(nominal.rows, nominal.cols, K, nominal.camera_from_world, nominal.pixel_spacing_mm)


def fbg_reading(true_control_points_deg: np.ndarray, cfg: FBGWorld, rng: np.random.Generator) -> np.ndarray:
    """The FBG reading of the control points: truth + ±bias (one sign per reading) + Gaussian noise.

    Args:
        true_control_points_deg: (..., n) control points, degrees.
        cfg: the FBG errors.
        rng: draws a uniform per reading (the bias sign, one per leading index) and the noise when
            on, nothing otherwise.

    Returns:
        (..., n) float64 reading, degrees; the input itself when both errors are off.
    """
    if not cfg.enabled:
        return true_control_points_deg
    cp = np.asarray(true_control_points_deg, dtype=np.float64)
    sign = np.where(rng.uniform(size=cp.shape[:-1]) < 0.5, 1.0, -1.0)[..., None]
    return cp + sign * cfg.bias_deg + cfg.noise_sd_deg * rng.standard_normal(cp.shape)


def case_fbg_reading(
    ideal_reading_deg: np.ndarray,
    true_control_points_deg: np.ndarray,
    cfg: FBGWorld,
    rng: np.random.Generator,
    *,
    built: BuiltCM | None = None,
) -> np.ndarray:
    """The FBG reading a simulated case gives: :func:`fbg_reading` of the true shape where the FBG
    source is on, else the ideal world's reading (the protocol's, truth ± 0.5°).

    An FBG senses the strain of the fibre in the instrument it is in: with the instrument as built
    (``built``) the reading is of that shape (the model's nearest to it,
    :func:`~fluoronav.simulation.instrument.spline_fit_control_points_deg`), not of the commanded
    control points; the ideal reading keeps its error about that shape.

    Args:
        ideal_reading_deg: (n,) the ideal world's reading of the commanded control points.
        true_control_points_deg: (n,) the commanded (true) control points, degrees.
        cfg: the FBG errors.
        rng: drawn from only where the FBG source is on (:func:`fbg_reading`).
        built: the instrument as built, or None (the model).

    Returns:
        (n,) float64 reading, degrees; ``ideal_reading_deg`` itself in the ideal world.
    """
    cp = np.asarray(true_control_points_deg, np.float64)
    sensed = cp if built is None else spline_fit_control_points_deg(built, cp).numpy()
    if cfg.enabled:
        return fbg_reading(sensed, cfg, rng)
    if built is None:
        return ideal_reading_deg
    return np.asarray(ideal_reading_deg, np.float64) + (sensed - cp)


def _unit_vector(rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def patient_motion(
    translation_mm: float, rotation_deg: float, rng: np.random.Generator, *, center_world: np.ndarray
) -> np.ndarray:
    """A rigid patient motion of exactly the given sizes (world frame, mm).

    Args:
        translation_mm: length of the translation, in a uniformly random direction.
        rotation_deg: angle of the rotation about a uniformly random axis through ``center_world``.
        rng: draws two unit vectors when either is non-zero, nothing otherwise.
        center_world: (3,) centre of the rotation, mm (e.g. the pelvis centre).

    Returns:
        (4, 4) ``moved_from_world``: ``p' = R (p − c) + c + t``; the identity when both are zero.
    """
    T = np.eye(4)
    if translation_mm <= 0 and rotation_deg <= 0:
        return T
    axis = _unit_vector(rng)
    direction = _unit_vector(rng)
    R = Rotation.from_rotvec(math.radians(rotation_deg) * axis).as_matrix()
    c = np.asarray(center_world, dtype=np.float64).reshape(3)
    T[:3, :3] = R
    T[:3, 3] = c - R @ c + translation_mm * direction
    return T
