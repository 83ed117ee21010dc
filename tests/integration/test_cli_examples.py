"""The examples ``psctl --help`` and docs/client.md print run as shown against the demo gateway."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from typing import Any

import pytest

PSCTL = [sys.executable, "-m", "clients.cli"]


@pytest.fixture(scope="module")
def demo_target(demo_gateway: Any) -> str:
    """Address of this module's demo gateway process (see conftest.py)."""
    return str(demo_gateway.address)


def run(target: str, args: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*PSCTL, "-t", target, *args], capture_output=True, text=True, timeout=60, check=False
    )


def help_examples() -> list[list[str]]:
    """The one-shot (ls, get, set) example commands of ``psctl --help``, as argument lists."""
    shown = subprocess.run([*PSCTL, "--help"], capture_output=True, text=True, timeout=30, check=True)
    examples = []
    for line in shown.stdout.splitlines():
        m = re.match(r"^  psctl (.*?)(?:\s{3,}.*)?$", line)
        if m:
            args = shlex.split(m.group(1))
            if "listen" not in args:
                examples.append(args)
    return examples


def test_every_one_shot_help_example_succeeds(demo_target: str) -> None:
    examples = help_examples()
    assert len(examples) >= 6
    for args in examples:
        done = run(demo_target, args)
        assert done.returncode == 0, f"psctl {shlex.join(args)}: {done.stderr}"
        assert done.stderr == ""


def test_listen_example_of_the_guide_runs(demo_target: str) -> None:
    # docs/client.md: listen to every service's location, throttled, as JSON, for a while.
    done = run(demo_target, ["listen", "*", "location", "--min-interval", "0.5", "--json", "--duration", "1"])
    assert done.returncode == 0, done.stderr
    services = {json.loads(line)["service"] for line in done.stdout.splitlines()}
    assert {"scout1", "scout2"} <= services


@pytest.mark.parametrize("timeout", ["nan", "-1", "soon", "inf"])
def test_a_bad_timeout_is_a_usage_error(demo_target: str, timeout: str) -> None:
    done = run(demo_target, ["--timeout", timeout, "ls"])
    assert done.returncode == 2
    assert "--timeout" in done.stderr
