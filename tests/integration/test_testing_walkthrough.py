"""docs/testing.md's "Serving your class from a gateway process", as a reader runs it.

The page's ``lamp.py`` (the class of its ``test_lamp.py``) and ``site.toml`` go into a folder; the
installed ``psgateway`` script serves them from there with ``PYTHONPATH=.`` (and this checkout on
the path after it), and the session's ``psctl`` lines must print what the page shows, on a busy
machine (tests/support/cpu_burner.py). Without ``PYTHONPATH=.`` the gateway must refuse to start
with the page's words: the installed script, unlike ``python -m``, does not import from the folder
it runs in.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest
from support.cpu_burner import cpu_burners, spinning
from support.gateway_process import ROOT, GatewayProcess
from support.walkthrough import console_steps, fenced_block, run_in_one_shell

PAGE = Path(ROOT, "docs", "testing.md").read_text(encoding="utf-8")
#: The page's gateway listens on its fixed ports; a test's on free ones.
FREE_PORTS = ("--listen", "127.0.0.1:0", "--http", "127.0.0.1:0")
SECTION = PAGE.split("## Serving your class from a gateway process", 1)[1]


def block(marker: str, language: str = "console") -> str:
    return fenced_block(SECTION, f"<!-- walkthrough: {marker} -->", language)


@pytest.fixture
def reader_folder(tmp_path: Path) -> Path:
    """lamp.py (the page's class, without its tests) and the page's site.toml."""
    test_lamp = fenced_block(PAGE, "## A test of your own class", "python")
    (tmp_path / "lamp.py").write_text(test_lamp.split("\nasync def test_", 1)[0], encoding="utf-8")
    (tmp_path / "site.toml").write_text(block("site.toml", "toml"), encoding="utf-8")
    return tmp_path


def psgateway_script() -> str:
    script = shutil.which("psgateway")
    if script is None:
        pytest.skip("the psgateway script is not installed here (pip install -e .)")
    return script


@pytest.mark.timeout(180)
def test_a_class_beside_the_config_is_served_with_pythonpath_dot(reader_folder: Path) -> None:
    steps = console_steps(block("session"))
    serve, *session = steps
    assert serve[0] == "PYTHONPATH=. psgateway serve --config site.toml &"
    gw = GatewayProcess(
        [psgateway_script(), "serve", "--config", "site.toml", *FREE_PORTS],
        {"PYTHONPATH": os.pathsep.join([".", str(ROOT)])},
        cwd=reader_folder,
    )
    try:
        gw.wait_ready()
        with cpu_burners() as burners:
            ran = run_in_one_shell([command for command, _ in session], reader_folder, gw.address)
            assert all(spinning(pid) for pid in burners), "the machine was busy until the session ended"
        for (command, expected), step in zip(session, ran, strict=True):
            assert step.status == 0, f"$ {command}: {step.output}"
            assert step.output == expected, f"$ {command}"
    finally:
        gw.stop()


@pytest.mark.timeout(120)
def test_without_pythonpath_dot_the_gateway_says_it_cannot_import_the_class(reader_folder: Path) -> None:
    [(command, expected)] = console_steps(block("without"))
    assert command == "psgateway serve --config site.toml"
    done = subprocess.run(
        [psgateway_script(), "serve", "--config", "site.toml", *FREE_PORTS],
        cwd=reader_folder,
        env={**os.environ, "PYTHONPATH": str(ROOT)},  # this checkout's gateway, and nothing of the reader's
        capture_output=True,
        text=True,
        timeout=90,
        check=False,
    )
    assert done.returncode == 2, done.stdout + done.stderr
    printed = (done.stdout + done.stderr).splitlines()
    for line in expected:
        if line.startswith("... "):  # a log line, its time left out
            assert any(re.fullmatch(r"\S+ \S+ " + re.escape(line[4:]), said) for said in printed), line
        else:
            assert line in printed, printed
