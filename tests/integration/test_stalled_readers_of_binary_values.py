"""Readers that never read a large binary value: on a live image (``/stream``), an event stream
and a gRPC Listen, each holds at most one value and its socket's buffer, all of them together no
more than ``limits.max_pending_binary``, and the gateway's memory comes back when they close,
while a bystander's Get keeps answering. The readers are raw sockets with a tiny receive buffer
(tests/support/stalled_readers.py) against a real gateway process."""

from __future__ import annotations

import asyncio
import base64
import itertools
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from pathlib import Path

import aiohttp
import grpc
import pytest
from support.blobs import BLOBS_CONFIG, start_blobs
from support.bystander import get_p99, rss_mb
from support.gateway_process import GatewayProcess
from support.multipart import PartReader, boundary_of
from support.sse import SseReader
from support.stalled_readers import close_readers, open_readers, payload, set_repeatedly
from support.waiting import eventually

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

MIB = 1024 * 1024
#: A camera frame of a few megabytes, Set four times a second while the readers stall.
VALUE = 2 * MIB
READERS = 16
RATE_HZ = 4.0
#: The copies of a value a stalled reader may hold: a live image none of its own (it writes the
#: value every reader shares), an event stream its base64 (a third more), a gRPC Listen its
#: message, grpc's copy of it and the message before still in grpc's socket buffer. Counted as one
#: whole value at the least.
COPIES = {"stream": 1.0, "sse": 4 / 3, "grpc": 3.0}
#: What a socket holds beyond the value: the transport's buffer and the kernel's send buffer.
SOCKET_BUFFER = 0.5 * MIB
#: Memory the Sets themselves move (each value in the request, the property and its encodings,
#: and what the allocator keeps of them), whatever the readers do.
SLACK = 40 * MIB
#: A bystander's Get while the readers stall: generous, on a shared machine.
BYSTANDER_P99_S = 1.0


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GatewayProcess]:
    config = BLOBS_CONFIG + f"[http]\nmax_streams_per_client = {READERS + 8}\n"
    gw = start_blobs(tmp_path_factory.mktemp("stalled"), config, "--http", "127.0.0.1:0")
    yield gw
    gw.stop()


def target(gw: GatewayProcess) -> dict[str, str]:
    """Where the readers go: the gateway's ports and its ``blobs/picture``."""
    return {
        "grpc_address": gw.address,
        "http_address": gw.http_address,
        "service": "blobs",
        "path": "picture",
    }


@pytest.fixture
async def stub(gateway: GatewayProcess) -> AsyncIterator[pb_grpc.PropertyServiceStub]:
    async with grpc.aio.insecure_channel(gateway.address) as channel:
        yield pb_grpc.PropertyServiceStub(channel)


@pytest.mark.parametrize("kind", ["stream", "sse", "grpc"])
async def test_stalled_readers_hold_one_value_each_and_give_it_back_when_they_close(
    gateway: GatewayProcess, stub: pb_grpc.PropertyServiceStub, kind: str
) -> None:
    await set_repeatedly(
        stub, "blobs", "picture", size=VALUE, rate_hz=RATE_HZ, seconds=1.5
    )  # the allocator warmed up
    await get_p99(stub, "blobs", "note", 20)
    before = rss_mb(gateway.proc.pid)
    readers = open_readers(kind, READERS, **target(gateway))
    try:
        await set_repeatedly(stub, "blobs", "picture", size=VALUE, rate_hz=RATE_HZ, seconds=3.0)
        stalled = rss_mb(gateway.proc.pid)
        p99 = await get_p99(stub, "blobs", "note")
    finally:
        close_readers(readers)
    bound = (READERS * (COPIES[kind] * VALUE + SOCKET_BUFFER) + SLACK) / MIB
    print(
        f"{kind}: RSS {before:.0f} -> {stalled:.0f} MB with {READERS} stalled readers (bound +{bound:.0f} MB)"
    )
    assert stalled - before < bound, f"{READERS} stalled {kind} readers took {stalled - before:.0f} MB"
    assert p99 < BYSTANDER_P99_S

    async def memory_came_back() -> bool:
        await set_repeatedly(stub, "blobs", "picture", size=VALUE, rate_hz=RATE_HZ, seconds=0.5)
        return rss_mb(gateway.proc.pid) - before < SLACK / MIB

    await eventually(memory_came_back, bool, within=15, what=f"the RSS of {before:.0f} MB again")
    print(f"{kind}: RSS {rss_mb(gateway.proc.pid):.0f} MB after they closed")


async def refused_over_grpc(stub: pb_grpc.PropertyServiceStub, count: int) -> grpc.aio.AioRpcError | None:
    """Set a new picture (the stalled readers' next value waits for them), then Listen once: the
    refusal, or None when the Listen was served (the readers may not have begun listening yet)."""
    await stub.Set(pb.SetRequest(service="blobs", property="picture", data=payload(VALUE, count)), timeout=10)
    listen = stub.Listen(pb.ListenRequest(service="blobs", property="picture"), timeout=10)
    try:
        async for _ in listen:
            listen.cancel()  # served: not refused
            return None
    except grpc.aio.AioRpcError as refused:
        if refused.code() == grpc.StatusCode.RESOURCE_EXHAUSTED:
            return refused
        if refused.code() == grpc.StatusCode.CANCELLED:
            return None
        raise
    return None


def refusal_prober(stub: pb_grpc.PropertyServiceStub) -> Callable[[], Awaitable[grpc.aio.AioRpcError | None]]:
    """A probe for ``eventually`` that Sets a different picture each time it is tried."""
    counts = itertools.count(3)

    async def probe() -> grpc.aio.AioRpcError | None:
        return await refused_over_grpc(stub, next(counts))

    return probe


@pytest.fixture
def small_budget(tmp_path: Path) -> Iterator[GatewayProcess]:
    """A gateway whose budget holds two stalled gRPC readers of VALUE (three copies each) and not a
    whole value more."""
    config = BLOBS_CONFIG + f"[limits]\nmax_pending_binary = {int(6.5 * VALUE)}\n"
    gw = start_blobs(tmp_path, config, "--http", "127.0.0.1:0")
    yield gw
    gw.stop()


async def test_readers_past_the_budget_are_ended_with_resource_exhausted_until_the_stalled_ones_close(
    small_budget: GatewayProcess,
) -> None:
    gw = small_budget
    async with (
        grpc.aio.insecure_channel(gw.address) as channel,
        aiohttp.ClientSession(f"http://{gw.http_address}") as http,
    ):
        stub = pb_grpc.PropertyServiceStub(channel)
        await stub.Set(pb.SetRequest(service="blobs", property="picture", data=payload(VALUE, 1)), timeout=10)
        stalled = open_readers("grpc", 2, **target(gw))
        try:
            # The first value goes to their sockets' buffers, the second waits for them: two
            # stalled readers hold 6 values' worth, and a third reader's value does not fit.
            refusal = await eventually(refusal_prober(stub), bool, within=20)
            assert refusal is not None and "limits.max_pending_binary" in (refusal.details() or "")
            async with http.get("/api/v1/events", params={"sel": "blobs/picture"}) as response:
                error = await SseReader(response).until("error")
            assert error.data["code"] == "RESOURCE_EXHAUSTED", error
            assert "limits.max_pending_binary" in error.data["message"]
            async with http.get("/api/v1/services/blobs/properties/picture/stream") as response:
                # The part that does not fit is never begun: the body ends at once.
                parts = PartReader(response.content, boundary_of(response.headers["Content-Type"]))
                assert await parts.next() is None
            # A small value still goes to everyone: only large ones count.
            await stub.Set(pb.SetRequest(service="blobs", property="small", data=b"tiny"), timeout=10)
            async for answer in stub.Listen(pb.ListenRequest(service="blobs", property="small"), timeout=10):
                assert answer.events[0].data == b"tiny"
                break
        finally:
            close_readers(stalled)

        async def served_again() -> bool:
            async for answer in stub.Listen(
                pb.ListenRequest(service="blobs", property="picture"), timeout=10
            ):
                return len(answer.events[0].data) == VALUE
            return False

        await eventually(served_again, bool, within=10)
        assert gw.proc.poll() is None
        assert "Traceback" not in gw.output


async def listen_in_a_session(stub: pb_grpc.PropertyServiceStub, count: int) -> dict[int, pb.Reply] | None:
    """Set a new picture (the stalled readers' next value waits for them), then, in one Session, a
    Listen (id 1) and, once it is answered, a Get (id 2): both replies when the Listen was refused,
    None when it was served (the readers' values had left for their sockets meanwhile)."""
    await stub.Set(pb.SetRequest(service="blobs", property="picture", data=payload(VALUE, count)), timeout=10)
    requests: asyncio.Queue[pb.SessionRequest | None] = asyncio.Queue()

    async def sent() -> AsyncIterator[pb.SessionRequest]:
        while (message := await requests.get()) is not None:
            yield message

    session = stub.Session(sent(), timeout=10)
    listen = pb.ListenRequest(service="blobs", property="picture")
    get = pb.GetRequest(service="blobs", property="small")
    await requests.put(pb.SessionRequest(requests=[pb.Request(id=1, listen=listen)]))
    replies: dict[int, pb.Reply] = {}
    try:
        async for message in session:
            replies.update((reply.id, reply) for reply in message.replies)
            if 1 in replies and replies[1].status.code == 0:
                return None  # served: not refused
            if 1 in replies and 2 not in replies:
                await requests.put(pb.SessionRequest(requests=[pb.Request(id=2, get=get)]))
            if 2 in replies:
                return replies
    finally:
        await requests.put(None)
        session.cancel()
    return None


async def test_listens_in_a_session_count_in_the_budget_and_one_past_it_ends_alone(
    small_budget: GatewayProcess,
) -> None:
    gw = small_budget
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        await stub.Set(pb.SetRequest(service="blobs", property="picture", data=payload(VALUE, 1)), timeout=10)
        await stub.Set(pb.SetRequest(service="blobs", property="small", data=b"tiny"), timeout=10)
        # Two Sessions whose Listen never reads take the budget as two stalled gRPC Listens do.
        stalled = open_readers("session", 2, **target(gw))
        try:
            # A Listen in a Session is ended with the refusal; the Session goes on answering.
            counts = itertools.count(3)
            replies = await eventually(
                lambda: listen_in_a_session(stub, next(counts)),
                lambda answer: answer is not None,
                within=20,
                what="a Listen in a Session refused while two stalled Sessions hold the budget",
            )
            assert replies is not None
            assert replies[1].status.code == grpc.StatusCode.RESOURCE_EXHAUSTED.value[0], replies[1]
            assert "limits.max_pending_binary" in replies[1].status.message
            assert replies[2].get.data == b"tiny", replies[2]
        finally:
            close_readers(stalled)

        async def served_again() -> bool:
            async for answer in stub.Listen(
                pb.ListenRequest(service="blobs", property="picture"), timeout=10
            ):
                return len(answer.events[0].data) == VALUE
            return False

        await eventually(served_again, bool, within=10)
        assert "Traceback" not in gw.output


async def test_a_reader_that_keeps_up_gets_every_byte_of_a_large_value(gateway: GatewayProcess) -> None:
    """The slices a large value is written in make up the value: on a live image, in an event stream."""
    async with (
        grpc.aio.insecure_channel(gateway.address) as channel,
        aiohttp.ClientSession(f"http://{gateway.http_address}") as http,
    ):
        stub = pb_grpc.PropertyServiceStub(channel)
        value = payload(VALUE + 12345, 7)
        await stub.Set(pb.SetRequest(service="blobs", property="picture", data=value), timeout=10)
        async with http.get("/api/v1/services/blobs/properties/picture/stream") as response:
            parts = PartReader(response.content, boundary_of(response.headers["Content-Type"]))
            part = await parts.next()
            assert part is not None and part.body == value
        # Base64 of at most 512 KiB a line: what aiohttp's reader takes.
        value = payload(300_007, 8)
        await stub.Set(pb.SetRequest(service="blobs", property="picture", data=value), timeout=10)
        async with http.get("/api/v1/events", params={"sel": "blobs/picture"}) as response:
            message = await SseReader(response).until("value")
        assert base64.b64decode(message.data["data"]) == value
