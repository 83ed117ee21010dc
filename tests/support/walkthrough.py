"""A doc page's commands, run as a reader runs them: one bash shell, one command line at a time.

A walkthrough test picks a fenced block out of a page (:func:`fenced_block`), runs its lines with
:func:`run_in_one_shell` — ``psctl`` and ``python`` being this checkout's, ``PSCTL_TARGET`` the
test's gateway — and compares what each line printed with what the page says. Run it inside
``cpu_burners()`` (tests/support/cpu_burner.py): each ``psctl`` then takes a second or two,
and :data:`READER_PAUSE` before each line gives the session a person's pace, not a script's.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

from support.gateway_process import ROOT, GatewayProcess

#: Seconds before each command line: a reader types or pastes each one.
READER_PAUSE = 1.0
#: Lines the script prints around each command line's output.
_BEGIN, _END = "@@walkthrough-begin", "@@walkthrough-rc"


@dataclass(frozen=True)
class Step:
    """One command line as the shell ran it: what it printed (stdout and stderr, blank lines
    dropped) and its exit status."""

    command: str
    output: list[str]
    status: int


def fenced_block(text: str, after: str, language: str = "bash") -> str:
    """The first ```LANGUAGE block of ``text`` after the first occurrence of ``after``."""
    assert after in text, f"the page has no {after!r}"
    rest = text.split(after, 1)[1]
    assert f"```{language}\n" in rest, f"no ```{language} block after {after!r}"
    return rest.split(f"```{language}\n", 1)[1].split("```", 1)[0]


def command_lines(block: str) -> list[str]:
    """The lines of a shell block, ``# comments`` (whole lines or trailing) and blank lines dropped."""
    lines = (re.sub(r"(^|\s+)#.*$", "", line).strip() for line in block.splitlines())
    return [line for line in lines if line]


def run_in_one_shell(
    commands: list[str],
    cwd: Path,
    target: str = "",
    *,
    timeout: float = 240.0,
    pause: float = READER_PAUSE,
) -> list[Step]:
    """Run ``commands`` in one bash shell in ``cwd``, ``pause`` seconds before each; each one's output.

    ``psctl`` is this checkout's CLI and talks to ``target`` (``PSCTL_TARGET``) unless a command says
    otherwise, ``grpcurl`` the one on this process's PATH."""
    script = [
        f'psctl() {{ "{sys.executable}" -m clients.cli "$@"; }}',
        f'python() {{ "{sys.executable}" "$@"; }}',
    ]
    grpcurl = shutil.which("grpcurl")
    if grpcurl:
        script.append(f'grpcurl() {{ "{grpcurl}" "$@"; }}')
    if target:
        script.append(f"export PSCTL_TARGET={target}")
    for i, command in enumerate(commands):
        script += [f"sleep {pause}", f"echo '{_BEGIN} {i}'", f"{command} 2>&1", f"echo '{_END}' $?"]
    done = subprocess.run(
        ["bash", "-c", "\n".join(script)],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "HOME": str(cwd)},
        check=False,
    )
    assert done.returncode == 0, done.stderr
    found = {
        int(m.group(1)): ([line for line in m.group(2).splitlines() if line], int(m.group(3)))
        for m in re.finditer(rf"^{_BEGIN} (\d+)\n(.*?)^{_END} (\d+)$", done.stdout, re.S | re.M)
    }
    assert sorted(found) == list(range(len(commands))), done.stdout
    return [Step(command, *found[i]) for i, command in enumerate(commands)]


def console_steps(block: str) -> list[tuple[str, list[str]]]:
    """(command, the lines shown after it) of a ```console block: ``$ `` starts a command."""
    steps: list[tuple[str, list[str]]] = []
    for line in block.splitlines():
        if line.startswith("$ "):
            steps.append((line[2:], []))
        elif line and steps:
            steps[-1][1].append(line)
    return steps


def normalised(lines: list[str], varying: tuple[tuple[re.Pattern[str], str], ...]) -> list[str]:
    """``lines`` with what differs from run to run (each pattern) replaced by its placeholder."""
    out = []
    for line in lines:
        for pattern, placeholder in varying:
            line = pattern.sub(placeholder, line)  # noqa: PLW2901 - the same line, normalised
        out.append(line)
    return out


@contextmanager
def demo_gateway_in(folder: Path) -> Iterator[GatewayProcess]:
    """The demo gateway, ready, running in ``folder`` (its ``files`` keep ``folder/.demo-files``, as
    they would in a reader's folder), on free ports; stopped when the block ends."""
    gw = GatewayProcess(
        [sys.executable, "-m", "gateway.cli", "serve", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0"],
        {"PYTHONPATH": str(ROOT)},
        cwd=folder,
    )
    try:
        gw.wait_ready()
        yield gw
    finally:
        gw.stop()


@pytest.fixture
def fresh_demo_gateway(tmp_path: Path) -> Iterator[GatewayProcess]:
    """:func:`demo_gateway_in` the test's own folder: a reader's fresh demo, with nothing another
    test stored in its ``files`` (a chart Set there is loaded again at the next start)."""
    with demo_gateway_in(tmp_path) as gw:
        yield gw


def commented_steps(block: str) -> list[tuple[str, list[str]]]:
    """(command, the lines shown after it) of a shell block that shows each command's output as
    ``# `` comments below it; a line that ends in a backslash goes on in the next one, and a
    comment at the end of a command line is dropped."""
    steps: list[tuple[str, list[str]]] = []
    going_on = ""
    for line in block.splitlines():
        if line.startswith("#") and not going_on:
            if steps:
                steps[-1][1].append(line.removeprefix("#").removeprefix(" "))
            continue
        command = going_on + re.sub(r"\s+#.*$", "", line).strip()
        if command.endswith("\\"):
            going_on = command.removesuffix("\\")
        elif command:
            going_on = ""
            steps.append((command, []))
    return steps
