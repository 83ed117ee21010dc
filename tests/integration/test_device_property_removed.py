"""A property a device drops: a gRPC Listen through a real gateway hears ``removed``, then its value again.

The device is a real device process serving a rig whose tool can be
unplugged (``tool.level`` goes away) and plugged in again. The gateway is a
real process reaching the device through its ``tcp://`` proxy. The proxy
learns that the property went in each way the line protocol tells it: a GONE
line from a device that pushes, NOT_FOUND on a poll of a device that cannot
push, and NOT_FOUND on the LISTEN it sends again after the device reconnects.
"""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
from collections.abc import AsyncIterator
from contextlib import AbstractContextManager, asynccontextmanager
from pathlib import Path

import grpc
import pytest
from line_device_support import device_process
from support.gateway_process import ROOT, StartGateway

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

RIG = """
from services.kernel.core import Resource, functional


class Tool(Resource):
    level: float = 0.5

    def __init__(self, level: float) -> None:
        super().__init__()
        self.level = level


class Rig(Resource):
    resource_type = "rig"

    def __init__(self, plugged: bool = True) -> None:
        super().__init__()
        if plugged:
            self.attach("tool", Tool(0.5))

    @functional
    def plug(self, on: bool) -> str:
        if on and "tool" not in self.children():
            self.attach("tool", Tool(0.5))
        elif not on and "tool" in self.children():
            self.detach("tool")
        return "plugged" if on else "unplugged"
"""

FAST = (
    "{ timeout = 2.0, connect_timeout = 2.0, backoff_initial = 0.05, backoff_max = 0.3, "
    "poll_interval = 0.05 }"
)
WAIT = 10.0


@pytest.fixture
def rig_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Device processes started by the test import ``rigs:Rig``."""
    (tmp_path / "rigs.py").write_text(RIG)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), str(ROOT)]))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rig_device(
    port: int, *options: str, push: bool = True
) -> AbstractContextManager[tuple[subprocess.Popen[str], str]]:
    """The rig as a device process on ``port``; ``options`` are its KEY=VALUE options."""
    args = ["--service", "rigs:Rig", "--name", "rig1", "--tcp", f"127.0.0.1:{port}"]
    for option in options:
        args += ["--option", option]
    if not push:
        args.append("--no-push")
    return device_process(*args)


class Listening:
    """One gRPC Listen of ``rig.tool.level``; ``next()`` is its next event."""

    def __init__(self, stub: pb_grpc.PropertyServiceStub) -> None:
        self.call = stub.Listen(pb.ListenRequest(service="rig", property="tool.level"))

    async def next(self) -> pb.Event:
        while True:
            response = await asyncio.wait_for(self.call.read(), WAIT)
            assert response is not grpc.aio.EOF, "the Listen ended"
            if response.events:
                assert len(response.events) == 1, response
                return response.events[0]

    async def removed(self) -> None:
        """The next event says ``tool.level`` is gone."""
        gone = await self.next()
        assert gone.removed and gone.property == "tool.level", gone

    async def value(self, expected: str) -> None:
        """The next event carries ``expected`` as the value of ``tool.level``."""
        event = await self.next()
        assert (event.property, event.value, event.removed) == ("tool.level", expected, False), event


@asynccontextmanager
async def gateway_with_rig(
    gateway_process: StartGateway, port: int
) -> AsyncIterator[pb_grpc.PropertyServiceStub]:
    gw = gateway_process(f'[[services]]\nname = "rig"\nurl = "tcp://127.0.0.1:{port}"\noptions = {FAST}\n')
    async with grpc.aio.insecure_channel(gw.address) as channel:
        yield pb_grpc.PropertyServiceStub(channel)


async def plug(stub: pb_grpc.PropertyServiceStub, on: bool) -> None:
    request = pb.SetRequest(service="rig", property="plug", value="true" if on else "false")
    await stub.Set(request, timeout=WAIT)


@pytest.mark.parametrize("push", [True, False], ids=["device-pushes-GONE", "device-polled-NOT_FOUND"])
async def test_unplugged_property_is_removed_and_comes_back(
    rig_path: None, gateway_process: StartGateway, push: bool
) -> None:
    port = free_port()
    with rig_device(port, push=push):
        async with gateway_with_rig(gateway_process, port) as stub:
            listen = Listening(stub)
            await listen.value("0.5")
            await plug(stub, False)
            await listen.removed()
            await plug(stub, True)
            await listen.value("0.5")
            listen.call.cancel()


async def test_property_missing_after_the_device_reconnects_is_removed_and_comes_back(
    rig_path: None, gateway_process: StartGateway
) -> None:
    port = free_port()
    with rig_device(port) as (device, _):
        async with gateway_with_rig(gateway_process, port) as stub:
            listen = Listening(stub)
            await listen.value("0.5")
            os.kill(device.pid, signal.SIGKILL)
            device.wait(5)
            with rig_device(port, "plugged=false"):
                await listen.removed()
                await plug(stub, True)
                await listen.value("0.5")
            listen.call.cancel()
