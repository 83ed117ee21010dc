"""What --version reports when the code runs from a source tree that was never installed."""

from __future__ import annotations

import importlib.metadata
import tomllib
from pathlib import Path

import pytest

from services.kernel import release

ROOT = Path(__file__).resolve().parents[2]


def _not_installed(name: str) -> str:
    raise importlib.metadata.PackageNotFoundError(name)


def test_a_source_tree_that_was_not_installed_reports_its_pyproject_version(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(importlib.metadata, "version", _not_installed)
    expected = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert release.package_version() == expected
    assert (
        release.version_line("psctl")
        == f"psctl {expected} (propertyservice-gateway; contract propertyservice.v1)"
    )


def test_without_an_installed_release_or_a_pyproject_the_version_is_unknown(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setattr(importlib.metadata, "version", _not_installed)
    monkeypatch.setattr(release, "_SOURCE_PYPROJECT", tmp_path / "pyproject.toml")
    assert release.package_version() == "unknown"
