"""The package's structure, held as tests: no import cycles, a small top, short functions and docstrings.

The layer contracts themselves are import-linter's (``lint-imports``, pyproject.toml); these tests
hold what a contract cannot say.
"""

from __future__ import annotations

import ast
from pathlib import Path

import grimp
import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "fluoronav"

#: the longest a function of ``src/`` may be, in lines (docstring included)
MAX_FUNCTION_LINES = 80
#: the longest a module docstring of ``src/`` may be, in lines (the theory goes to docs/)
MAX_MODULE_DOCSTRING_LINES = 12
#: the most modules the top of ``fluoronav.registration`` may hold (the methods are packages)
MAX_REGISTRATION_TOP_MODULES = 15


def _cycles(graph: grimp.ImportGraph) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    counter = 0
    for root in sorted(graph.modules):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.find_modules_directly_imported_by(child)))))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    comp = []
                    while True:
                        m = stack.pop()
                        on_stack.discard(m)
                        comp.append(m)
                        if m == node:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def test_cycle_finder_finds_a_cycle() -> None:
    graph = grimp.ImportGraph()
    for m in ("p.a", "p.b", "p.c"):
        graph.add_module(m)
    graph.add_import(importer="p.a", imported="p.b")
    graph.add_import(importer="p.b", imported="p.c")
    assert _cycles(graph) == []
    graph.add_import(importer="p.c", imported="p.a")
    assert _cycles(graph) == [["p.a", "p.b", "p.c"]]


def test_no_import_cycles() -> None:
    graph = grimp.build_graph("fluoronav")
    assert _cycles(graph) == []


def test_registration_top_level_is_small() -> None:
    modules = sorted(p.name for p in (SRC / "registration").glob("*.py"))
    assert len(modules) <= MAX_REGISTRATION_TOP_MODULES, modules
    for package in ("bone", "cm", "centerline"):
        assert (SRC / "registration" / package / "__init__.py").is_file()


def _long_functions() -> list[str]:
    out = []
    for path in sorted(SRC.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = (node.end_lineno or node.lineno) - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    out.append(f"{path.relative_to(SRC)}:{node.lineno} {node.name} ({n} lines)")
    return out


def test_no_function_is_too_long() -> None:
    assert _long_functions() == []


def _long_module_docstrings() -> list[str]:
    out = []
    for path in sorted(SRC.rglob("*.py")):
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")), clean=False)
        # lines counted with the closing quotes' line
        n_lines = doc.count("\n") + 1 if doc is not None else 0
        if n_lines > MAX_MODULE_DOCSTRING_LINES:
            out.append(f"{path.relative_to(SRC)} ({n_lines} lines)")
    return out


def test_module_docstrings_are_short() -> None:
    assert _long_module_docstrings() == []


@pytest.mark.parametrize("package", ["bone", "cm", "centerline"])
def test_method_packages_do_not_import_their_face(package: str) -> None:
    # a submodule importing its own package face would make a cycle through the face
    face = f"fluoronav.registration.{package}"
    for path in (SRC / "registration" / package).glob("*.py"):
        if path.name == "__init__.py":
            continue
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                assert node.module != face, f"{path.name} imports {face}"
