"""Package faces: each listed package's ``__init__`` names its public API, one commented name a line.

A face is the package's ``__init__.py``: a docstring, explicit imports from its submodules and an
``__all__`` with one name per line, each with a short trailing comment saying what it is. These
tests hold that every listed name is importable, is commented, and that no submodule imports its own
package face (that would make an import cycle through the face).
"""

from __future__ import annotations

import ast
import importlib
import io
import tokenize
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "fluoronav"

#: the packages with a face (add a package here once its ``__init__`` is one)
FACES = (
    "fluoronav.geometry",
    "fluoronav.manipulator",
    "fluoronav.anatomy",
    "fluoronav.rendering",
    "fluoronav.calibration",
    "fluoronav.simulation",
    "fluoronav.detection",
    "fluoronav.registration",
    "fluoronav.registration.view_set",
    "fluoronav.navigation",
)


def _all_entries(source: str) -> list[tuple[str, str]]:
    """``(name, trailing comment)`` of each ``__all__`` entry of a module's source, in order.

    An entry sharing its line with another gets the comment ``""`` (one name a line), as does an
    entry without a comment.
    """
    tokens = list(tokenize.generate_tokens(io.StringIO(source).readline))
    start = next(
        (
            i
            for i, t in enumerate(tokens[:-2])
            if t.type == tokenize.NAME
            and t.string == "__all__"
            and tokens[i + 1].string == "="
            and tokens[i + 2].string == "["
        ),
        None,
    )
    if start is None:
        return []
    names: list[tuple[str, int]] = []
    comments: dict[int, str] = {}
    for t in tokens[start + 3 :]:
        if t.type == tokenize.OP and t.string == "]":
            break
        if t.type == tokenize.STRING:
            names.append((ast.literal_eval(t.string), t.start[0]))
        elif t.type == tokenize.COMMENT:
            comments[t.start[0]] = t.string.lstrip("#").strip()
    lines = [line for _, line in names]
    return [(name, comments.get(line, "") if lines.count(line) == 1 else "") for name, line in names]


def _face_source(package: str) -> str:
    return (SRC.parent / Path(*package.split(".")) / "__init__.py").read_text(encoding="utf-8")


def test_entry_parser_sees_missing_and_shared_comments() -> None:
    source = '__all__ = [\n    "A",  # the A\n    "b",\n    "c", "d",  # two on a line\n]\n'
    assert _all_entries(source) == [("A", "the A"), ("b", ""), ("c", ""), ("d", "")]
    assert _all_entries("x = 1\n") == []


@pytest.mark.parametrize("package", FACES)
def test_face_names_are_importable(package: str) -> None:
    module = importlib.import_module(package)
    names = list(module.__all__)
    assert names, f"{package} has an empty __all__"
    assert len(names) == len(set(names)), f"{package}.__all__ repeats a name"
    missing = [name for name in names if not hasattr(module, name)]
    assert missing == [], f"{package} lists names it does not import: {missing}"
    assert [name for name, _ in _all_entries(_face_source(package))] == names


@pytest.mark.parametrize("package", FACES)
def test_face_names_have_one_line_comments(package: str) -> None:
    source = _face_source(package)
    assert ast.get_docstring(ast.parse(source)), f"{package} has no docstring"
    uncommented = [name for name, comment in _all_entries(source) if not comment]
    assert uncommented == [], f"{package}.__all__: give each name its own line and a comment: {uncommented}"


@pytest.mark.parametrize("package", FACES)
def test_submodules_do_not_import_their_face(package: str) -> None:
    folder = SRC.parent / Path(*package.split("."))
    offenders = []
    for path in sorted(folder.glob("*.py")):
        if path.name == "__init__.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module == package:
                offenders.append(f"{path.name}:{node.lineno}")
            if isinstance(node, ast.Import) and any(alias.name == package for alias in node.names):
                offenders.append(f"{path.name}:{node.lineno}")
    assert offenders == [], f"submodules importing the {package} face: {offenders}"
