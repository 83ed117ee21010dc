"""``psctl`` as a user runs it: a real subprocess against a real gateway process."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from typing import Any

import pytest
from support.ports import free_port
from support.psctl import ctrl_c_reaches_children

PSCTL = [sys.executable, "-m", "clients.cli"]


@pytest.fixture(scope="module")
def demo_target(demo_gateway: Any) -> str:
    """Address of this module's demo gateway process (see conftest.py)."""
    return demo_gateway.address


def psctl(target: str, *args: str, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*PSCTL, "-t", target, *args], capture_output=True, text=True, timeout=60, input=stdin, check=False
    )


def ok(target: str, *args: str) -> str:
    done = psctl(target, *args)
    assert done.returncode == 0, f"psctl {' '.join(args)} failed: {done.stderr}"
    assert done.stderr == ""
    return done.stdout


def test_help_shows_examples() -> None:
    done = subprocess.run([*PSCTL, "--help"], capture_output=True, text=True, timeout=30, check=False)
    assert done.returncode == 0
    assert "examples:" in done.stdout
    assert "psctl listen scout1 location" in done.stdout


def test_ls_services_and_properties(demo_target: str) -> None:
    assert {"scout1", "scout2", "thermo1"} <= set(ok(demo_target, "ls").split())
    listed = json.loads(ok(demo_target, "ls", "--json"))
    assert {"scout1", "scout2", "thermo1"} <= set(listed)
    long = {row["name"]: row for row in json.loads(ok(demo_target, "--json", "ls", "-l"))}
    assert long["scout1"]["type"] == "mobile_robot"
    assert long["thermo1"]["type"] == "sensor"
    props = ok(demo_target, "ls", "scout1").splitlines()
    assert "location" in props
    assert "behaviors.moveto" in props
    details = {row["name"]: row for row in json.loads(ok(demo_target, "ls", "-l", "scout1", "--json"))}
    assert details["location"]["gui"] == "pose"
    assert "frame" in details["behaviors.moveto"]["parameters"]
    table = ok(demo_target, "ls", "-l", "scout1").splitlines()
    assert table[0].split() == ["NAME", "TYPE", "ACCESS", "UNIT", "RANGE", "DOC"]


def test_get_one_and_several(demo_target: str) -> None:
    value = ok(demo_target, "get", "scout2", "location").strip()
    assert value.startswith("(")
    assert len(value.strip("()").split()) == 6
    x = float(ok(demo_target, "get", "scout2", "location.x"))
    assert x == float(value.strip("()").split()[0])
    lines = ok(demo_target, "get", "scout2", "location.x", "location.y").splitlines()
    assert [line.split(" = ")[0] for line in lines] == ["location.x", "location.y"]
    one = json.loads(ok(demo_target, "get", "scout2", "location.x", "--json"))
    assert one == {"service": "scout2", "property": "location.x", "value": str(lines[0].split(" = ")[1])}
    many = json.loads(ok(demo_target, "--json", "get", "scout2", "location.x", "speed"))
    assert [m["property"] for m in many] == ["location.x", "speed"]


def test_set_then_get(demo_target: str) -> None:
    ok(demo_target, "set", "scout2", "speed", "0.25")
    assert ok(demo_target, "get", "scout2", "speed").strip() == "0.25"
    answer = json.loads(ok(demo_target, "set", "scout2", "speed", "0.5", "--json"))
    assert (answer["service"], answer["property"]) == ("scout2", "speed")
    done = psctl(demo_target, "set", "scout2", "actuators.led", "-", stdin="true\n")
    assert done.returncode == 0, done.stderr
    assert ok(demo_target, "get", "scout2", "actuators.led").strip() == "true"
    ok(
        demo_target,
        "set",
        "scout2",
        "behaviors.moveto",
        "<marker><location>(1 0 0 0 0 0)</location></marker>",
        "-p",
        "frame=world",
    )
    # The value after a parameter, as it reads naturally.
    ok(
        demo_target,
        "set",
        "scout2",
        "behaviors.moveto",
        "-p",
        "frame=world",
        "<marker><location>(1 0)</location></marker>",
    )
    done = psctl(demo_target, "set", "scout2", "speed", "-p", "a=b", "0.5", "extra")
    assert done.returncode == 2 and "unrecognized arguments: 0.5 extra" in done.stderr, done.stderr


def test_listen_count_and_json(demo_target: str) -> None:
    lines = ok(demo_target, "listen", "scout2", "location", "--also", "thermo1:location", "--count", "2")
    rows = lines.splitlines()
    assert len(rows) == 2
    assert {tuple(r.split()[1:3]) for r in rows} == {("scout2", "location"), ("thermo1", "location")}
    assert all(" = (" in r for r in rows)
    events = [
        json.loads(r)
        for r in ok(demo_target, "listen", "thermo1", "data", "--json", "--count", "3").split("\n")
        if r
    ]
    assert [e["sequence"] for e in events] == [1, 2, 3]
    assert all(e["service"] == "thermo1" and e["property"] == "data" for e in events)
    assert all(float(e["value"]) == pytest.approx(20, abs=50) for e in events)


def test_listen_duration_ends_by_itself(demo_target: str) -> None:
    out = ok(demo_target, "listen", "scout2", "location", "--updates-only", "--duration", "0.5", "--marks")
    assert "-- sync" in out


def test_listen_ctrl_c_exits_cleanly(demo_target: str) -> None:
    with ctrl_c_reaches_children():
        proc = subprocess.Popen(
            [*PSCTL, "-t", demo_target, "listen", "thermo1", "data"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()  # the current value: the stream is up
        assert "thermo1 data = " in first
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert proc.returncode == 0
    assert "Traceback" not in err


def test_errors_are_one_line_with_exit_codes(demo_target: str) -> None:
    done = psctl(demo_target, "get", "scoutX", "location")
    assert done.returncode == 1
    assert done.stderr.startswith("error: NOT_FOUND: ")
    assert "scoutX" in done.stderr
    assert done.stderr.count("\n") == 1
    assert done.stdout == ""

    done = psctl(demo_target, "set", "scout2", "location", "(1 2 0 0 0 0)")
    assert done.returncode == 1
    assert done.stderr.startswith("error: FAILED_PRECONDITION: ")

    done = psctl(demo_target, "set", "scout2", "speed", "fast")
    assert done.returncode == 1
    assert done.stderr.startswith("error: INVALID_ARGUMENT: ")

    done = psctl(demo_target, "listen", "scout2", "no_such_property", "--count", "1")
    assert done.returncode == 1
    assert done.stderr.startswith("error: NOT_FOUND: ")

    done = psctl(demo_target, "get", "scout2", "location", "-p", "frame")
    assert done.returncode == 2
    assert "NAME=VALUE" in done.stderr

    done = psctl(demo_target, "listen", "scout2", "location", "--count", "0")
    assert done.returncode == 2

    for done in (
        psctl(demo_target, "get", "scoutX", "location"),
        psctl(demo_target, "frobnicate"),
    ):
        assert "Traceback" not in done.stderr


def test_unreachable_gateway_is_clear() -> None:
    port = free_port()
    done = psctl(f"127.0.0.1:{port}", "ls")
    assert done.returncode == 3
    assert done.stderr.startswith(f"error: UNAVAILABLE: cannot reach the gateway at 127.0.0.1:{port}")
    assert "Traceback" not in done.stderr


def test_target_from_environment(demo_target: str) -> None:
    env = {**os.environ, "PSCTL_TARGET": demo_target}
    done = subprocess.run([*PSCTL, "ls"], capture_output=True, text=True, timeout=60, env=env, check=False)
    assert done.returncode == 0, done.stderr
    assert "scout1" in done.stdout.split()
