"""docs/vision.md's first session, on a fresh demo gateway and a busy machine.

Each command line runs in one bash shell at a reader's pace, beside one spinning process per core
(tests/support/cpu_burner.py), and prints what the page shows (``…`` on the page stands for the
rest of a marker, or of the list). The page's ``listen`` runs until Ctrl-C, so here it runs in the
background for a bounded time while the robot drives out of view, as a second shell would.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from support.cpu_burner import cpu_burners, spinning
from support.gateway_process import ROOT, GatewayProcess
from support.walkthrough import console_steps, fenced_block, run_in_one_shell

PAGE = Path(ROOT, "docs", "vision.md").read_text(encoding="utf-8")
#: Seconds the page's listen runs here (it would run until Ctrl-C): scout1 passes behind camera1
#: (at y = -4) about 9 s after the Set (4.5 m at about 0.5 m/s); three times that, for a busy machine.
LISTEN_S = 30


def shown(line: str) -> re.Pattern[str]:
    """The page's line as a pattern: ``…`` is anything."""
    return re.compile(".*".join(re.escape(part) for part in line.split("…")))


@pytest.mark.timeout(240)
def test_the_camera_session_shows_what_the_page_says_on_a_busy_machine(
    fresh_demo_gateway: GatewayProcess, tmp_path: Path
) -> None:
    target = fresh_demo_gateway.address
    steps = [
        (re.sub(r"\s+#.*$", "", command), output)
        for command, output in console_steps(fenced_block(PAGE, "With the demo running", "console"))
    ]
    *gets, (listen, _), (drive, _) = steps
    assert listen == "psctl listen camera1 markers" and drive.startswith("psctl set scout1 behaviors.moveto")
    commands = [command for command, _ in gets]
    commands.append(f"psctl listen camera1 markers --duration {LISTEN_S} & sleep 3; {drive}; wait")
    with cpu_burners() as burners:
        ran = run_in_one_shell(commands, tmp_path, target, timeout=200)
        assert all(spinning(pid) for pid in burners), "the machine was busy until the session ended"
    for (command, expected), step in zip(gets, ran, strict=False):
        assert step.status == 0, f"$ {command}: {step.output}"
        assert len(step.output) == len(expected), f"$ {command}: {step.output}"
        for line, said in zip(expected, step.output, strict=True):
            assert shown(line).fullmatch(said), f"$ {command}: {said!r} is not {line!r}"
    assert (tmp_path / "frame.jpg").read_bytes()[:2] == b"\xff\xd8", "a JPEG"
    events = ran[-1].output
    assert ran[-1].status == 0, events
    assert "<id>scout1</id>" in events[0], "the listen starts with what the camera sees now"
    assert "<id>scout1</id>" not in events[-1], f"scout1 drove out of view: {events[-1]}"
