"""Unit tests run in this one process: a test that starts another one belongs in tests/integration/.

Every unit test runs with process starts refused (``subprocess.Popen``, which ``subprocess.run`` and
asyncio's subprocesses go through, ``os.fork`` and ``os.posix_spawn``): a compiler, node, a gateway
process or valgrind fails the test at once, naming the room it belongs in, instead of making the
unit tests slow. The refusal is :func:`pytest.fail`, which no ``except Exception`` swallows.
"""

from __future__ import annotations

import os
import subprocess
from typing import Any, NoReturn

import pytest


def _refuse(*args: Any, **kwargs: Any) -> NoReturn:
    pytest.fail(
        "a unit test started a process: unit tests run in-process in milliseconds; "
        "move this one to tests/integration/ (marked slow)"
    )


@pytest.fixture(autouse=True)
def no_processes(monkeypatch: pytest.MonkeyPatch) -> None:
    """Refuse every process start for the length of a unit test."""
    monkeypatch.setattr(subprocess.Popen, "__init__", _refuse)
    monkeypatch.setattr(os, "fork", _refuse)
    monkeypatch.setattr(os, "posix_spawn", _refuse)
