"""The scenario session of docs/scheduler.md runs as written against a real gateway process.

The page's ``site.toml`` block is the config; its console block is run line by line in one bash
shell in the config's folder, ``psctl`` and ``python`` being this checkout's (the gateway itself is
started by the test from that config where the session says ``psgateway serve``). Each command's
output must be what the page shows, licence ids and times aside (they differ from run to run);
a command shown with ``error:`` must fail, every other one succeed. It runs on a busy machine (one
spinning process per core, tests/support/cpu_burner.py) at a reader's pace, where each ``psctl``
call takes a second or two: the page's output must not depend on the pace.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from support.cpu_burner import cpu_burners, spinning
from support.gateway_process import ROOT, StartGateway
from support.walkthrough import console_steps, fenced_block, normalised, run_in_one_shell

PAGE = ROOT / "docs" / "scheduler.md"
#: What differs between runs: licence ids and ISO 8601 times.
VARYING = (
    (re.compile(r"\bL\d+-[0-9a-f]{6}\b"), "LICENCE"),
    (re.compile(r"\d{4}-\d\d-\d\dT[\d:.]+Z"), "TIME"),
)


def block_after(text: str, marker: str) -> str:
    """The fenced block that follows ``<!-- walkthrough: MARKER -->``."""
    found = re.search(rf"<!-- walkthrough: {re.escape(marker)} -->\n```\w+\n(.*?)```", text, re.S)
    assert found is not None, f"docs/scheduler.md has no walkthrough block {marker!r}"
    return found.group(1)


@pytest.mark.timeout(300)
def test_the_scenario_session_of_the_page_runs_as_written_on_a_busy_machine(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    page = PAGE.read_text()
    config = block_after(page, "site.toml")
    steps = console_steps(block_after(page, "session"))
    assert any("request" in command for command, _ in steps)
    shown: list[tuple[str, list[str]]] = []
    target = ""
    for command, output in steps:
        if command.startswith("psgateway serve"):
            # Everything before it runs first (the secret file is then there); the test starts the gateway.
            before = "\n".join(c for c, _ in shown)
            subprocess.run(["bash", "-c", before], cwd=tmp_path, check=True, timeout=60)
            target = gateway_process(config).address
            continue
        shown.append((command, output))
    assert target, "the session starts the gateway"
    with cpu_burners() as burners:
        ran = run_in_one_shell([command for command, _ in shown], tmp_path, target)
        assert all(spinning(pid) for pid in burners), "the machine was busy until the session ended"
    for (command, expected), step in zip(shown, ran, strict=True):
        assert normalised(step.output, VARYING) == normalised(expected, VARYING), f"$ {command}"
        failing = bool(expected) and expected[0].startswith("error:")
        assert (step.status != 0) == failing, f"$ {command}: exit code {step.status}"


def test_the_readmes_excerpt_is_the_sessions_own_steps_in_its_order() -> None:
    # The README shows four steps of this session: they are run (above) as part of it.
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    excerpt = console_steps(fenced_block(readme, "asks for two surveyors", "console"))
    steps = console_steps(block_after(PAGE.read_text(), "session"))
    assert len(excerpt) == 4
    positions = [steps.index(step) for step in excerpt]
    assert positions == sorted(positions), "in the session's order"
