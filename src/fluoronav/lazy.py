"""Lazy package faces: a face names its API, and a name's module is imported on its first use.

Why: ``fluoronav navigate`` should load only the modules it runs, while ``from fluoronav.detection
import Detector`` keeps working. A face writes its imports under ``if TYPE_CHECKING:`` (what type
checkers and readers see) and :func:`lazy_face` reads them from the face's source, once.
NOTE: a name that is also a submodule's name (``roll_scan`` in ``roll_scan.py``) is bound at once:
importing that submodule would otherwise bind the module to the name.
"""

from __future__ import annotations

import ast
import importlib
import pkgutil
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

__all__ = ["lazy_face"]


def type_checking_imports(source: str) -> dict[str, list[str]]:
    """module → names of the ``from module import names`` under a module's ``if TYPE_CHECKING:``."""
    exports: dict[str, list[str]] = {}
    for node in ast.parse(source).body:
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            for stmt in node.body:
                if isinstance(stmt, ast.ImportFrom) and stmt.module is not None:
                    exports.setdefault(stmt.module, []).extend(a.asname or a.name for a in stmt.names)
    return exports


def lazy_face(
    package: str, exports: Mapping[str, Sequence[str]] | None = None
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module ``__getattr__`` and ``__dir__`` of a face; ``exports``: module → the names it
    gives (default: the face's imports under ``if TYPE_CHECKING:``)."""
    face = sys.modules[package]
    if exports is None:
        with open(face.__file__ or "", encoding="utf-8") as fh:
            exports = type_checking_imports(fh.read())
    where = {name: module for module, names in exports.items() for name in names}
    submodules = {m.name for m in pkgutil.iter_modules(face.__path__)}

    def get_attribute(name: str) -> Any:
        module = where.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        if module == package:  # the face gives one of its submodules
            value = importlib.import_module(f"{package}.{name}")
        else:
            value = getattr(importlib.import_module(module), name)
        setattr(face, name, value)  # later look-ups skip this function
        return value

    def list_names() -> list[str]:
        return sorted(set(vars(face)) | set(where))

    for name in sorted(submodules & set(where)):
        if where[name] != package:
            get_attribute(name)
    return get_attribute, list_names
