"""The C device library's example device (services/device/c/examples/thermostat), built for this host,
driven by a real gateway process over TCP and over a pseudo-terminal: Get, Set, Listen, tags,
checksums, a reset mid-session, and a property that is GONE and comes back."""

from __future__ import annotations

import asyncio
import itertools
import struct
from collections.abc import Callable, Iterator
from pathlib import Path

import grpc
import pytest
from support.c_device import CProgram, build
from support.gateway_process import GatewayProcess, StartGateway
from support.serial_tap import WireTap
from support.waiting import eventually

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.kernel.line_protocol import crc8

WAIT = 15.0
PROXY_OPTIONS = "{ timeout = 2.0, backoff_initial = 0.05, backoff_max = 0.5 }"
NAMES = ["temp", "setpoint", "location", "label", "probe", "history"]
MORE_PATHS = ("label", "location.x", "setpoint", "temp.parameters")


@pytest.fixture(scope="module")
def thermostat(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The host build of the example device."""
    into = tmp_path_factory.mktemp("c-build")
    build("host", into)
    return into / "host" / "thermostat"


@pytest.fixture
def tcp_device(thermostat: Path) -> Iterator[CProgram]:
    with CProgram([str(thermostat), "--tcp", "127.0.0.1:0", "--period", "100"]) as device:
        yield device


def config(url: str, options: str = PROXY_OPTIONS) -> str:
    return f'[[services]]\nname = "thermo"\nurl = "{url}"\noptions = {options}\n'


async def get(stub: pb_grpc.PropertyServiceStub, prop: str) -> str:
    reply = await stub.Get(pb.GetRequest(service="thermo", property=prop), timeout=WAIT)
    return str(reply.value)


async def set_(stub: pb_grpc.PropertyServiceStub, prop: str, value: str) -> str:
    reply = await stub.Set(pb.SetRequest(service="thermo", property=prop, value=value), timeout=WAIT)
    return str(reply.value)


async def refused(call: Callable[[], object]) -> grpc.StatusCode:
    with pytest.raises(grpc.aio.AioRpcError) as info:
        await call()  # type: ignore[misc]
    return info.value.code()


async def next_event(stream: grpc.aio.UnaryStreamCall[pb.ListenRequest, pb.ListenResponse]) -> pb.Event:
    """The next event of a Listen stream (markers skipped)."""
    async with asyncio.timeout(WAIT):
        while True:
            msg = await stream.read()
            assert msg is not grpc.aio.EOF, "the Listen stream ended"
            if msg.events:
                assert len(msg.events) == 1 or all(e.property == "temp" for e in msg.events)
                return msg.events[-1]


async def check_get_set_and_errors(gw: GatewayProcess) -> None:
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        # A gateway that is up may not have opened the device yet (a pty on a loaded machine): ask
        # until it has.
        names = await eventually(lambda: get(stub, "properties"), retry_on=(grpc.aio.AioRpcError,))
        assert names.strip("()").split() == NAMES
        assert 19.0 <= float(await get(stub, "temp")) <= 21.5
        assert await get(stub, "setpoint") == "20"
        assert await set_(stub, "setpoint", "22.5") == "22.5"
        assert await get(stub, "setpoint") == "22.5"
        assert await set_(stub, "location", "(1.25 -2 0 0 0 0.5)") == "(1.25 -2 0 0 0 0.5)"
        assert await get(stub, "location.y") == "-2"
        assert await set_(stub, "label", "shelf 2, left") == "shelf 2, left"
        assert await get(stub, "temp.gui") == "gauge"
        # Several paths in one Get: the gateway sends them tagged, all at once where the device allows.
        many = await stub.Get(
            pb.GetRequest(
                service="thermo",
                property="setpoint",
                more=[pb.PropertyRef(property=p) for p in MORE_PATHS],
            ),
            timeout=WAIT,
        )
        assert [many.value, *(v.value for v in many.more)] == ["22.5", "shelf 2, left", "1.25", "22.5", "()"]
        # The device's refusals reach the client with their own codes.
        assert await refused(lambda: set_(stub, "setpoint", "99")) == grpc.StatusCode.INVALID_ARGUMENT
        assert await refused(lambda: set_(stub, "setpoint", "20.25")) == grpc.StatusCode.INVALID_ARGUMENT
        assert await refused(lambda: set_(stub, "temp", "30")) == grpc.StatusCode.FAILED_PRECONDITION
        assert await refused(lambda: get(stub, "probe")) == grpc.StatusCode.FAILED_PRECONDITION
        assert await refused(lambda: get(stub, "nosuch")) == grpc.StatusCode.NOT_FOUND
        assert await refused(lambda: set_(stub, "probe", "sideways")) == grpc.StatusCode.INVALID_ARGUMENT
        # The device describes itself: the gateway's Describe reads its properties.model.
        model = await stub.Describe(pb.DescribeRequest(service="thermo"), timeout=WAIT)
        by_name = {p.name: p for p in model.properties}
        assert list(by_name) == NAMES
        setpoint = by_name["setpoint"]
        assert setpoint.unit == "degC" and (setpoint.minimum, setpoint.maximum) == (5, 35)
        assert by_name["probe"].access == pb.ACCESS_ACTION and by_name["temp"].access == pb.ACCESS_READ
        history = by_name["history"]
        assert (history.type, history.media_type) == ("bytes", "application/octet-stream")
        # The binary value: the C library writes its base64 as it reads the ring (protocol 1.2).
        reply = await stub.Get(pb.GetRequest(service="thermo", property="history"), timeout=WAIT)
        assert reply.HasField("data") and len(reply.data) == 16
        readings = struct.unpack(">8h", reply.data)
        assert all(abs(a - b) <= 1 for a, b in itertools.pairwise(readings)), readings
        temp = round(float(await get(stub, "temp")) * 10)
        assert abs(readings[-1] - temp) <= 1, (readings, temp)  # the newest last (a tick may fall between)


async def check_listen_reset_gone_and_return(gw: GatewayProcess, device: CProgram) -> None:
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        stream = stub.Listen(pb.ListenRequest(service="thermo", property="temp"))
        first = await next_event(stream)
        values = {first.value}
        while len(values) < 3:  # the timer changes temp every 0.1 s
            values.add((await next_event(stream)).value)
        # Reset mid-session: the device greets again on the same line and has forgotten every
        # LISTEN; the gateway restores them and marks the next event as following a gap.
        await set_(stub, "setpoint", "30")
        device.reset()
        event = await next_event(stream)
        while not event.gap:
            event = await next_event(stream)
        assert await get(stub, "setpoint") == "20", "the reset set every value back"
        after = {(await next_event(stream)).value for _ in range(3)}
        assert len(after) >= 2, "events flow again after the reset"
        # The probe is unplugged: the Listen hears that temp is gone; plugged back, it resumes.
        assert await set_(stub, "probe", "out") == ""
        event = await next_event(stream)
        while not event.removed:
            event = await next_event(stream)
        assert "temp" not in (await get(stub, "properties")).split()
        assert await refused(lambda: get(stub, "temp")) == grpc.StatusCode.NOT_FOUND
        assert await set_(stub, "probe", "in") == ""
        back = await next_event(stream)
        assert not back.removed and 18 <= float(back.value) <= 22
        assert {(await next_event(stream)).value for _ in range(3)} - {back.value}, "and keeps changing"
        stream.cancel()


async def test_get_set_and_errors_over_tcp(gateway_process: StartGateway, tcp_device: CProgram) -> None:
    gw = gateway_process(config(f"tcp://{tcp_device.where}"))
    await check_get_set_and_errors(gw)


async def test_listen_reset_gone_and_return_over_tcp(
    gateway_process: StartGateway, tcp_device: CProgram
) -> None:
    gw = gateway_process(config(f"tcp://{tcp_device.where}"))
    await check_listen_reset_gone_and_return(gw, tcp_device)


def check_checksums(tap: WireTap) -> None:
    """Once the gateway sent a checksummed line, every line the device sent carries a right CRC-8,
    but for its greeting after a reset: a reset forgets checksum mode (docs/device-spec.md §6.5)."""
    record = tap.record()
    first = next(i for i, (who, line) in enumerate(record) if who == "gw" and line.startswith("$"))
    device_lines = [line for who, line in record[first:] if who == "dev" and line]
    assert device_lines, tap.transcript()
    restarts = [line for line in device_lines if line.startswith("HELLO 1 ")]
    assert len(restarts) == 1, tap.transcript()
    for line in (line for line in device_lines if line not in restarts):
        assert line.startswith("$") and line[-3] == "*", line
        assert int(line[-2:], 16) == crc8(line[1:-3].encode()), line


async def test_the_same_over_a_pty_with_checksums(gateway_process: StartGateway, thermostat: Path) -> None:
    with (
        CProgram([str(thermostat), "--pty", "--period", "100"]) as device,
        WireTap(device.where) as tap,
    ):
        options = "{ timeout = 2.0, backoff_initial = 0.05, backoff_max = 0.5, checksum = true }"
        gw = gateway_process(config(f"serial://{tap.path}?baudrate=115200", options))
        await check_get_set_and_errors(gw)
        await check_listen_reset_gone_and_return(gw, device)
        check_checksums(tap)
        assert any(who == "gw" and line.startswith("$#") for who, line in tap.record()), "tagged requests"


async def test_the_minimal_profile_serves_numbers_and_text_through_the_gateway(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    """The thermostat built with -DPS_MINIMAL (what fits 4 KiB on the AVR): Get, Set and Listen of
    its numbers and text through a real gateway; what the profile leaves out is not there."""
    build("host", tmp_path, profile="-DPS_MINIMAL")
    with CProgram(
        [str(tmp_path / "host" / "thermostat"), "--tcp", "127.0.0.1:0", "--period", "100"]
    ) as device:
        gw = gateway_process(config(f"tcp://{device.where}"))
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            assert (await get(stub, "properties")).strip("()").split() == ["temp", "setpoint", "label"]
            assert await set_(stub, "setpoint", "22.5") == "22.5"
            assert await set_(stub, "label", "shelf 2") == "shelf 2"
            stream = stub.Listen(pb.ListenRequest(service="thermo", property="temp"))
            values = {(await next_event(stream)).value for _ in range(3)}
            stream.cancel()
            assert len(values) >= 2, "temp moves on the timer"
            with pytest.raises(grpc.aio.AioRpcError) as info:
                await set_(stub, "setpoint", "99")
            assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT  # ERR 3 (docs/device-spec.md §3.2)
            assert await refused(lambda: get(stub, "temp.gui")) == grpc.StatusCode.NOT_FOUND  # no model
            assert await refused(lambda: get(stub, "history")) == grpc.StatusCode.NOT_FOUND  # no binary
