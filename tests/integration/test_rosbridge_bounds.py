"""The rosbridge endpoint's bounds, against a real gateway process: a reader that stalls holds one
message and gets the latest value after it, never a backlog; one that reads nothing is dropped
after ``http.write_timeout``; idle WebSockets take the places of event streams, bounded by
``http.max_streams_per_client`` and ``http.max_streams`` (lowered here, so that a few hundred
connections prove the bound), and give them back when they close."""

from __future__ import annotations

import asyncio
import base64
import json
import socket
from collections.abc import AsyncIterator, Iterator

import aiohttp
import grpc
import pytest
from support.blobs import BLOBS_CONFIG, start_blobs
from support.bystander import get_p99, rss_mb
from support.gateway_process import GatewayProcess
from support.stalled_readers import close_readers, open_readers, set_repeatedly
from support.waiting import eventually, wait_until

from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

MIB = 1024 * 1024
VALUE = 2 * MIB
READERS = 16
RATE_HZ = 4.0
#: What a stalled rosbridge reader may hold of a value: its message (base64 in JSON, a third
#: more) encoded, and the transport's copy of what the socket did not take; and its socket buffers.
COPIES = 2 * 4 / 3
SOCKET_BUFFER = 0.5 * MIB
#: Memory the Sets themselves move, whatever the readers do (as for the other fronts' readers).
SLACK = 40 * MIB
BYSTANDER_P99_S = 1.0
WRITE_TIMEOUT_S = 2.0
#: The lowered bounds on places the idle-socket tests prove.
PER_CLIENT = 300
IN_ALL = 120


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GatewayProcess]:
    config = (
        BLOBS_CONFIG + f"[http]\nmax_streams_per_client = {READERS + 8}\nwrite_timeout = {WRITE_TIMEOUT_S}\n"
    )
    gw = start_blobs(tmp_path_factory.mktemp("rosbridge"), config, "--http", "127.0.0.1:0")
    yield gw
    gw.stop()


@pytest.fixture
async def stub(gateway: GatewayProcess) -> AsyncIterator[pb_grpc.PropertyServiceStub]:
    async with grpc.aio.insecure_channel(gateway.address) as channel:
        yield pb_grpc.PropertyServiceStub(channel)


def counter_of(message: dict[str, object]) -> int:
    """The count at the head of a ``blobs/picture`` value (tests/support/stalled_readers.payload)."""
    msg = message["msg"]
    assert isinstance(msg, dict)
    return int.from_bytes(base64.b64decode(msg["data"][:12])[:8], "big")


def read_frame(reader: socket.socket, buffered: bytearray) -> bytes:
    """The payload of the next WebSocket frame the gateway sent (a server's frames are unmasked)."""

    def need(count: int) -> bytes:
        while len(buffered) < count:
            chunk = reader.recv(1 << 20)
            assert chunk, "the gateway closed the connection"
            buffered.extend(chunk)
        taken = bytes(buffered[:count])
        del buffered[:count]
        return taken

    head = need(2)
    length = head[1] & 0x7F
    if length == 126:
        length = int.from_bytes(need(2), "big")
    elif length == 127:
        length = int.from_bytes(need(8), "big")
    return need(length)


async def test_a_reader_that_stalls_gets_the_latest_picture_not_a_backlog(
    gateway: GatewayProcess, stub: pb_grpc.PropertyServiceStub
) -> None:
    target = {"grpc_address": gateway.address, "http_address": gateway.http_address}
    [reader] = open_readers("rosbridge", 1, service="blobs", path="picture", **target)
    try:
        # Not read for 1.5 s (within the write timeout) while twelve pictures are set.
        sent = await set_repeatedly(stub, "blobs", "picture", size=VALUE, rate_hz=8, seconds=1.5)
        reader.settimeout(10)
        buffered = bytearray()
        while b"\r\n\r\n" not in buffered:
            buffered.extend(reader.recv(4096))
        head, _, rest = bytes(buffered).partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 101")
        buffered = bytearray(rest)
        counters = []
        while not counters or counters[-1] < sent:
            message = json.loads(read_frame(reader, buffered))
            assert message["op"] == "publish" and message["topic"] == "/blobs/picture"
            assert message["msg"]["format"] == "png"
            if message["msg"]["data"]:
                counters.append(counter_of(message))
    finally:
        close_readers([reader])
    # Fewer messages than Sets, in order, the last one last: what the reader missed while it
    # stalled was replaced by the latest picture, never queued.
    print(f"a stalled rosbridge reader got pictures {counters} of 1..{sent}")
    assert len(counters) < sent, counters
    assert counters == sorted(counters)


async def test_stalled_readers_hold_one_message_each_and_give_it_back_when_they_close(
    gateway: GatewayProcess, stub: pb_grpc.PropertyServiceStub
) -> None:
    await set_repeatedly(stub, "blobs", "picture", size=VALUE, rate_hz=RATE_HZ, seconds=1.5)
    await get_p99(stub, "blobs", "note", 20)
    before = rss_mb(gateway.proc.pid)
    target = {"grpc_address": gateway.address, "http_address": gateway.http_address}
    readers = open_readers("rosbridge", READERS, service="blobs", path="picture", **target)
    try:
        # Within the write timeout: the readers are stalled, not yet dropped.
        await set_repeatedly(stub, "blobs", "picture", size=VALUE, rate_hz=RATE_HZ, seconds=1.5)
        stalled = rss_mb(gateway.proc.pid)
        p99 = await get_p99(stub, "blobs", "note")
    finally:
        close_readers(readers)
    bound = (READERS * (COPIES * VALUE + SOCKET_BUFFER) + SLACK) / MIB
    print(
        f"rosbridge: RSS {before:.0f} -> {stalled:.0f} MB with {READERS} stalled readers"
        f" (bound +{bound:.0f} MB)"
    )
    assert stalled - before < bound, f"{READERS} stalled rosbridge readers took {stalled - before:.0f} MB"
    assert p99 < BYSTANDER_P99_S

    async def memory_came_back() -> bool:
        await set_repeatedly(stub, "blobs", "picture", size=VALUE, rate_hz=RATE_HZ, seconds=0.5)
        return rss_mb(gateway.proc.pid) - before < SLACK / MIB

    await eventually(memory_came_back, bool, within=15, what=f"the RSS of {before:.0f} MB again")


async def test_a_reader_that_reads_nothing_is_dropped_after_the_write_timeout(
    gateway: GatewayProcess, stub: pb_grpc.PropertyServiceStub
) -> None:
    target = {"grpc_address": gateway.address, "http_address": gateway.http_address}
    [reader] = open_readers("rosbridge", 1, service="blobs", path="picture", **target)
    try:
        await set_repeatedly(
            stub, "blobs", "picture", size=VALUE, rate_hz=RATE_HZ, seconds=WRITE_TIMEOUT_S + 2
        )
        reader.setblocking(False)

        def dropped() -> bool:
            try:
                while chunk := reader.recv(1 << 20):
                    del chunk
            except BlockingIOError:
                return False
            except ConnectionError:
                return True
            return True  # end of stream

        await wait_until(dropped, within=10, what="the gateway drops the reader")
    finally:
        close_readers([reader])
    assert "it read nothing for 2 s (http.write_timeout)" in gateway.output


@pytest.fixture
def capped(gateway_process) -> GatewayProcess:  # type: ignore[no-untyped-def]
    return gateway_process(
        f"""
        [http]
        max_streams_per_client = {PER_CLIENT}
        max_streams = {PER_CLIENT * 4}
        max_connections_per_address = {PER_CLIENT + 50}

        [[services]]
        name = "scout1"
        type = "sim-robot"
        """
    )


async def open_sockets(
    session: aiohttp.ClientSession, url: str, count: int
) -> list[aiohttp.ClientWebSocketResponse]:
    return list(await asyncio.gather(*(session.ws_connect(url) for _ in range(count))))


async def test_idle_websockets_from_one_client_are_bounded_by_max_streams_per_client(
    capped: GatewayProcess,
) -> None:
    url = f"ws://{capped.http_address}/rosbridge"
    before = rss_mb(capped.proc.pid)
    connector = aiohttp.TCPConnector(limit=0)
    async with aiohttp.ClientSession(connector=connector) as session:
        sockets = await open_sockets(session, url, PER_CLIENT)
        held = rss_mb(capped.proc.pid)
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await session.ws_connect(url)
        assert refused.value.status == 429
        # An event stream shares the same places: refused too.
        async with session.get(f"http://{capped.http_address}/api/v1/events?sel=scout1/location") as sse:
            assert sse.status == 429
            assert "max_streams_per_client" in (await sse.json())["error"]["message"]
        # Every idle socket still answers.
        await sockets[-1].send_json({"op": "call_service", "id": "c", "service": "/scout1/speed"})
        answer = await sockets[-1].receive_json(timeout=10)
        assert answer["values"] == {"value": "0.5", "data": 0.5}
        for ws in sockets[:10]:
            await ws.close()
        again = await session.ws_connect(url)
        await again.close()
        for ws in sockets[10:]:
            await ws.close()
    print(f"{PER_CLIENT} idle rosbridge sockets: RSS {before:.0f} -> {held:.0f} MB")


async def test_idle_websockets_are_bounded_in_all_by_max_streams(gateway_process) -> None:  # type: ignore[no-untyped-def]
    gw = gateway_process(
        f"""
        [http]
        max_streams = {IN_ALL}
        max_streams_per_client = {IN_ALL * 2}
        """
    )
    url = f"ws://{gw.http_address}/rosbridge"
    async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(limit=0)) as session:
        sockets = await open_sockets(session, url, IN_ALL)
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await session.ws_connect(url)
        assert refused.value.status == 503
        for ws in sockets:
            await ws.close()
        again = await eventually(
            lambda: session.ws_connect(url), what="a place again", retry_on=(aiohttp.WSServerHandshakeError,)
        )
        await again.close()


def test_the_stalled_reader_speaks_the_websocket_protocol(gateway: GatewayProcess) -> None:
    """The raw reader's bytes are a real upgrade and subscribe: read, it gets a publish."""
    target = {"grpc_address": gateway.address, "http_address": gateway.http_address}
    [reader] = open_readers("rosbridge", 1, service="blobs", path="note", **target)
    try:
        reader.settimeout(10)
        received = b""
        while b'"op":"publish"' not in received:
            chunk = reader.recv(65536)
            assert chunk, received
            received += chunk
        assert received.startswith(b"HTTP/1.1 101")
        _, _, frames = received.partition(b"\r\n\r\n")
        assert frames[0] == 0x81  # a text frame
        length = frames[1]
        assert json.loads(frames[2 : 2 + length]) == {
            "op": "publish",
            "topic": "/blobs/note",
            "msg": {"data": ""},
        }
    finally:
        reader.close()
