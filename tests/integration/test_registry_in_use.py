"""The registry and the demo's swarm as a user meets them through a real gateway process."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from typing import Any

import grpc
import pytest
from line_device_support import tcp_device
from support.gateway_process import GatewayProcess, StartGateway
from support.ports import free_port
from support.waiting import eventually

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 15.0


async def get(stub: pb_grpc.PropertyServiceStub, service: str, prop: str) -> str:
    reply = await stub.Get(pb.GetRequest(service=service, property=prop), timeout=WAIT)
    return str(reply.value)


async def value_becomes(stub: pb_grpc.PropertyServiceStub, service: str, prop: str, want: str) -> str:
    """The value of ``service``/``prop`` once it equals ``want``; fails after WAIT seconds."""
    return await eventually(
        lambda: get(stub, service, prop), lambda v: v == want, within=WAIT, what=f"{service} {prop}"
    )


async def members_become(stub: pb_grpc.PropertyServiceStub, want: set[str]) -> list[str]:
    """The swarm's robots once they are ``want`` (in whatever order they joined); fails after WAIT seconds."""
    robots = await eventually(
        lambda: get(stub, "swarm", "robots"),
        lambda v: set(v.strip("()").split()) == want,
        within=WAIT,
        what="swarm robots",
    )
    return robots.strip("()").split()


async def test_demo_devices_are_mobile_robots_in_the_swarm(demo_gateway: GatewayProcess) -> None:
    async with grpc.aio.insecure_channel(demo_gateway.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        # The rovers greet with type=mobile_robot; the registry learns it from the greeting.
        for rover in ("rover1", "rover2"):
            assert await value_becomes(stub, "registry", f"services.{rover}.type", "mobile_robot") == (
                "mobile_robot"
            )
        robots = await members_become(stub, {"scout1", "scout2", "rover1", "rover2"})
        assert sorted(robots) == ["rover1", "rover2", "scout1", "scout2"]
        reply = await stub.Get(
            pb.GetRequest(service="registry", property="find", parameters={"type": "mobile_robot"}),
            timeout=WAIT,
        )
        assert reply.value == "(rover1 rover2 scout1 scout2)"


async def test_registering_a_dead_url_past_the_call_timeout_leaves_nothing(
    gateway_process: StartGateway,
) -> None:
    # The gateway gives a call 1 s; the registry waits longer for a device. When the gateway
    # gives up on the Set, nothing may stay registered.
    gw = gateway_process(
        """
        [gateway]
        call_timeout = 1.0
        """
    )
    url = f"tcp://127.0.0.1:{free_port()}"
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        with pytest.raises(grpc.aio.AioRpcError) as failed:
            await stub.Set(
                pb.SetRequest(service="registry", property="services.ghost", value=url), timeout=WAIT
            )
        assert failed.value.code() in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED)
        await asyncio.sleep(0.5)
        assert await get(stub, "registry", "services") == "(registry)"
        with pytest.raises(grpc.aio.AioRpcError) as unknown:
            await get(stub, "ghost", "location")
        assert unknown.value.code() == grpc.StatusCode.NOT_FOUND


async def test_registering_a_dead_url_answers_unavailable_before_the_call_timeout(
    gateway_process: StartGateway,
) -> None:
    # The registry's wait for the device ends before the gateway's call timeout, so the user
    # hears why nothing was registered instead of a bare DEADLINE_EXCEEDED.
    gw = gateway_process(
        """
        [gateway]
        call_timeout = 1.5
        """
    )
    url = f"tcp://127.0.0.1:{free_port()}"
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        with pytest.raises(grpc.aio.AioRpcError) as failed:
            await stub.Set(
                pb.SetRequest(service="registry", property="services.ghost", value=url), timeout=WAIT
            )
        assert failed.value.code() == grpc.StatusCode.UNAVAILABLE, failed.value.details()
        assert "nothing was registered" in str(failed.value.details())
        assert await get(stub, "registry", "services") == "(registry)"


async def test_a_wildcard_listen_hears_a_member_leave_once(demo_gateway: GatewayProcess) -> None:
    events: list[pb.ListenEvent] = []
    with tcp_device("--service", "sim-robot", "--name", "scout7") as (host, port):
        async with grpc.aio.insecure_channel(demo_gateway.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            url = f"tcp://{host}:{port}"
            await stub.Set(
                pb.SetRequest(service="registry", property="services.scout7", value=url), timeout=WAIT
            )
            await members_become(stub, {"scout1", "scout2", "rover1", "rover2", "scout7"})
            call = stub.Listen(pb.ListenRequest(service="swarm", property="robots.*.location"))
            try:
                async with asyncio.timeout(WAIT):
                    async for msg in call:
                        events.extend(e for e in msg.events if e.property == "robots.scout7.location")
                        if msg.sync:
                            await stub.Set(
                                pb.SetRequest(service="registry", property="services.scout7", value=""),
                                timeout=WAIT,
                            )
                        if any(e.removed for e in events):
                            break
                # Anything else about scout7 would come in the next moments.
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(1.0):
                        async for msg in call:
                            events.extend(e for e in msg.events if e.property == "robots.scout7.location")
            finally:
                call.cancel()
    assert [e.removed for e in events] == [False, True]


def has_location(msg: pb.ListenResponse, service: str, prefix: str) -> bool:
    return any(e.service == service and e.value.startswith(prefix) for e in msg.events)


async def read_until(call: Any, wanted: Callable[[pb.ListenResponse], bool]) -> pb.ListenResponse:
    """Read ``call`` until a message satisfies ``wanted``; a stream that ends first fails the test."""
    async for msg in call:
        if wanted(msg):
            return msg
    raise AssertionError(f"the Listen stream ended ({await call.code()}) before the awaited message")


async def test_listens_live_on_when_a_device_registers_and_comes_back(demo_gateway: GatewayProcess) -> None:
    # A Listen on every service's location, and one on a registered device's location, stay
    # open while the device registers, leaves and registers again: its proxy is still
    # connecting when the gateway first serves it.
    with tcp_device("--service", "sim-robot", "--name", "scout8", "--option", "start=[8, 8]") as (host, port):
        url = f"tcp://{host}:{port}"
        async with grpc.aio.insecure_channel(demo_gateway.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)

            async def register(value: str) -> None:
                await stub.Set(
                    pb.SetRequest(service="registry", property="services.scout8", value=value), timeout=WAIT
                )

            everyone = stub.Listen(pb.ListenRequest(service="*", property="location"))
            try:
                async with asyncio.timeout(WAIT):
                    await read_until(everyone, lambda msg: msg.sync)
                    await register(url)
                    await read_until(everyone, lambda msg: has_location(msg, "scout8", "(8 8 "))
                one = stub.Listen(pb.ListenRequest(service="scout8", property="location"))
                try:
                    async with asyncio.timeout(WAIT):
                        await read_until(one, lambda msg: msg.sync)
                        await register("")
                        await register(url)
                        await stub.Set(
                            pb.SetRequest(
                                service="scout8",
                                property="behaviors.moveto",
                                value="<marker><location>(8 8.2)</location></marker>",
                            ),
                            timeout=WAIT,
                        )
                        await read_until(one, lambda msg: has_location(msg, "scout8", "(8 8.2 "))
                    async with asyncio.timeout(WAIT):
                        await read_until(everyone, lambda msg: has_location(msg, "scout8", "(8 8.2 "))
                finally:
                    one.cancel()
            finally:
                everyone.cancel()
                with contextlib.suppress(grpc.aio.AioRpcError):
                    await register("")


async def test_a_gateway_with_query_groups_shuts_down_quietly(gateway_process: StartGateway) -> None:
    gw = gateway_process(
        """
        [[services]]
        name = "scout1"
        type = "sim-robot"

        [[services]]
        name = "swarm"
        type = "group"
        options = { query = { type = "mobile_robot" } }

        [[services]]
        name = "pair"
        type = "group"
        options = { query = { type = "mobile_robot" } }
        """
    )
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        assert await value_becomes(stub, "swarm", "robots", "(scout1)") == "(scout1)"
    assert gw.stop() == 0
    noisy = [line for line in gw.output.splitlines() if "WARNING" in line or "ERROR" in line]
    assert noisy == [], gw.output
