"""The gateway's folders say what depends on what: the engine knows no front, the fronts know no
other front.

``gateway/engine/`` is the protocol-neutral heart (plain types, router, guard, licences, calls,
the listen hub); ``gateway/fronts/`` holds one folder per wire protocol (``grpc_v1``, ``http``,
``line``, ``foxglove``, ``rosbridge``), each translating its wire into the engine's types; a plain
module directly in ``gateway/fronts/`` (``websocket.py``) is no front but what several fronts share,
and imports no front itself. The imports are read with
:mod:`ast` by the same reader as ``test_import_graph`` (nothing is imported; imports under
``if TYPE_CHECKING`` count, since a type from another layer is still a dependency on it).
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from tests.unit.test_import_graph import Import, project_imports

ENGINE = "gateway.engine"
FRONTS = "gateway.fronts"
#: The fronts there are; a new one is a new folder here and in docs/architecture.md.
FRONT_NAMES = ("foxglove", "grpc_v1", "http", "line", "rosbridge")
#: What stands above the engine: the assembly, the command line and its entry point.
ABOVE_THE_ENGINE = ("gateway.app", "gateway.cli", "gateway.__main__", "gateway.testing")
CONFIG = "gateway.config"
#: Engine modules that still take a type of the configuration (``Limits``, ``Config``) as an
#: argument's type. The engine's limits belong to the engine, with config building them; until
#: then the list may only shrink (a module that no longer needs config must leave it).
STILL_TAKE_CONFIG_TYPES = {
    "gateway.engine.guard",
    "gateway.engine.listen.hub",
    "gateway.engine.listen.requests",
    "gateway.engine.listen.stream",
}


def _within(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def _front_of(module: str) -> str | None:
    parts = module.split(".")
    return parts[2] if _within(module, FRONTS) and len(parts) > 2 and parts[2] in FRONT_NAMES else None


def _shared_by_fronts(module: str) -> bool:
    parts = module.split(".")
    return _within(module, FRONTS) and len(parts) == 3 and parts[2] not in FRONT_NAMES


def _imports_by_source() -> dict[str, list[Import]]:
    found: dict[str, list[Import]] = defaultdict(list)
    for imp in project_imports():
        found[imp.source].append(imp)
    return found


def _where(imp: Import) -> str:
    return f"{imp.source}:{imp.line} imports {imp.target}"


def test_the_engine_imports_no_front() -> None:
    wrong = [
        _where(imp)
        for imp in project_imports()
        if _within(imp.source, ENGINE) and _within(imp.target, FRONTS)
    ]
    assert wrong == []


def test_the_engine_imports_neither_the_assembly_nor_the_command_line() -> None:
    wrong = [
        _where(imp)
        for imp in project_imports()
        if _within(imp.source, ENGINE) and any(_within(imp.target, above) for above in ABOVE_THE_ENGINE)
    ]
    assert wrong == []


def test_the_engine_takes_no_more_from_the_configuration_than_it_did() -> None:
    taking = {imp.source for imp in project_imports() if _within(imp.source, ENGINE) and imp.target == CONFIG}
    assert taking - STILL_TAKE_CONFIG_TYPES == set(), "a new engine module imports gateway.config"
    assert STILL_TAKE_CONFIG_TYPES - taking == set(), "no longer imports gateway.config: drop it"


def test_each_front_is_a_folder_that_calls_the_engine() -> None:
    by_source = _imports_by_source()
    for front in FRONT_NAMES:
        package = f"{FRONTS}.{front}"
        targets = {
            imp.target for source, imps in by_source.items() if _within(source, package) for imp in imps
        }
        assert any(_within(target, ENGINE) for target in targets), f"{package} does not call the engine"


def test_no_front_imports_another_front() -> None:
    wrong = [
        _where(imp)
        for imp in project_imports()
        if _front_of(imp.source) is not None
        and _front_of(imp.target) is not None
        and _front_of(imp.source) != _front_of(imp.target)
    ]
    assert wrong == []


def test_what_the_fronts_share_imports_no_front() -> None:
    wrong = [
        _where(imp)
        for imp in project_imports()
        if _shared_by_fronts(imp.source) and _front_of(imp.target) is not None
    ]
    assert wrong == []


def test_every_folder_of_the_fronts_is_a_front_named_here() -> None:
    folder = Path(__file__).resolve().parents[2] / "gateway" / "fronts"
    folders = {p.name for p in folder.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert folders == set(FRONT_NAMES)
