"""``psctl`` given several ``-t``: one command on each of two real gateway processes, their lines
tagged with the target, a listen that merges both streams, a target that fails while the others go
on; and the records of ``--format jsonl``, printed or appended to a rotating ``--output`` file."""

from __future__ import annotations

import itertools
import json
import signal
import subprocess
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path

import pytest
from support.gateway_process import GatewayProcess, start_gateway
from support.ports import free_port
from support.psctl import PSCTL, ctrl_c_reaches_children

from clients.cli import MAX_TARGETS

SENSORS = """
[history]
selectors = ["*/data"]

[[services]]
name = "thermo1"
type = "sim-sensor"
"""

RECORD_KEYS = {"target", "service", "property", "value", "time", "kind"}


@pytest.fixture(scope="module")
def two_gateways(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    """Two gateway processes, each with a sensor ``thermo1`` that changes by itself (5 Hz)."""
    started: list[GatewayProcess] = []
    try:
        for name in ("gw-a", "gw-b"):
            started.append(start_gateway(tmp_path_factory.mktemp(name), SENSORS))
        yield started[0].address, started[1].address
    finally:
        for gw in started:
            gw.stop(check_log=False)
        for gw in started:
            gw.check_log()


def run(*args: str, stdin: str | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*PSCTL, *args], capture_output=True, text=True, timeout=60, input=stdin, check=False
    )


def tagged(target: str, line: str) -> str:
    """What ``line`` of one target reads as when several share the output."""
    return f"[{target}] {line}"


def test_one_get_reads_each_gateway_and_each_line_names_its_target(two_gateways: tuple[str, str]) -> None:
    a, b = two_gateways
    done = run("-t", a, "-t", b, "get", "thermo1", "rate_hz")
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [tagged(a, "5"), tagged(b, "5")]
    # One target: the output as it always was, byte for byte.
    assert run("-t", a, "get", "thermo1", "rate_hz").stdout == "5\n"
    # -t before and after the command name add up, in order; several paths keep their own lines together.
    done = run("-t", b, "get", "thermo1", "rate_hz", "location", "-t", a)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [
        tagged(b, "rate_hz = 5"),
        tagged(b, "location = (0 0 0 0 0 0)"),
        tagged(a, "rate_hz = 5"),
        tagged(a, "location = (0 0 0 0 0 0)"),
    ]


def test_json_output_of_several_gateways_carries_the_target(two_gateways: tuple[str, str]) -> None:
    a, b = two_gateways
    done = run("-t", a, "-t", b, "--json", "get", "thermo1", "rate_hz")
    assert [json.loads(line) for line in done.stdout.splitlines()] == [
        {"target": a, "service": "thermo1", "property": "rate_hz", "value": "5"},
        {"target": b, "service": "thermo1", "property": "rate_hz", "value": "5"},
    ]
    listed = [json.loads(line) for line in run("-t", a, "-t", b, "--json", "ls").stdout.splitlines()]
    assert [doc["target"] for doc in listed] == [a, b]
    assert all("thermo1" in doc["result"] for doc in listed)


def test_a_set_from_stdin_reaches_every_gateway(two_gateways: tuple[str, str]) -> None:
    a, b = two_gateways
    done = run("-t", a, "-t", b, "set", "thermo1", "rate_hz", "-", stdin="4\n")
    assert done.returncode == 0, done.stderr
    try:
        assert run("-t", a, "-t", b, "get", "thermo1", "rate_hz").stdout.splitlines() == [
            tagged(a, "4"),
            tagged(b, "4"),
        ]
    finally:
        assert run("-t", a, "-t", b, "set", "thermo1", "rate_hz", "5").returncode == 0


def test_a_listen_on_two_gateways_merges_their_events_as_they_come(two_gateways: tuple[str, str]) -> None:
    a, b = two_gateways
    done = run("-t", a, "-t", b, "listen", "thermo1", "data", "--duration", "3")
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    targets = [
        a if line.startswith(f"[{a}] ") else b if line.startswith(f"[{b}] ") else "?" for line in lines
    ]
    assert "?" not in targets, lines
    assert " thermo1 data = " in lines[0]
    # Both streams run at once: over three seconds of 5 Hz each, the two are mixed, not one after the other.
    switches = sum(1 for before, after in itertools.pairwise(targets) if before != after)
    assert targets.count(a) >= 3 and targets.count(b) >= 3, lines
    assert switches >= 2, lines


def test_a_gateway_that_fails_is_reported_while_the_others_go_on(two_gateways: tuple[str, str]) -> None:
    a, b = two_gateways
    dead = f"127.0.0.1:{free_port()}"
    done = run("-t", a, "-t", dead, "-t", b, "get", "thermo1", "rate_hz")
    assert done.returncode == 3  # the exit status says one failed: it could not be reached
    assert done.stdout.splitlines() == [tagged(a, "5"), tagged(b, "5")]
    assert done.stderr.startswith(f"[{dead}] error: UNAVAILABLE: cannot reach the gateway at {dead}")
    assert done.stderr.count("\n") == 1

    # A listen: the other gateway's events go on to the end; the failure decides the exit status.
    done = run("-t", dead, "-t", a, "listen", "thermo1", "data", "--duration", "1.5")
    assert done.returncode == 3
    assert done.stderr.startswith(f"[{dead}] error: UNAVAILABLE")
    assert sum(line.startswith(f"[{a}] ") for line in done.stdout.splitlines()) >= 3

    # A gateway's own error answer on one target: exit 1, the other's value still printed.
    nothing = run("-t", a, "-t", b, "get", "thermo1", "no_such")
    assert nothing.returncode == 1
    assert nothing.stdout == ""
    assert nothing.stderr.splitlines()[0].startswith(f"[{a}] error: NOT_FOUND: ")
    assert nothing.stderr.splitlines()[1].startswith(f"[{b}] error: NOT_FOUND: ")


def test_ctrl_c_ends_a_listen_on_several_gateways_with_the_status_of_any_that_failed(
    two_gateways: tuple[str, str],
) -> None:
    a, b = two_gateways
    dead = f"127.0.0.1:{free_port()}"
    for targets, status in (((a, b), 0), ((a, dead), 3)):
        with ctrl_c_reaches_children():
            proc = subprocess.Popen(
                [*PSCTL, *(arg for t in targets for arg in ("-t", t)), "listen", "thermo1", "data"],
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
        try:
            assert proc.stdout is not None
            assert proc.stdout.readline().startswith(tuple(f"[{t}] " for t in targets))  # a stream is up
            if status:
                assert proc.stderr is not None
                assert proc.stderr.readline().startswith(f"[{dead}] error: UNAVAILABLE")
            proc.send_signal(signal.SIGINT)
            _, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
        assert proc.returncode == status
        assert "Traceback" not in err


def test_the_number_of_targets_is_bounded_and_each_given_once(two_gateways: tuple[str, str]) -> None:
    a, _ = two_gateways
    many = [arg for port in range(1, MAX_TARGETS + 2) for arg in ("-t", f"127.0.0.1:{port}")]
    done = run(*many, "get", "thermo1", "data")
    assert done.returncode == 2
    assert done.stderr == f"error: {MAX_TARGETS + 1} targets: at most {MAX_TARGETS} in one command\n"
    done = run("-t", a, "-t", a, "get", "thermo1", "data")
    assert done.returncode == 2
    assert "given twice" in done.stderr
    # A malformed parameter is said once, not once per target.
    done = run("-t", a, "-t", "127.0.0.1:1", "get", "thermo1", "data", "-p", "frame")
    assert done.returncode == 2
    assert done.stderr.count("error:") == 1


def test_top_of_two_gateways_shows_both_in_one_table_and_reports_one_that_fails(
    two_gateways: tuple[str, str],
) -> None:
    a, b = two_gateways
    done = run("-t", a, "-t", b, "top", "thermo1", "--properties", "data,rate_hz", "--count", "2")
    assert done.returncode == 0, done.stderr
    tables = [block.splitlines() for block in done.stdout.strip("\n").split("\n\n")]
    assert len(tables) == 2
    for table in tables:
        assert table[0].endswith(" 2 gateways  thermo1 (4 properties)")
        assert table[1].split() == ["TARGET", "NAME", "VALUE", "UNIT", "AGE", "CHANGES"]
        assert [row.split()[:2] for row in table[2:]] == [
            [a, "data"],
            [a, "rate_hz"],
            [b, "data"],
            [b, "rate_hz"],
        ]

    dead = f"127.0.0.1:{free_port()}"
    done = run("-t", a, "-t", dead, "top", "thermo1", "--properties", "rate_hz", "--count", "1")
    assert done.returncode == 3
    assert done.stderr.startswith(f"[{dead}] error: UNAVAILABLE: cannot reach the gateway at {dead}")
    assert [row.split()[:3] for row in done.stdout.splitlines()[2:] if row] == [[a, "rate_hz", "5"]]


def records(text: str) -> list[dict[str, object]]:
    return [json.loads(line) for line in text.splitlines()]


def test_jsonl_records_of_get_ls_listen_and_history_name_target_service_property_value_time_kind(
    two_gateways: tuple[str, str],
) -> None:
    a, b = two_gateways
    got = records(run("-t", a, "-t", b, "--format", "jsonl", "get", "thermo1", "rate_hz", "location").stdout)
    assert [(r["target"], r["property"], r["value"], r["kind"]) for r in got] == [
        (a, "rate_hz", "5", "value"),
        (a, "location", "(0 0 0 0 0 0)", "value"),
        (b, "rate_hz", "5", "value"),
        (b, "location", "(0 0 0 0 0 0)", "value"),
    ]
    for record in got:
        assert set(record) >= RECORD_KEYS
        assert datetime.fromisoformat(str(record["time"])).tzinfo is not None

    # One target: still a record with its target.
    listed = records(run("-t", a, "ls", "--format", "jsonl").stdout)
    assert {"target": a, "service": "thermo1", "property": None, "value": None, "kind": "service"} in [
        {k: v for k, v in r.items() if k != "time"} for r in listed
    ]
    props = records(run("-t", a, "ls", "thermo1", "--format", "jsonl").stdout)
    assert {(r["service"], r["property"], r["kind"]) for r in props} >= {("thermo1", "data", "property")}

    events = records(
        run("-t", a, "-t", b, "--format", "jsonl", "listen", "thermo1", "data", "--count", "2").stdout
    )
    assert sorted(str(r["target"]) for r in events) == sorted([a, a, b, b])
    assert all(r["kind"] == "event" and set(r) >= RECORD_KEYS and float(str(r["value"])) for r in events)

    kept = records(run("-t", a, "--format", "jsonl", "history", "thermo1", "data", "--limit", "3").stdout)
    assert [r["kind"] for r in kept[:3]] == ["history"] * 3
    times = [datetime.fromisoformat(str(r["time"])) for r in kept[:3]]
    assert times == sorted(times)

    done = run("-t", a, "--json", "--format", "jsonl", "ls")
    assert done.returncode == 2 and "--json and --format jsonl disagree" in done.stderr


def test_records_are_appended_to_an_output_file_that_rotates_at_its_bound(
    two_gateways: tuple[str, str], tmp_path: Path
) -> None:
    a, b = two_gateways
    out = tmp_path / "values.jsonl"
    read = ("-t", a, "-t", b, "--format", "jsonl", "get", "thermo1", "rate_hz", "--output", str(out))
    for _ in range(2):
        done = run(*read)
        assert done.returncode == 0, done.stderr
        assert done.stdout == ""
    appended = records(out.read_text())
    assert [(r["target"], r["value"]) for r in appended] == [(a, "5"), (b, "5")] * 2

    # A bound of 1 KiB, two old files kept: the history of both gateways (about 200 bytes a record) rotates.
    small = ("--output-max-bytes", "1k", "--output-keep", "2")
    for _ in range(6):
        done = run(
            "-t",
            a,
            "-t",
            b,
            "--format",
            "jsonl",
            "history",
            "thermo1",
            "data",
            "--limit",
            "3",
            "-o",
            str(out),
            *small,
        )
        assert done.returncode == 0, done.stderr
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["values.jsonl", "values.jsonl.1", "values.jsonl.2"]
    for path in tmp_path.iterdir():
        assert path.stat().st_size <= 1024
        assert all(set(r) >= RECORD_KEYS for r in records(path.read_text()))

    # --output belongs to jsonl records (get's value file aside); a folder is a clear error.
    done = run("-t", a, "listen", "thermo1", "data", "--count", "1", "--output", str(out))
    assert done.returncode == 2 and "--format jsonl" in done.stderr
    done = run("-t", a, "-t", b, "get", "thermo1", "rate_hz", "--output", str(tmp_path / "value"))
    assert (done.returncode, done.stderr.count("error:")) == (2, 1)
    assert "with several -t, use --format jsonl" in done.stderr
    done = run("-t", a, "--format", "jsonl", "ls", "--output", str(tmp_path))
    assert done.returncode == 2 and done.stderr.startswith(f"error: --output {tmp_path}: ")
    if Path("/dev/full").exists():  # a full disk: one line, exit 1, no traceback
        done = run("-t", a, "-t", b, "--format", "jsonl", "get", "thermo1", "rate_hz", "-o", "/dev/full")
        assert (done.returncode, done.stderr) == (1, "error: --output /dev/full: No space left on device\n")
