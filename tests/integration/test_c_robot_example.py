"""The small robot example of the C device library (services/device/c/examples/robot), driven through
a real gateway: built for this host on TCP, and for the ATmega328P in simavr on a serial line.

The robot drives at the velocity it is told for as long as it keeps being told (a dead-man), stops
on ``behaviors.stop``, reports where it is on a timer and drains its battery while it moves."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from pathlib import Path

import grpc
import pytest
from support.c_device import CProgram, build
from support.gateway_process import StartGateway
from support.waiting import eventually

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 20.0
OPTIONS = "{ timeout = 5.0, backoff_initial = 0.05, backoff_max = 0.5 }"
STOPPED = "(0 0 0 0 0 0)"


def config(url: str) -> str:
    return f'[[services]]\nname = "robot"\nurl = "{url}"\noptions = {OPTIONS}\n'


async def get(stub: pb_grpc.PropertyServiceStub, prop: str) -> str:
    return str((await stub.Get(pb.GetRequest(service="robot", property=prop), timeout=WAIT)).value)


async def set_(stub: pb_grpc.PropertyServiceStub, prop: str, value: str) -> str:
    reply = await stub.Set(pb.SetRequest(service="robot", property=prop, value=value), timeout=WAIT)
    return str(reply.value)


async def refused(stub: pb_grpc.PropertyServiceStub, prop: str, value: str | None = None) -> grpc.StatusCode:
    with pytest.raises(grpc.aio.AioRpcError) as info:
        await (get(stub, prop) if value is None else set_(stub, prop, value))
    return info.value.code()


async def values_of(stub: pb_grpc.PropertyServiceStub, prop: str) -> AsyncIterator[str]:
    """The values a Listen of ``prop`` hears: the current one first, then each change."""
    stream = stub.Listen(pb.ListenRequest(service="robot", property=prop))
    try:
        async with asyncio.timeout(WAIT):
            while True:
                msg = await stream.read()
                assert msg is not grpc.aio.EOF, "the Listen ended"
                for event in msg.events:
                    yield event.value
    finally:
        stream.cancel()


def pose(value: str) -> list[float]:
    return [float(n) for n in value.strip("()").split()]


async def drive_the_robot(address: str, tick_s: float) -> None:
    async with grpc.aio.insecure_channel(address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        # The gateway is up before it has heard the robot greet: ask until it has.
        names = await eventually(lambda: get(stub, "properties"), retry_on=(grpc.aio.AioRpcError,))
        assert names.strip("()").split() == [
            "location",
            "velocity",
            "behaviors.stop",
            "battery",
        ]
        assert await get(stub, "battery") == "100"
        # Elements are x y z roll pitch yaw whatever the property means: there is no "wz".
        assert await refused(stub, "velocity.wz") == grpc.StatusCode.NOT_FOUND
        # The range (-1..1) holds for each element, of a whole SET and of one element alike; outside
        # it is ERR 3, INVALID_ARGUMENT (docs/device-spec.md §3.2).
        assert await refused(stub, "velocity", "(1.5 0 0 0 0 0)") == grpc.StatusCode.INVALID_ARGUMENT
        assert await refused(stub, "velocity.yaw", "-2") == grpc.StatusCode.INVALID_ARGUMENT
        assert await refused(stub, "location", "(1 0 0 0 0 0)") == grpc.StatusCode.FAILED_PRECONDITION
        # Drive, and nobody SETs the velocity again: the location moves on each tick (0.5 m/s and
        # 0.1 rad/s for 0.5 s: 0.25 m and 0.05 rad), and the dead-man stops the robot on the third.
        velocity = values_of(stub, "velocity")
        assert await anext(velocity) == STOPPED
        assert await set_(stub, "velocity", "(0.5 0 0 0 0 0.1)") == "(0.5 0 0 0 0 0.1)"
        assert await anext(velocity) == "(0.5 0 0 0 0 0.1)"  # the core's EVENT after the SET's OK
        assert await anext(velocity) == STOPPED
        await velocity.aclose()
        x, *_, yaw = pose(await get(stub, "location"))
        assert x == 0.5 and yaw == 0.1, "two ticks of motion, then the stop"
        # The same value SET again runs on_set again: a driver that keeps sending keeps it moving,
        # for longer than the dead-man's three ticks, and no stop is heard meanwhile. The ticks are
        # counted by the distance moved (0.1 m a tick at 0.2 m/s), not by the wall's clock: a
        # simulated MCU may run faster or slower than real time.
        heard: list[str] = []
        velocity = values_of(stub, "velocity")
        assert await anext(velocity) == STOPPED

        async def hear() -> None:
            async for value in velocity:
                heard.append(value)

        listening = asyncio.create_task(hear())
        start = pose(await get(stub, "location"))[0]
        try:
            for _ in range(2000):
                assert await set_(stub, "velocity", "(0.2 0 0 0 0 0)") == "(0.2 0 0 0 0 0)"
                if pose(await get(stub, "location"))[0] >= start + 0.45:
                    break
                await asyncio.sleep(min(tick_s / 10, 0.02))
            else:
                raise AssertionError("the robot did not move 0.45 m while driven")
        finally:
            listening.cancel()
            await asyncio.gather(listening, return_exceptions=True)
        assert heard and STOPPED not in heard, heard
        # Read right after a Set, as in the loop: the dead-man's three ticks may pass in less time
        # than the listen's cancelling takes on a loaded machine.
        assert await set_(stub, "velocity", "(0.2 0 0 0 0 0)") == "(0.2 0 0 0 0 0)"
        assert await get(stub, "velocity.x") == "0.2"
        # behaviors.stop stops at once; reading an action is refused.
        assert await set_(stub, "behaviors.stop", "now") == ""
        assert await get(stub, "velocity") == STOPPED
        assert await refused(stub, "behaviors.stop") == grpc.StatusCode.FAILED_PRECONDITION
        assert float(await get(stub, "battery")) < 100, "moving drained the battery"
        model = await stub.Describe(pb.DescribeRequest(service="robot"), timeout=WAIT)
        velocity = next(p for p in model.properties if p.name == "velocity")
        assert (velocity.minimum, velocity.maximum) == (-1, 1)


async def test_the_robot_built_for_this_host_drives_through_the_gateway(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    build("host", tmp_path)
    period_ms = 250  # the dead-man (three ticks) then outlasts a slow Set on a loaded machine
    with CProgram(
        [str(tmp_path / "host" / "robot"), "--tcp", "127.0.0.1:0", "--period", str(period_ms)]
    ) as robot:
        gw = gateway_process(config(f"tcp://{robot.where}"))
        await drive_the_robot(gw.address, period_ms / 1000)


async def test_the_robot_firmware_in_simavr_drives_through_the_gateway(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    build("avr", tmp_path)
    build("sim", tmp_path)
    with CProgram([str(tmp_path / "sim" / "simavr_uart"), str(tmp_path / "avr" / "robot.elf")]) as mcu:
        gw = gateway_process(config(f"serial://{mcu.where}?baudrate=115200"))
        await drive_the_robot(gw.address, 0.5)
