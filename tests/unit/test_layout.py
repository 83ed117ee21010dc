"""The rooms of ``services/`` hold: the kernel imports no application, the SDK only the kernel.

Imports are read with :mod:`ast` by :mod:`test_import_graph` (nothing is imported): module-level,
function-level and ``if TYPE_CHECKING:`` imports alike, since a type from another room is still a
dependency on it.
"""

from __future__ import annotations

from collections.abc import Iterable

from test_import_graph import ROOT, Import, project_imports

#: The contract is below the kernel: the model's codec translates to and from its messages.
CONTRACT = "protos"


def _in(module: str, room: str) -> bool:
    return module == room or module.startswith(room + ".")


def _wrong(imports: Iterable[Import], source_room: str, allowed: tuple[str, ...]) -> list[str]:
    return [
        f"{imp.source} imports {imp.target} (line {imp.line})"
        for imp in imports
        if _in(imp.source, source_room) and not any(_in(imp.target, room) for room in allowed)
    ]


def test_the_kernel_imports_only_itself_and_the_contract() -> None:
    wrong = _wrong(project_imports(), "services.kernel", ("services.kernel", CONTRACT))
    assert not wrong, "the kernel imports only the kernel and protos:\n" + "\n".join(wrong)


def test_applications_build_on_the_kernel_not_on_the_device_side_or_the_gateway() -> None:
    wrong = _wrong(project_imports(), "services.apps", ("services.kernel", "services.apps", CONTRACT))
    assert not wrong, "an application imports the kernel, applications and protos only:\n" + "\n".join(wrong)


def test_the_sdk_imports_the_kernel_and_no_application() -> None:
    wrong = [
        f"{imp.source} imports {imp.target} (line {imp.line})"
        for imp in project_imports()
        if _in(imp.source, "clients")
        and (_in(imp.target, "services.apps") or _in(imp.target, "services.device"))
    ]
    assert not wrong, "clients imports no application and no device code:\n" + "\n".join(wrong)


def test_services_holds_only_its_three_rooms() -> None:
    # A new module goes into the kernel, the applications or the device side, never beside them.
    services = ROOT / "services"
    loose = sorted(
        p.name
        for p in services.iterdir()
        if (p.suffix == ".py" and p.name != "__init__.py")
        or (p.is_dir() and p.name not in {"kernel", "apps", "device", "__pycache__"})
    )
    assert not loose, f"services/ holds {', '.join(loose)} outside kernel/, apps/ and device/"
