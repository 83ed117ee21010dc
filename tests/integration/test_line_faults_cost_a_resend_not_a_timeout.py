"""Faults of a line device seen through a real gateway process: bytes lost on the line, replies
spoiled on the way, a subscription table that is full, a device that drops.

The devices are scripted (tests/integration/scripted_device.py) on real TCP sockets; the calls
go through the gateway's gRPC port as a client's would. The proxy's call timeout is 5 s: every
bound below is well under it, so a call that waited for its timeout fails the test.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc
from scripted_device import ScriptedDevice, tcp_scripted
from support.gateway_process import GatewayProcess, StartGateway
from support.waiting import wait_until

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 20.0
#: Well under the proxy's 5 s timeout: a call answered within it did not wait for a timeout.
QUICK = 2.5
GREETING = "HELLO 1 name=probe type=sensor push=1"
OPTIONS = "{ timeout = 5.0, backoff_initial = 0.05, backoff_max = 0.5, poll_interval = 0.2 }"


async def start(gateway_process: StartGateway, url: str, options: str = OPTIONS) -> GatewayProcess:
    config = f'[[services]]\nname = "probe"\nurl = "{url}"\noptions = {options}\n'
    return await asyncio.to_thread(gateway_process, config)


@asynccontextmanager
async def client(gw: GatewayProcess) -> AsyncIterator[pb_grpc.PropertyServiceStub]:
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        await connected(stub)
        yield stub


async def connected(stub: pb_grpc.PropertyServiceStub) -> None:
    deadline = time.monotonic() + WAIT
    while True:
        try:
            await stub.Get(pb.GetRequest(service="probe", property="a"), timeout=WAIT)
            return
        except grpc.aio.AioRpcError as exc:
            if exc.code() != grpc.StatusCode.UNAVAILABLE or time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.05)


def get(stub: pb_grpc.PropertyServiceStub, prop: str) -> grpc.aio.UnaryUnaryCall:
    return stub.Get(pb.GetRequest(service="probe", property=prop), timeout=WAIT)


async def values_until(
    stream: grpc.aio.UnaryStreamCall, wanted: dict[str, str], within: float = WAIT
) -> list[pb.Event]:
    """Read events until each property of ``wanted`` has had its value; return all events read."""
    seen: list[pb.Event] = []
    left = dict(wanted)
    async with asyncio.timeout(within):
        while left:
            msg = await stream.read()
            assert msg is not grpc.aio.EOF, f"the stream ended; read {seen}"
            for event in msg.events:
                seen.append(event)
                if left.get(event.property) == event.value:
                    del left[event.property]
    return seen


async def test_a_get_whose_line_the_device_lost_is_sent_again_at_once(gateway_process: StartGateway) -> None:
    device = ScriptedDevice(GREETING, {"a": "1", "b": "2", "c": "3"})
    async with tcp_scripted(device) as url:
        gw = await start(gateway_process, url)
        async with client(gw) as stub:
            device.losing["GET b"] = 1
            began = time.monotonic()
            replies = await asyncio.gather(get(stub, "a"), get(stub, "b"), get(stub, "c"))
            took = time.monotonic() - began
            assert [r.value for r in replies] == ["1", "2", "3"]
            assert took < QUICK, f"the lost GET waited {took:.1f} s: it was not sent again at once"
            # The same line, tag and all, went out twice: the device answered it the second time.
            sent_b = [line for line in device.lines if line.endswith("GET b")]
            assert len(sent_b) == 2 and sent_b[0] == sent_b[1], device.lines
    assert "never retrieved" not in gw.output, gw.output


async def test_a_reply_spoiled_on_the_way_is_asked_for_again(gateway_process: StartGateway) -> None:
    device = ScriptedDevice(GREETING, {"a": "1", "b": "2"})
    async with tcp_scripted(device) as url:
        gw = await start(gateway_process, url)
        async with client(gw) as stub:
            device.damaging["GET b"] = 2  # twice: the third answer arrives whole
            began = time.monotonic()
            reply = await get(stub, "b")
            assert reply.value == "2" and time.monotonic() - began < QUICK
            assert len([line for line in device.lines if line.endswith("GET b")]) == 3
            # A line spoiled every time is not noise: after two resends the call fails DATA_LOSS.
            device.damaging["GET a"] = 10
            try:
                await get(stub, "a")
                raise AssertionError("a reply damaged every time was taken")
            except grpc.aio.AioRpcError as exc:
                assert exc.code() == grpc.StatusCode.DATA_LOSS, exc
            assert len([line for line in device.lines if line.endswith("GET a")]) == 1 + 1 + 2
            assert (await get(stub, "b")).value == "2", "the connection carries on"
    assert "never retrieved" not in gw.output, gw.output


async def test_a_set_whose_line_was_lost_fails_at_once_and_is_not_applied_twice(
    gateway_process: StartGateway,
) -> None:
    device = ScriptedDevice(GREETING, {"a": "1", "count": "0"})
    async with tcp_scripted(device) as url:
        gw = await start(gateway_process, url)
        async with client(gw) as stub:
            device.losing["SET count"] = 1
            began = time.monotonic()
            try:
                await stub.Set(pb.SetRequest(service="probe", property="count", value="1"), timeout=WAIT)
                raise AssertionError("a SET the device lost was taken as applied")
            except grpc.aio.AioRpcError as exc:
                assert exc.code() == grpc.StatusCode.DATA_LOSS, exc
                assert "may or may not have been applied" in (exc.details() or ""), exc
            assert time.monotonic() - began < QUICK, "the lost SET waited for its timeout"
            assert len([line for line in device.lines if "SET count" in line]) == 1, "sent once only"
            assert (await get(stub, "count")).value == "0", "read back: it was not applied"


async def test_a_listen_lost_after_a_restart_is_retried_and_the_client_sees_a_gap(
    gateway_process: StartGateway,
) -> None:
    device = ScriptedDevice(GREETING, {"a": "1", "t": "20"})
    async with tcp_scripted(device) as url:
        gw = await start(gateway_process, url)
        async with client(gw) as stub:
            stream = stub.Listen(pb.ListenRequest(service="probe", property="t"))
            await values_until(stream, {"t": "20"})
            # The device restarts, and the LISTEN that restores the subscription is lost three
            # times over (more than the two resends): the proxy listens again with backoff.
            device.losing["LISTEN t"] = 3
            device.props["t"] = "21"
            device.restart()
            events = await values_until(stream, {"t": "21"})
            assert events[-1].gap, events
            device.change("t", "22")
            assert (await values_until(stream, {"t": "22"}))[-1].value == "22", "events flow again"
            stream.cancel()
    assert "never retrieved" not in gw.output, gw.output


async def test_a_full_subscription_table_costs_only_that_path_a_listen_line_it_is_polled(
    gateway_process: StartGateway,
) -> None:
    props = {name: "0" for name in ("a", "b", "c", "d", "e", "f")}
    device = ScriptedDevice(GREETING, props, max_listens=4)
    async with tcp_scripted(device) as url:
        gw = await start(gateway_process, url)
        async with client(gw) as stub:
            stream = stub.Listen(
                pb.ListenRequest(
                    service="probe",
                    property="a",
                    more=[pb.PropertyRef(property=name) for name in "bcdef"],
                )
            )
            await values_until(stream, dict.fromkeys("abcdef", "0"))
            assert device.subscribed == set("abcd"), "four fit the device's table; none was taken back"
            # The paths the device pushes and the ones the gateway polls both carry changes.
            device.change("a", "1")
            device.props["f"] = "1"
            await values_until(stream, {"a": "1", "f": "1"})
            assert not device.seen("UNLISTEN"), device.lines
            # A second Listen closes and frees room on the device: a polled path gets its LISTEN.
            other = stub.Listen(pb.ListenRequest(service="probe", property="a"))
            await values_until(other, {"a": "1"})
            stream.cancel()
            await wait_until(lambda: device.subscribed == {"a"}, within=WAIT, what="subscriptions")
            other.cancel()


async def test_a_polled_path_moves_to_a_listen_when_the_device_has_room_again(
    gateway_process: StartGateway,
) -> None:
    device = ScriptedDevice(GREETING, {"a": "0", "b": "0"}, max_listens=1)
    async with tcp_scripted(device) as url:
        gw = await start(gateway_process, url)
        async with client(gw) as stub:
            first = stub.Listen(pb.ListenRequest(service="probe", property="a"))
            await values_until(first, {"a": "0"})
            second = stub.Listen(pb.ListenRequest(service="probe", property="b"))
            await values_until(second, {"b": "0"})
            assert device.subscribed == {"a"}, "b is polled"
            first.cancel()
            await wait_until(lambda: device.subscribed == {"b"}, within=WAIT, what="subscriptions")
            device.change("b", "5")
            await values_until(second, {"b": "5"})
            second.cancel()


async def test_health_says_not_serving_as_soon_as_the_device_drops(gateway_process: StartGateway) -> None:
    device = ScriptedDevice(GREETING, {"a": "1"})
    async with tcp_scripted(device) as url:
        gw = await start(gateway_process, url)
        async with grpc.aio.insecure_channel(gw.address) as channel:
            await connected(pb_grpc.PropertyServiceStub(channel))
            health = health_pb2_grpc.HealthStub(channel)
            watch = health.Watch(health_pb2.HealthCheckRequest(service="probe"))
            async with asyncio.timeout(WAIT):
                assert (await watch.read()).status == health_pb2.HealthCheckResponse.SERVING
            # The device drops and does not come back at once (it answers no reconnection).
            began = time.monotonic()
            device.unplug()
            async with asyncio.timeout(WAIT):
                assert (await watch.read()).status == health_pb2.HealthCheckResponse.NOT_SERVING
            assert time.monotonic() - began < QUICK
            check = await health.Check(health_pb2.HealthCheckRequest(service="probe"), timeout=WAIT)
            assert check.status == health_pb2.HealthCheckResponse.NOT_SERVING
            try:  # and calls agree with it
                await get(pb_grpc.PropertyServiceStub(channel), "a")
                raise AssertionError("a Get was answered while the device was unplugged")
            except grpc.aio.AioRpcError as exc:
                assert exc.code() == grpc.StatusCode.UNAVAILABLE, exc
            # Back: it answers the gateway's HELLO, and health follows.
            device.plug_in()
            async with asyncio.timeout(WAIT):
                assert (await watch.read()).status == health_pb2.HealthCheckResponse.SERVING
            watch.cancel()
