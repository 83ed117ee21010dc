"""docs/environment.md's demo session, on a fresh demo gateway and a busy machine.

Each line runs in one bash shell at a reader's pace, beside one spinning process per core
(tests/support/cpu_burner.py). What the page shows must come out, numbers aside where they are
measurements (temperatures, the filter's estimate, counts, times): the sources, the swarm's
members, the markers once the swarm is there, the nearest robot, the cone, the media type, and
the two files the last lines write. The session waits for the swarm to get where it was sent
(``sleep 10``) before it reads the markers: right after the Set the robots are still on their way,
and the nearest to (3 2) is another one.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy
import pytest
from PIL import Image
from support.cpu_burner import cpu_burners, spinning
from support.gateway_process import ROOT, GatewayProcess
from support.walkthrough import console_steps, fenced_block, normalised, run_in_one_shell

PAGE = Path(ROOT, "docs", "environment.md").read_text(encoding="utf-8")
#: Measurements: every number but the grid's own (origin, cell, shape) and the ids' digits.
MEASURED = ((re.compile(r"(?<![\w.])-?\d+(\.\d+)?(?![\w.])"), "N"),)


def comparable(lines: list[str]) -> list[str]:
    """``lines`` with measurements left out, and the ``markers`` ids in name order: the list is
    least recently seen first, which changes as the robots and the camera report."""
    out = []
    for line in normalised(lines, MEASURED):
        if m := re.fullmatch(r"markers = \((.*)\)", line):
            line = f"markers = ({' '.join(sorted(m.group(1).split()))})"  # noqa: PLW2901 - the same line, in order
        out.append(line)
    return out


@pytest.mark.timeout(240)
def test_the_demo_session_shows_what_the_page_says_on_a_busy_machine(
    fresh_demo_gateway: GatewayProcess, tmp_path: Path
) -> None:
    target = fresh_demo_gateway.address
    steps = console_steps(fenced_block(PAGE, "## In the demo", "console"))
    commands = [re.sub(r"\s+#.*$", "", command) for command, _ in steps]
    with cpu_burners() as burners:
        ran = run_in_one_shell(commands, tmp_path, target)
        assert all(spinning(pid) for pid in burners), "the machine was busy until the session ended"
    for (command, expected), step in zip(steps, ran, strict=True):
        assert step.status == 0, f"$ {command}: {step.output}"
        assert comparable(step.output) == comparable(expected), f"$ {command}"
    shape = numpy.load(tmp_path / "t.npy").shape
    assert shape == (40, 40)
    with Image.open(io.BytesIO((tmp_path / "heat.png").read_bytes())) as heat:
        assert (heat.size, heat.mode) == ((320, 320), "RGBA")
