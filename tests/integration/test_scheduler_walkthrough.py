"""The scenario session of docs/scheduler.md runs as written against a real gateway process.

The page's ``site.toml`` block is the config; its console block is run line by line in one bash
shell in the config's folder, ``psctl`` and ``python`` being this checkout's (the gateway itself is
started by the test from that config where the session says ``psgateway serve``). Each command's
output must be what the page shows, licence ids and times aside (they differ from run to run);
a command shown with ``error:`` must fail, every other one succeed. It runs on a busy machine (one
spinning process per core, tests/support/cpu_burner.py), where each ``psctl`` call takes a second
or two, as on a reader's shared machine: the page's output must not depend on the pace.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from support.cpu_burner import spinning
from support.gateway_process import ROOT

PAGE = ROOT / "docs" / "scheduler.md"
#: What differs between runs: licence ids and ISO 8601 times.
VARYING = (
    (re.compile(r"\bL\d+-[0-9a-f]{6}\b"), "LICENCE"),
    (re.compile(r"\d{4}-\d\d-\d\dT[\d:.]+Z"), "TIME"),
)
#: Seconds between one command's end and the next one's start: a reader types each command, so the
#: session runs at a person's pace (with the busy machine's: about 2 s a command), not a script's.
READER_PAUSE = 1.0
#: Lines the script prints around each command's output.
BEGIN, END = "@@walkthrough-begin", "@@walkthrough-rc"


def block_after(text: str, marker: str) -> str:
    """The fenced block that follows ``<!-- walkthrough: MARKER -->``."""
    found = re.search(rf"<!-- walkthrough: {re.escape(marker)} -->\n```\w+\n(.*?)```", text, re.S)
    assert found is not None, f"docs/scheduler.md has no walkthrough block {marker!r}"
    return found.group(1)


def session(text: str) -> list[tuple[str, list[str]]]:
    """(command, the lines shown after it) of the console block."""
    steps: list[tuple[str, list[str]]] = []
    for line in text.splitlines():
        if line.startswith("$ "):
            steps.append((line[2:], []))
        elif line:
            steps[-1][1].append(line)
    return steps


def normalised(lines: list[str]) -> list[str]:
    out = []
    for line in lines:
        text = line
        for pattern, placeholder in VARYING:
            text = pattern.sub(placeholder, text)
        out.append(text)
    return out


@pytest.mark.timeout(300)
def test_the_scenario_session_of_the_page_runs_as_written_on_a_busy_machine(  # type: ignore[no-untyped-def]
    busy_machine: list[int], gateway_process, tmp_path: Path
) -> None:
    page = PAGE.read_text()
    config = block_after(page, "site.toml")
    steps = session(block_after(page, "session"))
    assert any("request" in command for command, _ in steps)
    script = [
        f'psctl() {{ "{sys.executable}" -m clients.cli "$@"; }}',
        f'python() {{ "{sys.executable}" "$@"; }}',
    ]
    shown: list[tuple[str, list[str]]] = []
    for command, output in steps:
        if command.startswith("psgateway serve"):
            # Everything before it ran already: the secret file is there. The test starts the gateway.
            prelude = "\n".join(script + [c for c, _ in shown])
            subprocess.run(["bash", "-c", prelude], cwd=tmp_path, check=True, timeout=60)
            gw = gateway_process(config)
            script.append(f"export PSCTL_TARGET={gw.address}")
            continue
        shown.append((command, output))
    lines = list(script)
    for i, (command, _) in enumerate(shown):
        lines += [f"sleep {READER_PAUSE}", f"echo '{BEGIN} {i}'", f"{command} 2>&1", f"echo '{END}' $?"]
    done = subprocess.run(
        ["bash", "-c", "\n".join(lines)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=240,
        env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT), "HOME": str(tmp_path)},
        check=False,
    )
    assert done.returncode == 0, done.stderr
    results = {
        int(m.group(1)): ([line for line in m.group(2).splitlines() if line], int(m.group(3)))
        for m in re.finditer(rf"^{BEGIN} (\d+)\n(.*?)^{END} (\d+)$", done.stdout, re.S | re.M)
    }
    assert sorted(results) == list(range(len(shown))), done.stdout
    for i, (command, expected) in enumerate(shown):
        output, rc = results[i]
        assert normalised(output) == normalised(expected), f"$ {command}"
        failing = bool(expected) and expected[0].startswith("error:")
        assert (rc != 0) == failing, f"$ {command}: exit code {rc}"
    assert all(spinning(pid) for pid in busy_machine), "the machine was busy until the session ended"
