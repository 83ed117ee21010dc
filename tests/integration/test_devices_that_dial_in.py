"""Devices that dial in to the gateway's line listener and greet, liveness through the router, persistence.

An in-process gateway with its line listener on; simulated robots run as
device processes that dial the listener (``--connect``) and register by
their greeting. A client that never greets still uses the listener as
before; a device with a bad or taken name gets an ERR line and is hung up on.
"""

from __future__ import annotations

import asyncio
import re
import subprocess
from collections.abc import Awaitable, Callable
from contextlib import AbstractContextManager
from pathlib import Path

import grpc
import pytest
from line_device_support import LineClient, device_process, tcp_device
from support.fake_backend import DictBackend
from support.waiting import eventually

from clients.aio import AsyncClient
from clients.errors import PropertyServiceError
from gateway.app import Gateway
from gateway.config import parse_config
from services.device import DeviceServer

WAIT = 10.0


def dialling_robot(
    name: str, address: str, x: float, y: float
) -> AbstractContextManager[tuple[subprocess.Popen[str], str]]:
    """A simulated robot process that dials ``address`` (a gateway's line listener) and greets as ``name``."""
    return device_process(
        "--service", "sim-robot", "--name", name, "--connect", address, "--option", f"start=[{x}, {y}]"
    )  # fmt: skip


async def greet_as(address: str, greeting: str) -> list[str]:
    """Dial the line listener, send ``greeting``, and return every line until the gateway hangs up."""
    host, _, port = address.rpartition(":")
    client = await LineClient.tcp(host, int(port))
    try:
        await client.send(greeting)
        data = await asyncio.wait_for(client.reader.read(), WAIT)  # to the end of the stream
    finally:
        await client.close()
    return data.decode().splitlines()


def liveness_config(**registry: object) -> dict[str, object]:
    return {
        "gateway": {"listen": "127.0.0.1:0", "line_listen": "127.0.0.1:0"},
        "registry": {"period": 0.2, "timeout": 1.0, "misses": 2, "grace": 30.0, **registry},
        "services": [{"name": "pair", "type": "group", "options": {"members": ["dial1", "dial2"]}}],
    }


@pytest.mark.timeout(60)
async def test_a_device_that_greets_is_registered_goes_down_when_it_hangs_up_and_comes_back() -> None:
    config = parse_config(liveness_config())
    async with Gateway(config) as gw, AsyncClient(gw.address, timeout=5) as client:
        assert await client.get_names("pair", "robots") == []  # named members not served yet

        with dialling_robot("dial1", gw.line_address, 2, 3) as (proc, first):
            assert first == f"connecting to {gw.line_address}"
            await eventually(lambda: client.get_names("registry", "services"), lambda n: "dial1" in n)
            url = await client.get("registry", "services.dial1")
            assert re.fullmatch(r"tcp-in://127\.0\.0\.1:\d+", url), url
            assert await client.get("registry", "services.dial1.type") == "mobile_robot"
            assert await client.get("registry", "services.dial1.state") == "up"
            assert await client.get("dial1", "location.x") == "2"
            found = await eventually(
                lambda: client.get_names("registry", "find", type="mobile_robot", near="(2 3)", radius="1"),
                lambda n: n == ["dial1"],
            )
            assert found == ["dial1"]
            # The static group takes its member as soon as it is served.
            assert await eventually(lambda: client.get_names("pair", "robots"), lambda n: n == ["dial1"])

            # A client that never greets still reaches every service through the listener.
            host, _, port = gw.line_address.rpartition(":")
            line = await LineClient.tcp(host, int(port))
            try:
                assert (await line.line()).startswith("HELLO 1 name=gateway type=gateway")
                await line.send("get dial1.location.x", "#7 get registry.services.dial1.state")
                assert await line.replies(2) == ["OK 2", "#7 OK up"]
            finally:
                await line.close()

            # A taken name, a bad name, no name: an ERR line with the registry's code, then the end.
            taken = await greet_as(gw.line_address, "HELLO 1 name=dial1 type=mobile_robot push=1")
            assert taken[0].startswith("HELLO 1 name=gateway")
            assert taken[1:] == [f"ERR 6 the name 'dial1' is taken (by the device at {url})"]
            (reserved,) = (await greet_as(gw.line_address, "HELLO 1 name=registry"))[1:]
            assert reserved == "ERR 6 the name 'registry' is taken (by local)"
            (bad,) = (await greet_as(gw.line_address, "HELLO 1 name=bad.name type=sensor"))[1:]
            assert bad.startswith("ERR 3 ") and "bad.name" in bad
            (nameless,) = (await greet_as(gw.line_address, "HELLO 1 type=sensor"))[1:]
            assert nameless.startswith("ERR 3 a device that dials in must give its name")
            assert "bad" not in await client.get_names("registry", "services")

            proc.terminate()
            proc.wait(10)
            await eventually(lambda: client.get("registry", "services.dial1.state"), lambda s: s == "down")
            with pytest.raises(PropertyServiceError) as info:
                await client.get("dial1", "location")
            assert info.value.code is grpc.StatusCode.UNAVAILABLE
            assert info.value.message == "service 'dial1' is down: it missed 2 liveness checks"
            assert await client.get("registry", "services.dial1.misses") in ("2", "3", "4")
            assert await client.get("registry", "services.registry.state") == "up"

        # The same device dials in again (from a new address): up again, calls go through.
        with dialling_robot("dial1", gw.line_address, 5, 5):
            await eventually(lambda: client.get("registry", "services.dial1.state"), lambda s: s == "up")
            assert await eventually(lambda: client.get("dial1", "location.x"), lambda x: x == "5") == "5"
            assert await client.get("registry", "services.dial1") != url
            assert await client.get_names("pair", "robots") == ["dial1"]


@pytest.mark.timeout(60)
async def test_registrations_by_set_come_back_after_a_restart_and_config_services_by_the_config(
    tmp_path: Path,
) -> None:
    config = parse_config(liveness_config(persist="registrations.json", period=0), folder=tmp_path)
    assert config.registry.persist == str(tmp_path / "registrations.json")
    with tcp_device("--service", "sim-robot", "--name", "survivor") as (host, port):
        url = f"tcp://{host}:{port}"
        async with Gateway(config) as gw, AsyncClient(gw.address, timeout=5) as client:
            await client.set("registry", "services.survivor", url, type="mobile_robot")
            assert await client.get_names("pair", "robots") == []
        assert '"survivor"' in (tmp_path / "registrations.json").read_text()

        async with Gateway(config) as gw, AsyncClient(gw.address, timeout=5) as client:
            names = await client.get_names("registry", "services")
            assert {"registry", "pair", "survivor"} <= set(names)
            assert await client.get("registry", "services.survivor") == url
            assert await client.get("registry", "services.survivor.type") == "mobile_robot"
            assert await client.get("survivor", "location.x") == "0"


async def test_a_device_leaves_a_gateway_that_does_not_answer_its_keep_alive_for_the_next_one() -> None:
    """A frozen gateway keeps the TCP connection open: the device's PING goes unanswered, and it dials
    the alternate the frozen gateway named in its greeting."""
    heard: dict[str, list[str]] = {"frozen": [], "alternate": []}

    def gateway(
        kind: str, greeting: str
    ) -> Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]:
        async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            writer.write(greeting.encode())
            while line := await reader.readline():  # it reads, and answers nothing: frozen
                heard[kind].append(line.decode().strip())
            writer.close()

        return serve

    alternate = await asyncio.start_server(
        gateway("alternate", "HELLO 1 name=gateway type=gateway push=1\n"), "127.0.0.1", 0
    )
    host, port = alternate.sockets[0].getsockname()[:2]
    frozen = await asyncio.start_server(
        gateway("frozen", f"HELLO 1 name=gateway type=gateway push=1 alternates={host}:{port}\n"),
        "127.0.0.1",
        0,
    )
    device = DeviceServer(
        DictBackend({"x": "1"}, type="sensor"), name="probe", keepalive=0.3, keepalive_timeout=0.3
    )
    dialling = asyncio.create_task(device.dial(*frozen.sockets[0].getsockname()[:2]))
    try:
        greeted = await eventually(
            lambda: asyncio.sleep(0, heard["alternate"]),
            bool,
            what="the alternate dialled",
        )
        assert greeted[0].startswith("HELLO 1 name=probe")
        assert heard["frozen"][0].startswith("HELLO 1 name=probe")
        assert heard["frozen"][1:] == ["PING keepalive"]
    finally:
        dialling.cancel()
        await asyncio.gather(dialling, return_exceptions=True)
        await device.aclose()
        for server in (frozen, alternate):
            server.close()
