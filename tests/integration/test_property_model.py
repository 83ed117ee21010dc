"""Reads never act, and every service describes its typed model: through a real gateway process.

psctl and the SDK as a user runs them against the demo gateway (robots in-process,
a TCP device served by the device server), and a line device that does not
describe itself.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import subprocess
import sys
import time

import aiohttp
import pytest
from support.gateway_process import GatewayProcess, StartGateway

from clients import AsyncClient, Client
from services.kernel.model import Access, PropertyModel

PSCTL = [sys.executable, "-m", "clients.cli"]
FAR = "<marker><location>(500 0 0 0 0 0)</location></marker>"


@pytest.fixture(scope="module")
def target(demo_gateway: GatewayProcess) -> str:
    return demo_gateway.address


def psctl(target: str, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*PSCTL, "-t", target, *args], capture_output=True, text=True, timeout=timeout, check=False
    )


def x_of(client: Client, service: str) -> float:
    return float(client.get(service, "location.x"))


def assert_moving(client: Client, service: str) -> None:
    """The robot's x grows within a few seconds (it drives towards x = 500)."""
    start = x_of(client, service)
    deadline = time.monotonic() + 10
    while x_of(client, service) <= start + 0.05:
        assert time.monotonic() < deadline, f"{service} does not move"
        time.sleep(0.05)


def test_get_of_an_action_fails_and_the_robot_keeps_moving(target: str) -> None:
    with Client(target) as client:
        client.set("scout1", "behaviors.moveto", FAR)
        assert_moving(client, "scout1")
        done = psctl(target, "get", "scout1", "behaviors.stop")
        assert done.returncode == 1
        assert "FAILED_PRECONDITION" in done.stderr
        assert "behaviors.stop` is an action: Set it to invoke it" in done.stderr
        assert_moving(client, "scout1")


@pytest.mark.parametrize(
    "selector", [("scout1", "*"), ("scout1", "behaviors.*"), ("*", "behaviors.*"), ("swarm", "*"), ("*", "*")]
)
def test_wildcard_listens_skip_actions_and_stay_open(target: str, selector: tuple[str, str]) -> None:
    with Client(target) as client:
        client.set("scout2", "behaviors.moveto", FAR)
        assert_moving(client, "scout2")
        done = psctl(target, "listen", *selector, "--duration", "1.5", "--json")
        assert done.returncode == 0, done.stderr
        events = [json.loads(line) for line in done.stdout.splitlines() if line.strip()]
        assert not any(e["property"].startswith("behaviors.") for e in events if "property" in e)
        assert_moving(client, "scout2")


def test_listen_naming_an_action_exactly_is_failed_precondition(target: str) -> None:
    done = psctl(target, "listen", "scout1", "behaviors.stop", "--duration", "2")
    assert done.returncode == 1
    assert "FAILED_PRECONDITION" in done.stderr and "is an action" in done.stderr


def test_sets_that_would_do_nothing_are_refused(target: str) -> None:
    garbage = psctl(target, "set", "scout1", "behaviors.stop", "garbage")
    assert garbage.returncode == 1
    assert "INVALID_ARGUMENT" in garbage.stderr and "takes no value" in garbage.stderr
    query = psctl(target, "set", "registry", "find", "garbage")
    assert query.returncode == 1
    assert "FAILED_PRECONDITION" in query.stderr and "is a query" in query.stderr
    # The query still answers a Get with its parameters.
    assert "scout1" in psctl(target, "get", "registry", "find", "-p", "type=mobile_robot").stdout


def test_describe_gives_the_typed_model_of_a_robot(target: str) -> None:
    with Client(target) as client:
        model = client.describe("scout1")
    assert model.type == "mobile_robot"
    props = {p.name: p for p in model.properties}
    location = props["location"]
    assert (location.type, location.access, location.length, location.unit) == (
        "vector",
        Access.READ,
        6,
        "m, rad",
    )
    speed = props["speed"]
    assert (speed.access, speed.unit, speed.minimum) == (Access.READ_WRITE, "m/s", 0.0)
    assert speed.maximum is not None and speed.maximum > 0
    moveto = props["behaviors.moveto"]
    assert moveto.access is Access.ACTION
    assert moveto.value is not None and moveto.value.type == "marker"
    assert [p.name for p in moveto.parameters] == ["frame"]
    assert props["behaviors.stop"].access is Access.ACTION and props["behaviors.stop"].value is None
    assert props["sensors.battery"].maximum == 1.0


def test_describe_of_the_registry_and_a_group(target: str) -> None:
    with Client(target) as client:
        registry = {p.name: p for p in client.describe("registry").properties}
        swarm = {p.name: p for p in client.describe("swarm").properties}
    assert registry["find"].access is Access.QUERY
    assert {"type", "near", "radius"} <= {p.name for p in registry["find"].parameters}
    assert (swarm["velocity"].access, swarm["velocity"].type) == (Access.READ_WRITE, "vector")
    assert swarm["behaviors.moveto"].access is Access.ACTION
    members = [name for name in swarm if name.startswith("robots.") and name.endswith(".behaviors.stop")]
    assert members and all(swarm[name].access is Access.ACTION for name in members)


def test_psctl_ls_long_shows_the_model(target: str) -> None:
    table = psctl(target, "ls", "-l", "scout1")
    assert table.returncode == 0, table.stderr
    lines = table.stdout.splitlines()
    assert lines[0].split() == ["NAME", "TYPE", "ACCESS", "UNIT", "RANGE", "DOC"]
    rows = {line.split()[0]: line for line in lines[1:]}
    assert rows["location"].split()[1:3] == ["vector[6]", "read"]
    assert "m/s" in rows["speed"] and "0..1000" in rows["speed"]
    assert rows["behaviors.stop"].split()[1:3] == ["none", "action"]
    as_json = {p["name"]: p for p in json.loads(psctl(target, "ls", "-l", "scout1", "--json").stdout)}
    assert as_json["behaviors.moveto"]["value"]["type"] == "marker"
    assert as_json["location"]["access"] == "read"


def test_a_line_device_describes_itself_through_the_proxy(target: str) -> None:
    # rover1 is a sim-robot served by the device server over TCP.
    with Client(target) as client:
        props = {p.name: p for p in client.describe("rover1").properties}
        assert props["location"].type == "vector" and props["location"].access is Access.READ
        assert props["location"].unit == "m, rad"
        assert props["behaviors.stop"].access is Access.ACTION
        assert props["speed"].minimum == 0.0
        done = psctl(target, "get", "rover1", "behaviors.stop")
        assert done.returncode == 1 and "is an action" in done.stderr


@pytest.mark.parametrize("rover", ["rover1", "rover2"])
async def test_a_line_device_has_the_same_model_as_an_in_process_robot(
    demo_gateway: GatewayProcess, rover: str
) -> None:
    """rover1 (TCP) and rover2 (a serial line) are the same sim-robot as scout1, served in-process:
    through the line protocol their models carry the same widgets, types, ranges, value and
    parameters (the docs, and the resolution that only says how to show a value, may be left out
    to fit the device's line: what a Set and a call need is kept first)."""

    def shape(p: PropertyModel) -> PropertyModel:
        return dataclasses.replace(
            p,
            doc="",
            resolution=None,
            value=p.value and dataclasses.replace(p.value, doc=""),
            parameters=tuple(dataclasses.replace(q, doc="") for q in p.parameters),
        )

    async with AsyncClient(demo_gateway.address) as client:
        scout = {p.name: shape(p) for p in (await client.describe("scout1")).properties}
        device = {p.name: shape(p) for p in (await client.describe(rover)).properties}
    assert device == scout
    assert device["location"].gui == "pose" and device["speed"].gui == "slider"
    moveto = device["behaviors.moveto"]
    assert moveto.gui == "button" and moveto.value is not None and moveto.value.type == "marker"
    assert [(q.name, q.type, q.required, q.default) for q in moveto.parameters] == [
        ("frame", "text", False, "world")
    ]
    # The HTTP front end's model (what the console builds its widgets from) says the same.
    async with (
        aiohttp.ClientSession(base_url=demo_gateway.http_url) as http,
        http.get(f"/api/v1/services/{rover}/model") as response,
    ):
        assert response.status == 200
        model = await response.json()
    props = {p["name"]: p for p in model["properties"]}
    assert props["location"]["gui"] == "pose"
    assert props["behaviors.moveto"]["gui"] == "button"
    assert props["behaviors.moveto"]["value"]["type"] == "marker"
    assert [q["name"] for q in props["behaviors.moveto"]["parameters"]] == ["frame"]


async def test_a_line_device_that_does_not_describe_itself(gateway_process: StartGateway) -> None:
    asked: list[str] = []

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(b"HELLO 1 name=plain type=light push=0\n")
        while line := (await reader.readline()).decode().rstrip("\n"):
            tag, _, request = line.partition(" ")
            asked.append(request)
            answers = {"GET properties": "OK (power level)", "GET power": "OK true", "GET level": "OK 0.5"}
            writer.write(f"{tag} {answers.get(request, 'ERR 5 no such property')}\n".encode())
        writer.close()

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        config = f'[[services]]\nname = "plain"\nurl = "tcp://127.0.0.1:{port}"\n'
        gw = await asyncio.to_thread(gateway_process, config)
        async with AsyncClient(gw.address) as client:
            model = await client.describe("plain")
            assert await client.get("plain", "level") == "0.5"
    finally:
        server.close()
    assert [(p.name, p.type, p.access) for p in model.properties] == [
        ("power", "unknown", Access.UNKNOWN),
        ("level", "unknown", Access.UNKNOWN),
    ]
    assert "GET properties.model" in asked
