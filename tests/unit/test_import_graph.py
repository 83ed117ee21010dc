"""The project's modules import each other without circles, and the layers point one way.

Every module of ``protos``, ``gateway``, ``services`` and ``clients`` is
parsed with :mod:`ast` (nothing is imported), and its imports of project
modules become edges: module-level and function-level imports alike;
``from X import Y`` is an edge to ``X.Y`` when that is a module, to ``X``
otherwise; ``importlib.import_module("X")`` is an edge to ``X``. A package's
``__init__`` is the package's module, so its re-exports are edges too, and
importing ``a.b.c`` is an edge to the packages ``a`` and ``a.b`` as well
(Python runs their ``__init__`` first) unless the importing module is in them.
Imports under ``if TYPE_CHECKING:`` never run and make no circle; the
layering checks count them all the same, since a type from another layer is
still a dependency on it.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("protos", "gateway", "services", "clients")
#: The one module of the gateway allowed to import the SDK: the test kit hands out SDK clients.
TEST_KIT = "gateway.testing"


@dataclass(frozen=True)
class Import:
    """One import of a project module by another."""

    source: str
    target: str
    line: int
    typing_only: bool


def module_files() -> dict[str, Path]:
    """Every project module by its dotted name."""
    found: dict[str, Path] = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join(parts)] = path
    return found


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _import_module_call(node: ast.AST) -> str | None:
    """The module named by ``importlib.import_module("literal")``: an import all the same."""
    if not (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)):
        return None
    func = node.func
    called = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
    value = node.args[0].value
    return value if called == "import_module" and isinstance(value, str) else None


def _imported_names(tree: ast.AST, typing_only: bool = False) -> Iterator[tuple[ast.stmt | ast.expr, bool]]:
    """Every import under ``tree``, anywhere, and whether it sits under ``if TYPE_CHECKING``."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, ast.Import | ast.ImportFrom):
            yield node, typing_only
        elif _import_module_call(node) is not None:
            assert isinstance(node, ast.expr)
            yield node, typing_only
        elif isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.body:
                yield from _imported_names(ast.Module(body=[child], type_ignores=[]), True)
            for child in node.orelse:
                yield from _imported_names(ast.Module(body=[child], type_ignores=[]), typing_only)
        else:
            yield from _imported_names(node, typing_only)


def imports_of(name: str, path: Path, modules: set[str]) -> list[Import]:
    """The imports of project modules that module ``name`` (at ``path``) makes."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: list[Import] = []

    own_packages = {".".join(name.split(".")[:end]) for end in range(1, name.count(".") + 1)}

    def add(target: str | None, node: ast.stmt | ast.expr, typing_only: bool) -> None:
        if target is None:
            return
        # Importing a.b.c runs a/__init__ and a/b/__init__ first; the packages this module is in
        # are already being imported, so only the others are edges.
        parts = target.split(".")
        for end in range(1, len(parts) + 1):
            reached = ".".join(parts[:end])
            if reached in modules and reached != name and reached not in own_packages:
                found.append(Import(name, reached, node.lineno, typing_only))

    for node, typing_only in _imported_names(tree):
        called = _import_module_call(node)
        if called is not None:
            add(_known_prefix(called, modules), node, typing_only)
            continue
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(_known_prefix(alias.name, modules), node, typing_only)
            continue
        assert isinstance(node, ast.ImportFrom)
        if node.level:
            base = package.split(".")
            base = base[: len(base) - (node.level - 1)]
            origin = ".".join([*base, node.module] if node.module else base)
        else:
            origin = node.module or ""
        for alias in node.names:
            submodule = f"{origin}.{alias.name}"
            add(submodule if submodule in modules else _known_prefix(origin, modules), node, typing_only)
    return found


def _known_prefix(dotted: str, modules: set[str]) -> str | None:
    """``dotted`` or its longest prefix that is a project module; None for other packages."""
    parts = dotted.split(".")
    for end in range(len(parts), 0, -1):
        candidate = ".".join(parts[:end])
        if candidate in modules:
            return candidate
    return None


@cache
def project_imports() -> tuple[Import, ...]:
    """Every import of a project module by another; parsed once for all the tests here."""
    files = module_files()
    names = set(files)
    return tuple(imp for name, path in files.items() for imp in imports_of(name, path, names))


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for succ in sorted(edges.get(node, ())):
            if succ not in index:
                visit(succ)
                low[node] = min(low[node], low[succ])
            elif succ in on_stack:
                low[node] = min(low[node], index[succ])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(edges):
        if node not in index:
            visit(node)
    return sorted(found)


def a_circle_through(start: str, members: set[str], edges: dict[str, set[str]]) -> list[str]:
    """The shortest path from ``start`` back to itself inside one component, for the message."""
    paths = {succ: [start, succ] for succ in sorted(edges.get(start, ())) if succ in members}
    queue = list(paths)
    while queue:
        node = queue.pop(0)
        if node == start:
            return paths[node]
        for succ in sorted(edges.get(node, ())):
            if succ in members and succ not in paths:
                paths[succ] = [*paths[node], succ]
                queue.append(succ)
    return [start]


def runtime_edges(imports: tuple[Import, ...]) -> dict[str, set[str]]:
    edges: dict[str, set[str]] = {}
    for imp in imports:
        if not imp.typing_only:
            edges.setdefault(imp.source, set()).add(imp.target)
    return edges


def test_the_parser_sees_every_kind_of_import(tmp_path: Path) -> None:
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from pkg.a import thing\n")
    (pkg / "a.py").write_text(
        "from typing import TYPE_CHECKING\n"
        "import os\n"
        "from . import b\n"
        "from .sub import name_in_init\n"
        "if TYPE_CHECKING:\n"
        "    from pkg.c import Only\n"
        "else:\n"
        "    import pkg.d\n"
        "def f():\n"
        "    from pkg.sub.e import late\n"
        "    importlib.import_module('pkg.f')\n"
    )
    for leaf in ("b.py", "c.py", "d.py", "f.py", "sub/__init__.py", "sub/e.py"):
        (pkg / leaf).write_text("")
    modules = {"pkg", "pkg.a", "pkg.b", "pkg.c", "pkg.d", "pkg.f", "pkg.sub", "pkg.sub.e"}
    found = {(i.target, i.typing_only) for i in imports_of("pkg.a", pkg / "a.py", modules)}
    assert found == {
        ("pkg.b", False),
        ("pkg.sub", False),
        ("pkg.c", True),
        ("pkg.d", False),
        ("pkg.sub.e", False),
        ("pkg.f", False),
    }
    assert [i.target for i in imports_of("pkg", pkg / "__init__.py", modules)] == ["pkg.a"]
    assert cycles({"x": {"y"}, "y": {"z", "x"}, "z": set(), "w": {"w"}}) == [["x", "y"]]


def test_there_is_no_import_circle() -> None:
    edges = runtime_edges(project_imports())
    found = cycles(edges)
    described = [
        f"{', '.join(members)} (e.g. {' -> '.join(a_circle_through(members[0], set(members), edges))})"
        for members in found
    ]
    assert not found, "modules that import each other in a circle:\n" + "\n".join(described)


@pytest.mark.parametrize(
    ("layer", "forbidden"),
    [
        ("services", ("gateway", "clients")),
        ("clients", ("gateway",)),
        ("protos", ("gateway", "services", "clients")),
    ],
)
def test_layers_import_downwards_only(layer: str, forbidden: tuple[str, ...]) -> None:
    wrong = [
        f"{imp.source} imports {imp.target} (line {imp.line})"
        for imp in project_imports()
        if imp.source.split(".")[0] == layer
        and any(imp.target == f or imp.target.startswith(f + ".") for f in forbidden)
    ]
    assert not wrong, f"{layer} must not import {', '.join(forbidden)}:\n" + "\n".join(wrong)


def test_only_the_test_kit_of_the_gateway_imports_the_sdk() -> None:
    wrong = [
        f"{imp.source} imports {imp.target} (line {imp.line})"
        for imp in project_imports()
        if imp.source.startswith("gateway")
        and imp.target.split(".")[0] == "clients"
        and imp.source != TEST_KIT
    ]
    assert not wrong, f"only {TEST_KIT} may import clients:\n" + "\n".join(wrong)
