"""The client SDK loads without numpy and defusedxml: only a parsed vector or marker needs them.

Checked in a fresh interpreter, since this test's own process has long loaded both.
"""

from __future__ import annotations

import subprocess
import sys

import pytest
from support.gateway_process import ROOT

pytestmark = pytest.mark.slow

HEAVY = ("numpy", "defusedxml")

IMPORT_THE_SDK = f"""
import runpy, sys
import clients, clients.aio, clients.sync, clients.values, clients.cli
sys.argv = ["psctl", "--help"]
try:
    runpy.run_module("clients.cli", run_name="__main__")
except SystemExit as done:
    assert done.code == 0, done.code
print("loaded after import:", *[m for m in {HEAVY!r} if m in sys.modules])
clients.values.parse_vector("(1 2)")
clients.values.parse_marker("<marker><name>a</name></marker>")
assert clients.Vector is clients.values.Vector
print("loaded after parsing:", *[m for m in {HEAVY!r} if m in sys.modules])
"""


def test_importing_the_sdk_and_its_cli_loads_neither_numpy_nor_defusedxml() -> None:
    done = subprocess.run(
        [sys.executable, "-c", IMPORT_THE_SDK],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith("usage: psctl"), done.stdout
    assert "loaded after import:" in lines
    # The same process then parses a vector and a marker: the parsers bring in what they need.
    assert "loaded after parsing: numpy defusedxml" in lines
