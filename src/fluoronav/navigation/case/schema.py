"""The navigation case file (``navigation.json``) as pydantic models: its keys, their types and the
rules that need no other file (docs/data-formats.md, "Navigation case").

:func:`validate_case` checks a case file's JSON object and turns the first problem into one
:class:`~fluoronav.errors.InputError` naming the file and the key path (``case.json:
views[1].camera: missing (...)``). Paths inside stay strings; :mod:`.model` resolves and reads them
and checks what needs those files (the robot's joint count and limits, the CM's control points, the
image sizes). Inline plans are checked by :func:`fluoronav.navigation.planning.plan_from_dict`, as
plan files are. The writer dumps the same models (absent optional keys are not written).
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from annotated_types import Ge, Gt, Len
from pydantic import (
    AfterValidator,
    AllowInfNan,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    SerializerFunctionWrapHandler,
    Strict,
    Tag,
    TypeAdapter,
    ValidationError,
    model_serializer,
    model_validator,
)
from pydantic_core import ErrorDetails, PydanticCustomError

from fluoronav.errors import InputError
from fluoronav.manipulator.config import CMConfig

__all__ = [
    "COMMENT_KEYS",
    "CaseFile",
    "InlineCamera",
    "MovedFrom",
    "RobotEntry",
    "Side",
    "Verification",
    "ViewEntry",
    "is_comment_key",
    "rigid_matrix",
    "validate_case",
    "view_names",
]

#: Top-level keys the reader skips (free text for people); any key starting with ``_`` is skipped too.
COMMENT_KEYS = ("description", "notes")
#: Tolerance of a rigid matrix's rotation part, element-wise on R Rᵀ − I (the contract's "to 1e-4").
RIGID_TOL = 1e-4
# union tags (see _source_kind): they appear in pydantic's error locations and are left out of messages
_FILE, _INLINE = "<file>", "<inline>"


def is_comment_key(key: str) -> bool:
    """Whether a top-level key is a comment (``description``, ``notes``, ``_…``)."""
    return key in COMMENT_KEYS or key.startswith("_")


def _problem(problem: str, field: str | None = None) -> PydanticCustomError:
    """A validation error whose message is ``problem`` (about ``field`` of the model, if given)."""
    ctx = {"problem": problem} if field is None else {"problem": problem, "field": field}
    return PydanticCustomError("case", "{problem}", ctx)


# ----- value types -------------------------------------------------------------------------------
def _not_blank(value: str) -> str:
    if not value.strip():
        raise _problem("expected a non-empty string")
    return value


def _real_array(value: Any) -> np.ndarray | None:
    """``value`` as float64 if it is a number or nested lists of numbers (not bools), else None."""

    def numeric(v: Any) -> bool:
        if isinstance(v, list):
            return all(numeric(x) for x in v)
        return isinstance(v, int | float) and not isinstance(v, bool)

    if not numeric(value):
        return None
    try:
        return np.asarray(value, dtype=np.float64)
    except ValueError:  # ragged
        return None


def _shaped(shape: tuple[int, ...], what: str) -> BeforeValidator:
    """Checks that a value is nested lists of finite numbers of ``shape``; one message says ``what``."""

    def check(value: Any) -> Any:
        arr = _real_array(value)
        if arr is None:
            raise _problem(f"expected {what}")
        if arr.shape != shape:
            raise _problem(f"expected {what}, got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise _problem(f"expected {what} of finite numbers")
        return value

    return BeforeValidator(check)


def _rigid(value: list[list[float]]) -> list[list[float]]:
    """A 4×4 whose rotation part is orthonormal (det +1) to :data:`RIGID_TOL` and last row 0 0 0 1."""
    T = np.asarray(value, dtype=np.float64)
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=RIGID_TOL) or np.linalg.det(R) < 0:
        raise _problem("expected a 4x4 rigid matrix (the rotation part is not orthonormal)")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise _problem("expected a 4x4 rigid matrix (the last row must be [0, 0, 0, 1])")
    return value


FiniteFloat = Annotated[float, Strict(), AllowInfNan(False)]
PositiveFloat = Annotated[float, Strict(), AllowInfNan(False), Gt(0)]
Name = Annotated[str, AfterValidator(_not_blank)]  # a file or view name
Side = Literal["left", "right"]
Readings = list[FiniteFloat]  # joint or FBG readings; their count is the robot's or the CM's
Vector3 = Annotated[list[FiniteFloat], Len(3, 3), _shaped((3,), "3 numbers")]
Landmarks = Annotated[
    list[Annotated[list[FiniteFloat], Len(2, 2)]], Len(2, 2), _shaped((2, 2), "[[uA, vA], [uB, vB]] (pixels)")
]
Matrix3 = Annotated[list[Annotated[list[FiniteFloat], Len(3, 3)]], Len(3, 3), _shaped((3, 3), "a 3x3 matrix")]
RigidMatrix = Annotated[
    list[Annotated[list[FiniteFloat], Len(4, 4)]],
    Len(4, 4),
    AfterValidator(_rigid),
    _shaped((4, 4), "a 4x4 rigid matrix"),
]


def _source_kind(value: Any) -> str | None:
    """The union tag of a key that takes a file name or an inline value (a model when written)."""
    if isinstance(value, str):
        return _FILE
    return _INLINE if isinstance(value, dict | list | BaseModel) else None


def _file_or(what: str) -> Discriminator:
    return Discriminator(_source_kind, custom_error_type="case", custom_error_message=f"expected {what}")


# ----- models ------------------------------------------------------------------------------------
class _CaseModel(BaseModel):
    """Base of the case file's objects: frozen, JSON types only, unknown keys refused."""

    model_config = ConfigDict(frozen=True, extra="forbid", strict=True, ser_json_inf_nan="constants")
    #: whether comment keys (:data:`COMMENT_KEYS`, ``_…``) are allowed and skipped (the top level)
    takes_comments: ClassVar[bool] = False

    @model_validator(mode="before")
    @classmethod
    def _keys(cls, data: Any) -> Any:
        """One message for a value that is no object, for unknown keys and for a missing key."""
        keys = list(cls.model_fields)
        if not isinstance(data, dict):
            raise _problem(f"expected an object with keys {keys}")
        if cls.takes_comments:
            data = {k: v for k, v in data.items() if not is_comment_key(k)}
        unknown = sorted(str(k) for k in data if k not in cls.model_fields)
        if unknown:
            note = ""
            if cls.takes_comments:
                note = f" (and {list(COMMENT_KEYS)} or keys starting with '_' for comments)"
            raise _problem(f"unknown key(s) {unknown}; allowed: {keys}{note}")
        for key, field in cls.model_fields.items():
            if field.is_required() and data.get(key) is None:
                raise _problem(f"missing (give {field.description})", field=key)
        return data

    @model_serializer(mode="wrap")
    def _without_absent(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """Absent optional keys (None) are not written."""
        return {k: v for k, v in handler(self).items() if v is not None}


class InlineCamera(_CaseModel):
    """A camera given inline: the camera file's keys (``camera_from_world`` = camera_from_ct)."""

    rows: Annotated[int, Gt(0)] = Field(description="the image's rows")
    cols: Annotated[int, Gt(0)] = Field(description="the image's columns")
    K: Matrix3 = Field(description="the 3x3 intrinsics, pixels")
    camera_from_world: RigidMatrix = Field(description="camera_from_ct, 4x4 mm")
    pixel_spacing_mm: PositiveFloat | None = None


class MovedFrom(_CaseModel):
    """A view's C-arm position: a first view's, moved by the C-arm's nominal motion since."""

    view: Name = Field(description="the first view's name")
    carm_after_from_carm_before: RigidMatrix = Field(description="the C-arm's motion, 4x4 mm")


CameraSource = Annotated[
    Annotated[Name, Tag(_FILE)] | Annotated[InlineCamera, Tag(_INLINE)],
    _file_or('a camera file, an inline camera or "dicom"'),
]


class ViewEntry(_CaseModel):
    """One C-arm image (``views[k]``); its fields are in the order the writer writes them."""

    name: Name | None = None
    image: Name = Field(description="an image file")
    camera: CameraSource = Field(description='a camera file, an inline camera or "dicom"')
    landmarks_px: Landmarks | None = None
    isocenter_ct_mm: Vector3 | None = None
    moved_from: MovedFrom | None = None
    same_camera_as: Name | None = None
    mask: Name | None = None

    @model_validator(mode="after")
    def _rules(self) -> ViewEntry:
        if self.same_camera_as is not None and self.moved_from is not None:
            raise _problem("give same_camera_as or moved_from, not both")
        if self.mask is not None and self.landmarks_px is None:
            raise _problem("given without landmarks_px (a mask comes with them)", field="mask")
        return self

    def carm_relation(self) -> tuple[str | None, np.ndarray | None]:
        """(the first view this one's C-arm position is from, the C-arm's motion since, (4, 4) mm)."""
        if self.same_camera_as is not None:
            return self.same_camera_as, np.eye(4)
        if self.moved_from is None:
            return None, None
        return self.moved_from.view, np.asarray(self.moved_from.carm_after_from_carm_before, np.float64)


ViewList = Annotated[list[ViewEntry], Len(1)]


def view_names(views: list[ViewEntry], prefix: str) -> list[str]:
    """The views' names: each its own ``name``, else ``<prefix><k>``."""
    return [f"{prefix}{k}" if v.name is None else v.name for k, v in enumerate(views)]


class RobotEntry(_CaseModel):
    """``robot``: the kinematic model, the joint readings while imaging, the hand-eye matrix."""

    model: Name = Field(description='"UR10" or a DH file')
    joints_deg: Readings = Field(description="the joint readings, degrees")
    ee_from_cm: Annotated[
        Annotated[Name, Tag(_FILE)] | Annotated[RigidMatrix, Tag(_INLINE)],
        _file_or("a 4x4 rigid matrix or a `calibrate` output file"),
    ] = Field(description="a 4x4 matrix or a `calibrate` output file")


class Verification(_CaseModel):
    """``verification``: the images after the robot moved and the joints read with them."""

    joints_deg: Readings = Field(description="the joint readings with the verification views, degrees")
    views: ViewList = Field(description="a non-empty list of views")


class CaseFile(_CaseModel):
    """A navigation case file; its fields are in the order the writer writes them."""

    takes_comments = True

    ct: Name = Field(description='a CT file, a DICOM directory or "phantom"')
    phantom_seed: Annotated[int, Ge(0)] | None = None
    labels: Name | None = None
    landmarks: Name | None = None
    plan: Annotated[
        Annotated[Name, Tag(_FILE)] | Annotated[dict[str, Any], Tag(_INLINE)],
        _file_or("a plan file or an inline plan object"),
    ] = Field(description="a plan file or an inline plan object")
    side: Side | None = None
    cm: (
        Annotated[
            Annotated[Name, Tag(_FILE)] | Annotated[CMConfig, Tag(_INLINE)],
            _file_or("a CM config file or an inline object"),
        ]
        | None
    ) = None
    fbg_control_points_deg: Readings | None = None
    fbg_sigma_deg: PositiveFloat | None = None
    robot: RobotEntry = Field(description="an object with model, joints_deg and ee_from_cm")
    isocenter_ct_mm: Vector3 | None = None
    views: ViewList = Field(description="a non-empty list of views")
    verification: Verification | None = None

    def is_phantom(self) -> bool:
        """Whether ``ct`` is ``"phantom"`` (the built-in hip phantom)."""
        return self.ct.strip().lower() == "phantom"

    @model_validator(mode="after")
    def _rules(self) -> CaseFile:
        own = [k for k in ("labels", "landmarks") if getattr(self, k) is not None]
        if self.is_phantom() and own:
            raise _problem(f"{own} cannot be given with 'ct': \"phantom\" (it has its own)")
        if not self.is_phantom() and self.phantom_seed is not None:
            raise _problem("'phantom_seed' is only for 'ct': \"phantom\"")
        if self.fbg_sigma_deg is not None and self.fbg_control_points_deg is None:
            raise _problem("'fbg_sigma_deg' is given without 'fbg_control_points_deg'")
        names = view_names(self.views, "view")
        _unique(names, "views")
        if self.verification is not None:
            _unique(view_names(self.verification.views, "verify"), "verification.views")
            for k, v in enumerate(self.verification.views):
                first, _ = v.carm_relation()
                if first is not None and first not in names:
                    raise _problem(
                        f"verification.views[{k}] names view {first!r}, which is not among the views"
                    )
        return self


def _unique(names: list[str], key: str) -> None:
    seen: set[str] = set()
    for k, name in enumerate(names):
        if name in seen:
            raise _problem(f"{key}[{k}].name {name!r} is used twice (view names must be unique)")
        seen.add(name)


# ----- errors ------------------------------------------------------------------------------------
def _path(loc: tuple[int | str, ...]) -> str:
    """``views[1].camera`` from a pydantic location (a lone top-level key quoted: ``'ct'``)."""
    parts = [p for p in loc if p not in (_FILE, _INLINE)]
    if len(parts) == 1 and isinstance(parts[0], str):
        return repr(parts[0])
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else f".{p}" if out else str(p)
    return out


def _message(error: ErrorDetails, prefix: tuple[int | str, ...] = ()) -> str:
    """One error as ``path: problem``."""
    ctx = error.get("ctx") or {}
    loc = (*prefix, *error["loc"], *([ctx["field"]] if "field" in ctx else []))
    problem = error["msg"]
    if error["type"] != "case":  # pydantic's own message, as a phrase
        problem = problem.removeprefix("Value error, ")
        problem = problem[:1].lower() + problem[1:]
    path = _path(loc)
    return f"{path}: {problem}" if path else problem


def validate_case(d: dict[str, Any], source: str) -> CaseFile:
    """The case file's JSON object → :class:`CaseFile`; its first problem is an :class:`InputError`
    naming ``source`` and the key path."""
    try:
        return CaseFile.model_validate(d)
    except ValidationError as exc:
        raise InputError(source, _message(exc.errors()[0])) from None


_RIGID_MATRIX: TypeAdapter[list[list[float]]] = TypeAdapter(RigidMatrix)


def rigid_matrix(value: Any, key: str, source: str) -> np.ndarray:
    """(4, 4) float64 from a rigid 4×4 ``value`` (as :data:`RigidMatrix` checks it); a problem is an
    :class:`InputError` naming ``source`` and ``key``."""
    try:
        return np.asarray(_RIGID_MATRIX.validate_python(value), dtype=np.float64)
    except ValidationError as exc:
        raise InputError(source, _message(exc.errors()[0], prefix=(key,))) from None
