"""Settings trees of frozen dataclasses, and the TOML files a site sets them from.

A field declares its one-line doc, unit and range with :func:`setting`. A settings file gives
overrides by dotted path (``safety.max_joint_motion_deg = 20``) or as TOML tables (``[safety]``); a
tuple of dataclasses is an array of tables, each element built on the one of that index; ``"none"``
sets a field that may be None to None (TOML has no null). :func:`load_settings` applies them with
:func:`dataclasses.replace`, checking types and ranges: an unknown key or a bad value is one
:class:`~fluoronav.errors.InputError` naming the file and the key. A root dataclass may name paths a
file cannot set (a ``derived_settings`` class variable: pattern → why; the program sets them).
:func:`settings_dict` (JSON) and :func:`settings_toml` (an editable file of the values, each key
with its doc and unit as a comment) write a tree out; the TOML loads back to an equal tree.
"""

from __future__ import annotations

import dataclasses
import difflib
import fnmatch
import functools
import inspect
import json
import math
import operator
import re
import tomllib
import types
import typing
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, Literal, TypeVar, Union

from fluoronav.errors import InputError

__all__ = [
    "NONE",
    "apply_settings",
    "load_settings",
    "setting",
    "settings_dict",
    "settings_toml",
]

T = TypeVar("T")

#: how a settings file says None
NONE = "none"

_MISSING: Any = dataclasses.MISSING
_SCALARS = (bool, int, float, str)
_RANGES = (("ge", "at least"), ("gt", "more than"), ("le", "at most"), ("lt", "less than"))
_RANGE_OK = {"ge": operator.ge, "gt": operator.gt, "le": operator.le, "lt": operator.lt}


def setting(
    default: Any = _MISSING,
    doc: str = "",
    *,
    default_factory: Any = _MISSING,
    unit: str = "",
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    site: bool = True,
) -> Any:
    """A dataclass field with its one-line ``doc``, ``unit`` and range (``ge``, ``gt``, ``le``, ``lt``;
    of each element of a tuple), checked where a settings file sets it. ``site`` False: a run's own
    option (e.g. the device), recorded but not read from a settings file."""
    meta = {"doc": doc, "unit": unit, "ge": ge, "gt": gt, "le": le, "lt": lt, "site": site}
    if default_factory is not _MISSING:
        return dataclasses.field(default_factory=default_factory, metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


class _Bad(Exception):
    """A key of a settings file that cannot be applied: its dotted path and the problem."""

    def __init__(self, path: str, problem: str) -> None:
        super().__init__(f"key {path}: {problem}")
        self.path, self.problem = path, problem


# ----- the types of a tree ---------------------------------------------------------------------------
@functools.cache
def _fields(cls: type) -> dict[str, tuple[dataclasses.Field[Any], Any]]:
    """The init fields of a dataclass with their resolved types."""
    hints = typing.get_type_hints(cls)
    return {f.name: (f, hints[f.name]) for f in dataclasses.fields(cls) if f.init}


def _strip_optional(tp: Any) -> tuple[Any, bool]:
    """``(T, True)`` for ``T | None``, ``(tp, False)`` otherwise."""
    if typing.get_origin(tp) in (Union, types.UnionType):
        args = typing.get_args(tp)
        rest = tuple(a for a in args if a is not type(None))
        return (rest[0] if len(rest) == 1 else Union[rest]), len(rest) < len(args)  # noqa: UP007
    return tp, False


def _is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _derived(cls: type) -> dict[str, str]:
    """The root's paths a settings file cannot set (glob patterns → why)."""
    return dict(getattr(cls, "derived_settings", {}))


def _join(path: str, name: str) -> str:
    return f"{path}.{name}" if path else name


def _matching(patterns: Mapping[str, str], path: str) -> str | None:
    return next((why for pattern, why in patterns.items() if fnmatch.fnmatchcase(path, pattern)), None)


# ----- applying a file ----------------------------------------------------------------------------
class _Applier:
    """Applies a nested mapping of overrides to a tree (one settings file)."""

    def __init__(self, root: Any) -> None:
        self.root, self.derived = root, _derived(type(root))

    def fixed(self, path: str, f: dataclasses.Field[Any]) -> str | None:
        """Why a file may not set ``path``; None where it may."""
        if not f.metadata.get("site", True):
            return "a run's own option, set on the command line"
        return _matching(self.derived, path)

    def table(self, current: Any, cls: type, data: Any, path: str) -> Any:
        """A dataclass ``cls`` with the overrides ``data`` on ``current`` (None: on its defaults)."""
        if not isinstance(data, dict):
            raise _Bad(path, f"a table of {cls.__name__} settings expected, got {_what(data)}")
        fields = _fields(cls)
        changes: dict[str, Any] = {}
        for key, value in data.items():
            full = _join(path, key)
            if key not in fields:
                raise _Bad(full, "unknown setting" + self.suggestion(key, path, fields))
            f, tp = fields[key]
            why = self.fixed(full, f)
            if why is not None:
                raise _Bad(full, f"not a site setting ({why})")
            cur = getattr(current, key) if current is not None else _field_default(f)
            cur = None if cur is _MISSING else cur
            changes[key] = self.value(tp, value, cur, full, f.metadata)
        if current is None:
            missing = [
                n for n, (f, _) in fields.items() if _field_default(f) is _MISSING and n not in changes
            ]
            if missing:
                raise _Bad(path, f"is none: a table that sets it must give {', '.join(missing)}")
        try:
            return cls(**changes) if current is None else dataclasses.replace(current, **changes)
        except (TypeError, ValueError) as exc:
            raise _Bad(path or "(top)", str(exc)) from None

    def value(self, tp: Any, value: Any, current: Any, path: str, meta: Mapping[str, Any]) -> Any:
        """``value`` from the file as a value of type ``tp`` (built on ``current``), checked."""
        inner, optional = _strip_optional(tp)
        if optional and value == NONE:
            return None
        if _is_dataclass_type(inner):
            return self.table(current, inner, value, path)
        origin = typing.get_origin(inner)
        if origin is tuple:
            return self.array(inner, value, current, path, meta)
        if origin is Literal:
            choices = typing.get_args(inner)
            if not isinstance(value, str) or value not in choices:
                raise _Bad(path, f"one of {', '.join(map(repr, choices))} expected, got {_what(value)}")
            return value
        if inner in _SCALARS:
            return _in_range(_scalar(inner, value, path), meta, path)
        raise _Bad(path, "cannot be set from a settings file")

    def array(self, tp: Any, value: Any, current: Any, path: str, meta: Mapping[str, Any]) -> tuple[Any, ...]:
        """A tuple from a TOML array (of values, or of tables built on ``current``'s elements)."""
        if not isinstance(value, list):
            raise _Bad(path, f"an array expected, got {_what(value)}")
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            types_ = [args[0]] * len(value)
        elif len(args) != len(value):
            raise _Bad(path, f"an array of {len(args)} values expected, got {len(value)}")
        else:
            types_ = list(args)
        cur = current if isinstance(current, tuple) else ()
        return tuple(
            self.value(t, v, cur[i] if i < len(cur) else None, f"{path}[{i}]", meta)
            for i, (t, v) in enumerate(zip(types_, value, strict=True))
        )

    def suggestion(self, key: str, path: str, fields: Mapping[str, Any]) -> str:
        """`` (did you mean X?)`` for a misspelled or misplaced key, or ""."""
        here = difflib.get_close_matches(key, list(fields), n=1, cutoff=0.6)
        if here:
            return f" (did you mean {_join(path, here[0])}?)"
        leaves: dict[str, str] = {}  # elsewhere in the tree: the first path of each name
        for p in self.paths(self.root, ""):
            leaves.setdefault(p.rsplit(".", 1)[-1], p)
        near = difflib.get_close_matches(key, list(leaves), n=1, cutoff=0.6)
        return f" (did you mean {leaves[near[0]]}?)" if near else ""

    def paths(self, obj: Any, path: str) -> Iterator[str]:
        """Every path a file may set below ``obj`` (not into tuples)."""
        for name, (f, _) in _fields(obj.__class__).items():
            full = _join(path, name)
            if self.fixed(full, f) is not None:
                continue
            yield full
            value = getattr(obj, name)
            if dataclasses.is_dataclass(value) and not isinstance(value, type):
                yield from self.paths(value, full)


def _field_default(f: dataclasses.Field[Any]) -> Any:
    """A field's default (``dataclasses.MISSING`` where it has none)."""
    if f.default_factory is not _MISSING:
        return typing.cast(Callable[[], Any], f.default_factory)()
    return f.default


def _what(value: Any) -> str:
    """A file's value as a message names it."""
    if isinstance(value, dict):
        return "a table"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value)


def _scalar(tp: type, value: Any, path: str) -> Any:
    """A bool, int, float or str from the file (an int is a float too; a bool is neither)."""
    if tp is bool and isinstance(value, bool):
        return value
    if tp is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if tp is float and isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    if tp is str and isinstance(value, str):
        return value
    expected = {bool: "true or false", int: "an integer", float: "a number", str: "a string"}[tp]
    raise _Bad(path, f"{expected} expected, got {_what(value)}")


def _in_range(value: Any, meta: Mapping[str, Any], path: str) -> Any:
    """``value`` where it lies within the field's declared range."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return value
    for key, words in _RANGES:
        bound = meta.get(key)
        if bound is not None and not _RANGE_OK[key](value, bound):
            unit = f" {meta['unit']}" if meta.get("unit") else ""
            raise _Bad(path, f"{value:g}{unit} is out of range (must be {words} {bound:g}{unit})")
    return value


def apply_settings(base: T, overrides: Mapping[str, Any], *, source: str | Path = "settings") -> T:
    """``base`` (a frozen dataclass) with the nested ``overrides`` (a parsed settings file) applied.

    Raises:
        InputError: ``source``, naming the key: unknown, not settable, of the wrong type or out of range.
    """
    applier = _Applier(base)
    try:
        out: T = applier.table(base, type(base), dict(overrides), "")
    except _Bad as bad:
        raise InputError(source, f"key {bad.path}: {bad.problem}") from None
    return out


def load_settings(base: T, path: str | Path) -> T:
    """``base`` with the overrides of the TOML settings file ``path`` (:func:`apply_settings`).

    Raises:
        InputError: the file is missing, unreadable or not TOML, or a key cannot be applied.
    """
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(p, "settings file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(p, f"cannot read the settings file ({exc.__class__.__name__})") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(p, f"not valid TOML ({exc})") from None
    return apply_settings(base, data, source=p)


# ----- writing a tree -----------------------------------------------------------------------------
def settings_dict(config: Any) -> dict[str, Any]:
    """The tree as JSON-ready nested dicts (tuples as lists), the root's derived settings left out."""
    out = _json_value(config, "", _derived(type(config)))
    assert isinstance(out, dict)
    return out


def _json_value(value: Any, path: str, derived: Mapping[str, str]) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            f.name: _json_value(getattr(value, f.name), _join(path, f.name), derived)
            for f in dataclasses.fields(value)
            if _matching(derived, _join(path, f.name)) is None
        }
    if isinstance(value, tuple | list):
        return [_json_value(v, f"{path}[{i}]", derived) for i, v in enumerate(value)]
    if value is None or isinstance(value, _SCALARS):
        return value
    dump = getattr(value, "model_dump", None)
    return dump(mode="json") if callable(dump) else repr(value)


def settings_toml(config: Any, *, title: str = "") -> str:
    """The tree as a TOML settings file: every key a file may set, with its value and, above it, its
    one-line doc, unit and range as a comment; tuples of dataclasses as arrays of tables. Loading it
    onto a tree of the same type gives ``config`` back."""
    lines = [f"# {line}".rstrip() for line in title.splitlines()]
    derived = _derived(type(config))
    if derived:
        lines += [
            "# Not settable here (the program sets them):",
            *(f"#   {k}: {v}" for k, v in derived.items()),
        ]
    lines.append(f'# A value "{NONE}" sets a setting that may be None to None.')
    _toml_table(config, "", "", lines, derived)
    return "\n".join(lines) + "\n"


def _toml_table(obj: Any, path: str, key: str, out: list[str], derived: Mapping[str, str]) -> None:
    """``obj``'s keys (``path``: its logical path, ``key``: its TOML key), then its tables."""
    docs = _attribute_docs(obj.__class__)
    tables: list[tuple[str, Any, str]] = []
    for name, (f, _) in _fields(obj.__class__).items():
        full = _join(path, name)
        if _matching(derived, full) is not None:
            continue
        value = getattr(obj, name)
        comment = _comment(f.metadata, docs.get(name, ""))
        if not f.metadata.get("site", True):
            out.append(f"# {name}: {comment or 'a run option'}; set by the run, not here")
            continue
        if (dataclasses.is_dataclass(value) and not isinstance(value, type)) or (
            isinstance(value, tuple) and value and all(dataclasses.is_dataclass(v) for v in value)
        ):
            tables.append((name, value, comment))
            continue
        if not _toml_writable(value):
            out.append(f"# {name}: not settable here")
            continue
        if comment:
            out.append(f"# {comment}")
        out.append(f"{name} = {_toml_value(value)}")
    for name, value, comment in tables:
        full, sub = _join(path, name), _join(key, name)
        about = [f"# {comment}"] if comment else []
        if isinstance(value, tuple):
            for i, element in enumerate(value):
                out += ["", f"[[{sub}]]", *about]
                _toml_table(element, f"{full}[{i}]", sub, out, derived)
        else:
            out += ["", f"[{sub}]", *about]
            _toml_table(value, full, sub, out, derived)


def _comment(meta: Mapping[str, Any], fallback: str) -> str:
    """A key's comment: its doc, then its unit and range in parentheses."""
    doc = meta.get("doc") or fallback
    extra = [meta["unit"]] if meta.get("unit") else []
    signs = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<"}
    extra += [f"{signs[k]} {meta[k]:g}" for k, _ in _RANGES if meta.get(k) is not None]
    return doc + (f" ({', '.join(extra)})" if extra else "")


def _toml_writable(value: Any) -> bool:
    if value is None or isinstance(value, _SCALARS):
        return True
    return isinstance(value, tuple) and all(_toml_writable(v) for v in value)


def _toml_value(value: Any) -> str:
    if value is None:
        return json.dumps(NONE)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return repr(value) if math.isfinite(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # a JSON string is a TOML basic string
    return "[" + ", ".join(_toml_value(v) for v in value) + "]"


@functools.cache
def _attribute_docs(cls: type) -> dict[str, str]:
    """The first sentence of each attribute in the class docstring's ``Attributes:`` section (the
    comment of a field declared without :func:`setting`)."""
    doc = inspect.getdoc(cls) or ""
    match = re.search(r"^Attributes:\s*$", doc, re.MULTILINE)
    if match is None:
        return {}
    texts: dict[str, str] = {}
    indent, names = -1, []
    for line in doc[match.end() :].splitlines():
        if not line.strip():
            continue
        depth = len(line) - len(line.lstrip())
        indent = depth if indent < 0 else indent
        if depth < indent:
            break
        item = re.match(r"([\w, ]+?):\s+(.*)", line.strip()) if depth == indent else None
        if item is not None:
            names = [n.strip() for n in item.group(1).split(",")]
            texts.update({n: item.group(2) for n in names})
        else:
            texts.update({n: f"{texts[n]} {line.strip()}" for n in names})
    return {n: _first_sentence(t) for n, t in texts.items()}


def _first_sentence(text: str) -> str:
    text = re.sub(r":\w+:`~?([^`]+)`", r"\1", " ".join(text.split())).replace("``", "")
    end = re.search(r"(?<!e\.g)(?<!i\.e)\.(\s|$)", text)
    text = text[: end.start()] if end else text
    return text if len(text) <= 100 else text[:97].rsplit(" ", 1)[0] + " ..."
