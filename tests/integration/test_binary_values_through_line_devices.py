"""Binary values (line protocol 1.2) between gRPC clients and line devices, through a real gateway.

The gateway is a real process; the device is played by the test on a real TCP
socket or a real pty (:mod:`scripted_device`), so what crosses the line is
checked as the device saw it. A value goes both ways byte for byte: a device's
``\\=`` value reaches a gRPC client as ``data``, a gRPC Set with ``data`` reaches
the device as ``\\=`` and base64. Limits are counted on the encoded line, and a
1.1 device that does not know the form is named in a clear INVALID_ARGUMENT.
The Python device server and the gateway's own line listener serve a Python
service's binary properties in the same form.
"""

from __future__ import annotations

import asyncio
import base64
import os
import re
import subprocess
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import grpc
import pytest
from line_device_support import LineClient, tcp_device
from scripted_device import ScriptedDevice, pty_scripted, tcp_scripted
from support.blobs import Blobs
from support.gateway_process import GatewayProcess, StartGateway
from support.waiting import eventually

from gateway.engine.router import Router
from gateway.fronts.line.listener import LineListener
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.kernel.core import LocalService
from services.kernel.line_protocol import encode_value

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
WAIT = 10.0
OPTIONS = "{ timeout = 3.0, connect_timeout = 3.0, backoff_initial = 0.05, backoff_max = 0.3 }"
#: Every byte value, then random bytes: 30 kB, a small JPEG's size.
FRAME = bytes(range(256)) + os.urandom(30_000 - 256)


def greeting(maxline: int) -> str:
    return f"HELLO 1 name=cam type=camera push=1 maxline={maxline}"


@asynccontextmanager
async def device_on(transport: str, device: ScriptedDevice) -> AsyncIterator[str]:
    """``device`` on a real TCP socket or a real pty; yields the URL a registration names."""
    if transport == "tcp":
        async with tcp_scripted(device) as url:
            yield url
    else:
        device.greet_first = False  # a serial device greets when asked
        async with pty_scripted(device) as path:
            yield f"serial://{path}?baudrate=115200"


async def start_gateway(
    gateway_process: StartGateway, url: str, maxline: int | None = None
) -> GatewayProcess:
    if maxline is not None:
        url += f"{'&' if '?' in url else '?'}maxline={maxline}"
    config = f'[[services]]\nname = "cam"\nurl = "{url}"\noptions = {OPTIONS}\n'
    # Started from a thread: the device lives on this event loop and must answer while it starts.
    return await asyncio.to_thread(gateway_process, config)


def get_(
    stub: pb_grpc.PropertyServiceStub, prop: str
) -> grpc.aio.UnaryUnaryCall[pb.GetRequest, pb.GetResponse]:
    return stub.Get(pb.GetRequest(service="cam", property=prop), timeout=WAIT)


def set_(
    stub: pb_grpc.PropertyServiceStub, prop: str, value: str | bytes
) -> grpc.aio.UnaryUnaryCall[pb.SetRequest, pb.SetResponse]:
    """A Set as a client sends it: bytes in ``data``, text in ``value``."""
    request = pb.SetRequest(service="cam", property=prop)
    if isinstance(value, bytes):
        request.data = value
    else:
        request.value = value
    return stub.Set(request, timeout=WAIT)


async def connected(stub: pb_grpc.PropertyServiceStub) -> None:
    """Wait until the gateway has reached the device (UNAVAILABLE until then)."""
    await eventually(
        lambda: get_(stub, "note"),
        retry_on=(grpc.aio.AioRpcError,),
        within=WAIT,
        what="the gateway reached the device",
    )


async def refusal(call: object) -> grpc.aio.AioRpcError:
    with pytest.raises(grpc.aio.AioRpcError) as info:
        await call  # type: ignore[misc]
    return info.value


async def next_event(stream: grpc.aio.UnaryStreamCall[pb.ListenRequest, pb.ListenResponse]) -> pb.Event:
    async with asyncio.timeout(WAIT):
        while True:
            message = await stream.read()
            assert message is not grpc.aio.EOF, "the Listen stream ended"
            if message.events:
                return message.events[-1]


@pytest.mark.parametrize("transport", ["tcp", "serial"])
async def test_get_set_and_listen_carry_a_binary_value_byte_for_byte(
    gateway_process: StartGateway, transport: str
) -> None:
    device = ScriptedDevice(
        greeting(65536), {"frame": encode_value(FRAME), "note": "plain text", "properties": "(frame note)"}
    )
    async with device_on(transport, device) as url:
        gw = await start_gateway(gateway_process, url, maxline=65536)
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            await connected(stub)

            got = await get_(stub, "frame")
            assert got.HasField("data") and got.value == ""
            assert got.data == FRAME
            note = await get_(stub, "note")
            assert (note.value, note.HasField("data")) == ("plain text", False)

            # A Set with data: the device receives \= and the standard base64 of exactly those bytes.
            sent = os.urandom(20_000)
            reply = await set_(stub, "frame", sent)
            assert reply.HasField("data") and reply.data == sent
            (line,) = device.seen("SET frame")
            assert line.endswith(" SET frame \\=" + base64.b64encode(sent).decode())
            assert device.props["frame"] == "\\=" + base64.b64encode(sent).decode()

            # Listen: the current value first, then each change, empty bytes still binary.
            stream = stub.Listen(pb.ListenRequest(service="cam", property="frame"))
            first = await next_event(stream)
            assert first.HasField("data") and first.data == sent
            for value in (FRAME[::-1], b"", bytes([0, 10, 13, 92, 61, 255])):
                device.change("frame", value)
                event = await next_event(stream)
                assert event.HasField("data") and event.data == value and event.value == ""
            stream.cancel()


async def test_a_binary_value_over_the_line_limit_is_refused_clearly(gateway_process: StartGateway) -> None:
    # Both sides keep the default 1024 bytes: "#N SET frame \=" leaves room for about 750 bytes.
    device = ScriptedDevice(greeting(1024), {"frame": encode_value(b"x"), "note": "n"})
    async with tcp_scripted(device) as url:
        gw = await start_gateway(gateway_process, url)
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            await connected(stub)
            fits = os.urandom(700)
            reply = await set_(stub, "frame", fits)
            assert reply.data == fits

            # Too long for the device's maxline: refused in the gateway, nothing sent.
            error = await refusal(set_(stub, "frame", bytes(800)))
            assert error.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert "line too long" in error.details() and "the device takes 1024" in error.details()
            assert "a binary value of 800 bytes is 1068 characters of base64" in error.details()
            assert len(device.seen("SET frame")) == 1

            # Too long for the gateway's own limit: that call fails, naming the proxy option.
            device.change("frame", bytes(2000))
            error = await refusal(get_(stub, "frame"))
            assert error.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert "reply was too long" in error.details() and "maxline, now 1024" in error.details()
            # The connection carries on.
            note = await get_(stub, "note")
            assert note.value == "n"


async def test_a_1_1_device_that_refuses_the_binary_form_gives_invalid_argument_naming_it(
    gateway_process: StartGateway,
) -> None:
    device = ScriptedDevice(greeting(1024), {"label": "bench", "note": "n"}, binary=False)
    async with tcp_scripted(device) as url:
        gw = await start_gateway(gateway_process, url)
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            await connected(stub)
            error = await refusal(set_(stub, "label", b"\x00\x01"))
            assert error.code() == grpc.StatusCode.INVALID_ARGUMENT
            details = error.details()
            assert "device cam" in details and "does not take binary values for 'label'" in details
            assert "bad escape" in details
            assert device.props["label"] == "bench"
            # Text still works with it.
            reply = await set_(stub, "label", "shelf")
            assert reply.value == "shelf"


async def test_a_python_service_with_bytes_properties_served_as_a_line_device(
    gateway_process: StartGateway,
) -> None:
    # The test kit's Blobs service (tests/support/blobs.py) in a device process, behind the proxy:
    # the same bytes, the same model and the same refusals as the service has in a gateway.
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests")])}
    args = ("--service", "support.blobs:Blobs", "--name", "blobs", "--max-line", "1048576")
    with tcp_device(*args, env=env) as (host, port):
        gw = await start_gateway(gateway_process, f"tcp://{host}:{port}", maxline=1048576)
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            await connected(stub)
            picture = os.urandom(300_000)
            reply = await set_(stub, "picture", picture)
            assert reply.data == picture
            got = await get_(stub, "picture")
            assert got.HasField("data") and got.data == picture
            echo = await set_(stub, "echo", b"\x00abc\xff")
            assert echo.data == b"\xff" + b"cba\x00"
            # The device describes its binary properties with their media type and size limit.
            model = await stub.Describe(pb.DescribeRequest(service="cam"), timeout=WAIT)
            by_name = {p.name: p for p in model.properties}
            assert (by_name["picture"].type, by_name["picture"].media_type) == ("bytes", "image/png")
            assert by_name["small"].max_size == 16 and by_name["frame"].media_type == "image/jpeg"
            # A property with no limit of its own may carry what one line of 1 MiB holds as base64,
            # less the request around it: the model says so, not the 4 MiB of a gRPC message.
            fits = by_name["picture"].max_size
            assert 786_000 < fits < 1_048_576 * 3 // 4, fits
            most = await set_(stub, "picture", bytes(fits))
            assert most.data == bytes(fits)
            # The limit keeps room for the longest tag and a checksum: a kilobyte more never fits.
            over = await refusal(set_(stub, "picture", bytes(fits + 1024)))
            assert over.code() == grpc.StatusCode.RESOURCE_EXHAUSTED, over.details()
            # Text to a bytes property and bytes to a text property: the service's own refusals.
            wrong = await refusal(set_(stub, "note", b"x"))
            assert wrong.code() == grpc.StatusCode.INVALID_ARGUMENT
            large = await refusal(set_(stub, "small", bytes(17)))
            assert large.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "small" in large.details()
            # Listen to a changing binary value: each event's data is the frame the service rendered.
            await set_(stub, "frame_bytes", "5000")
            stream = stub.Listen(pb.ListenRequest(service="cam", property="frame"))
            await set_(stub, "stream", "true")
            seen: set[int] = set()
            while len(seen) < 3:
                event = await next_event(stream)
                if event.data:
                    assert len(event.data) == 5000
                    counter = int.from_bytes(event.data[:8], "big")
                    assert event.data[8:] == bytes([counter % 256]) * 4992
                    seen.add(counter)
            stream.cancel()


async def test_the_line_listener_serves_a_services_binary_values_as_base64_lines() -> None:
    # The gateway's own line listener is a device for every service behind it: a microcontroller
    # that asks the gateway reads and writes a binary property in the \= form.
    router = Router()
    blobs = LocalService(Blobs())
    await blobs.start()
    router.add("blobs", blobs)
    listener = LineListener(router)
    host, port = await listener.start("127.0.0.1", 0)
    try:
        c = await LineClient.tcp(host, port)
        await c.line()  # the greeting
        await c.send("#1 SET blobs.small \\=AAEC/w==", "#2 GET blobs.small", "#3 LISTEN blobs.small")
        assert await c.lines(3) == ["#1 OK \\=AAEC/w==", "#2 OK \\=AAEC/w==", "#3 OK \\=AAEC/w=="]
        await blobs.set("small", b"")
        assert await c.line() == "EVENT blobs.small \\="
        await blobs.set("small", b"\xfb\xff")
        assert await c.line() == "EVENT blobs.small \\=+/8="
        await c.send("#4 SET blobs.small \\=QUJ$")
        reply = await c.line()
        assert reply.startswith("#4 ERR 3 bad base64 after '\\\\=': '$' at position 3"), reply
        await c.send("#5 SET blobs.note \\=AA==")  # bytes to a text property: the service refuses
        assert (await c.line()).startswith("#5 ERR 3 ")
        await c.send("#6 SET blobs.small \\=" + base64.b64encode(bytes(17)).decode())
        assert (await c.line()).startswith("#6 ERR 8 ")  # over the property's max_size of 16
        # A value whose line would pass the listener's 1024 bytes is refused, not cut.
        await blobs.set("picture", os.urandom(2000))
        await c.send("#7 GET blobs.picture")
        reply = await c.line()
        assert reply.startswith("#7 ERR 8 cannot send the reply: line too long"), reply
        assert await blobs.get("small") == b"\xfb\xff"
        await c.close()
    finally:
        await listener.aclose()
        await blobs.aclose()


def test_the_binary_value_benchmark_runs_and_reads_every_value_back() -> None:
    # A smoke run of `python -m bench.line_binary --quick`: every size measured, each Get's bytes
    # compared with the file's (the benchmark stops on a difference); nothing about speed.
    done = subprocess.run(
        [sys.executable, "-m", "bench.line_binary", "--quick"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    rows = re.findall(r"^\s*([\d,]+)\s+([\d,]+)\s+\d+\s+[\d,]+\s+[\d.]+", done.stdout, re.M)
    assert [size for size, _ in rows] == ["750", "40,000", "1,000,000"], done.stdout
    assert [line for _, line in rows] == ["1,016", "53,352", "1,333,352"], done.stdout
