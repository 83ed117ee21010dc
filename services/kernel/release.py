"""What ``--version`` reports: the release of this code and the contract it speaks.

The release is the installed distribution's version; a source tree run without installing it (a
checkout on ``PYTHONPATH``) reads its own ``pyproject.toml`` instead. The contract is the package
of the generated protobuf code, so it cannot drift from what the wire actually carries.
"""

from __future__ import annotations

import importlib.metadata
import tomllib
from pathlib import Path

from protos.propertyservice.v1 import property_service_pb2

__all__ = ["CONTRACT", "DISTRIBUTION", "package_version", "version_line"]

#: The distribution this code ships in (pyproject.toml's ``[project] name``).
DISTRIBUTION = "propertyservice-gateway"
#: The protobuf package of the contract, e.g. ``propertyservice.v1``.
CONTRACT: str = property_service_pb2.DESCRIPTOR.package

_SOURCE_PYPROJECT = Path(__file__).resolve().parents[2] / "pyproject.toml"


def package_version() -> str:
    """The installed release; else the source tree's ``pyproject.toml`` version; else ``unknown``."""
    try:
        return importlib.metadata.version(DISTRIBUTION)
    except importlib.metadata.PackageNotFoundError:
        pass
    try:
        project = tomllib.loads(_SOURCE_PYPROJECT.read_text(encoding="utf-8")).get("project", {})
    except (OSError, tomllib.TOMLDecodeError):
        return "unknown"
    version = project.get("version") if project.get("name") == DISTRIBUTION else None
    return version if isinstance(version, str) else "unknown"


def version_line(program: str) -> str:
    """``psctl 0.1.0 (propertyservice-gateway; contract propertyservice.v1)``."""
    return f"{program} {package_version()} ({DISTRIBUTION}; contract {CONTRACT})"
