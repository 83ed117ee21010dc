"""The examples ``psctl --help`` and docs/client.md print run as shown against the demo gateway."""

from __future__ import annotations

import functools
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


SUBCOMMANDS = ("ls", "get", "set", "listen")
#: Seconds a listen example may run before the test calls it stuck (examples end within a few).
LISTEN_LIMIT = 20.0


@functools.cache
def all_help_examples() -> tuple[tuple[str, ...], ...]:
    """Every example command of ``psctl --help`` and of each ``psctl COMMAND --help``, as argument lists."""
    examples = []
    for extra in [[], *([c] for c in SUBCOMMANDS)]:
        shown = subprocess.run(
            [*PSCTL, *extra, "--help"], capture_output=True, text=True, timeout=30, check=True
        )
        for line in shown.stdout.splitlines():
            m = re.match(r"^  psctl (.*?)(?:\s{3,}.*)?$", line)
            if m:
                examples.append(tuple(shlex.split(m.group(1))))
    return tuple(examples)


def help_examples() -> list[list[str]]:
    """The one-shot (ls, get, set) example commands of the helps. ``psctl cluster`` needs a cluster,
    which the demo is not: tests/integration/test_cluster_operations.py runs it against one. An
    example with gateways of its own (-t) names gateways the demo is not, and ``psctl top`` is a
    view that runs until q: tests/integration/test_psctl_on_several_gateways.py and test_psctl_top.py
    run them."""
    return [
        list(args)
        for args in all_help_examples()
        if "listen" not in args and args[0] not in ("cluster", "top") and "-t" not in args
    ]


def listen_examples() -> list[list[str]]:
    """The listen example commands of the helps."""
    return [list(args) for args in all_help_examples() if "listen" in args]


def test_every_one_shot_help_example_succeeds(demo_target: str) -> None:
    examples = help_examples()
    assert len(examples) >= 6
    for args in examples:
        done = run(demo_target, args)
        assert done.returncode == 0, f"psctl {shlex.join(args)}: {done.stderr}"
        assert done.stderr == ""


def test_every_listen_help_example_ends_by_itself(gateway_process: Any) -> None:
    # A fresh demo: nothing has moved a robot, so an example must not rely on one moving.
    target = str(gateway_process().address)
    examples = list({shlex.join(args): args for args in listen_examples()}.values())
    assert len(examples) >= 4
    # They run side by side; each is given LISTEN_LIMIT seconds and stopped (its PID) after that.
    procs = [
        subprocess.Popen(
            [*PSCTL, "-t", target, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for args in examples
    ]
    stuck = []
    for args, proc in zip(examples, procs, strict=True):
        try:
            out, err = proc.communicate(timeout=LISTEN_LIMIT)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate(timeout=LISTEN_LIMIT)
            stuck.append(shlex.join(args))
            continue
        assert proc.returncode == 0, f"psctl {shlex.join(args)}: {err}"
        assert err == ""
        assert out.strip(), f"psctl {shlex.join(args)} printed nothing"
    assert stuck == [], f"did not end within {LISTEN_LIMIT} s on the demo: {stuck}"


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
