"""The README's first steps, in the order it gives them, on a fresh demo gateway."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

from support.gateway_process import ROOT, StartGateway
from support.psctl import psctl

README = Path(ROOT, "README.md").read_text(encoding="utf-8")
#: Seconds one walkthrough command may take; a listen that waits for a change would exceed it.
COMMAND_LIMIT = 30.0


def walkthrough_commands() -> list[list[str]]:
    """The psctl lines of the README's CLI block, comments dropped, in order."""
    block = README.split("The same with the project's CLI", 1)[1].split("```bash", 1)[1].split("```", 1)[0]
    lines = [re.sub(r"\s+#.*$", "", line).strip() for line in block.splitlines()]
    return [shlex.split(line)[1:] for line in lines if line.startswith("psctl ")]


def test_the_cli_walkthrough_works_in_its_order(gateway_process: StartGateway) -> None:
    target = gateway_process().address
    commands = walkthrough_commands()
    assert any(args[0] == "listen" for args in commands) and len(commands) >= 5
    for args in commands:
        done = psctl(target, *args, timeout=COMMAND_LIMIT)
        assert done.returncode == 0, f"psctl {shlex.join(args)}: {done.stderr}"
        if args[0] != "set":  # a moveto answers nothing
            assert done.stdout.strip(), f"psctl {shlex.join(args)} printed nothing"
    # Run again, now that scout1 has arrived: the listen still ends by itself.
    listen = next(args for args in commands if args[0] == "listen")
    again = psctl(target, *listen, timeout=COMMAND_LIMIT)
    assert again.returncode == 0, again.stderr


def test_bench_help_needs_no_test_extra() -> None:
    # After `pip install -e .` (no test extra) psutil may be missing: --help must not need it.
    hide_psutil = (
        "import runpy, sys; sys.modules['psutil'] = None; sys.argv = ['bench', '--help']; "
        "runpy.run_module('bench', run_name='__main__', alter_sys=True)"
    )
    done = subprocess.run(
        [sys.executable, "-c", hide_psutil], cwd=ROOT, capture_output=True, text=True, timeout=60, check=False
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: python -m bench")


def test_vector_and_marker_import_where_the_docs_say() -> None:
    from services.kernel.core import Marker, Vector
    from services.kernel.values import Marker as ValueMarker
    from services.kernel.values import Vector as ValueVector

    assert (Vector, Marker) == (ValueVector, ValueMarker)
    docs = "\n".join(p.read_text(encoding="utf-8") for p in Path(ROOT, "docs").glob("*.md")) + README
    imports = set(re.findall(r"from ([\w.]+) import [^`\n]*\bVector\b", docs))
    assert imports, "the docs say where Vector comes from"
    for module in imports:
        done = subprocess.run(
            [sys.executable, "-c", f"from {module} import Vector"],
            cwd=ROOT,
            capture_output=True,
            timeout=60,
            check=False,
        )
        assert done.returncode == 0, (module, done.stderr)
