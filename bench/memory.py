"""Part (d): server memory per idle Listen stream.

On a freshly started server: open the channels (each its own TCP connection)
and one Listen stream on each, so that connection set-up and first-use
allocations are paid; read the server's RSS. Then open ``streams`` more
Listen streams on one property, spread evenly over the channels, wait until
each has read its ``sync`` marker (so the server holds every one of them),
let the server settle, and read RSS again. Per-stream memory is the
difference divided by ``streams``. Nothing is set while the streams are
open: they are idle.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

import grpc

from bench.listen import CHANNEL_OPTIONS
from bench.measure import STREAM_END, read_until_sync
from bench.servers import ServerProcess
from bench.target import SERVICE, VALUE_PROPERTY
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

SETTLE_S = 1.0
#: Streams opened together. When about 1,500 arrive at once, grpc core
#: cancels some before the server handles them (its queue of pending calls
#: is bounded, see ``grpc.server_max_pending_requests``), so streams are
#: opened in waves.
WAVE = 200


@dataclass
class MemoryResult:
    """What part (d) measured on one server."""

    streams: int
    channels: int
    #: "streams": one Listen RPC each; "session": Listen requests inside
    #: Session streams, one Session a channel.
    how: str = "streams"
    opened: int = 0
    rss_start: int = 0
    rss_before: int = 0
    rss_after: int = 0
    rss_closed: int = 0
    open_s: float = 0.0

    @property
    def per_stream_kib(self) -> float:
        return (self.rss_after - self.rss_before) / max(self.opened, 1) / 1024

    def as_dict(self) -> dict[str, Any]:
        return {
            "how": self.how,
            "streams": self.streams,
            "channels": self.channels,
            "opened": self.opened,
            "rss_start_mib": round(self.rss_start / 2**20, 2),
            "rss_before_mib": round(self.rss_before / 2**20, 2),
            "rss_after_mib": round(self.rss_after / 2**20, 2),
            "rss_after_close_mib": round(self.rss_closed / 2**20, 2),
            "open_s": round(self.open_s, 3),
            "per_stream_kib": round(self.per_stream_kib, 2),
        }


async def _open(stub: pb_grpc.PropertyServiceStub, request: pb.ListenRequest) -> Any:
    call = stub.Listen(request)
    await read_until_sync(call)
    return call


async def _measure(
    server: ServerProcess,
    result: MemoryResult,
    time_limit: float,
    *,
    open_first: Callable[[list[pb_grpc.PropertyServiceStub]], Awaitable[None]],
    open_rest: Callable[[list[pb_grpc.PropertyServiceStub]], Awaitable[None]],
    held: list[Any],
) -> MemoryResult:
    """Read RSS before and after ``open_rest`` opens the ``result.streams`` idle Listens.

    ``open_first`` opens one Listen on each channel first, so that connection
    set-up is paid before the first reading. Both put what they open (calls
    or Sessions) into ``held``, which is cancelled before the channels close.
    """
    result.rss_start = server.rss_bytes()
    opened = [
        grpc.aio.insecure_channel(server.address, options=CHANNEL_OPTIONS) for _ in range(result.channels)
    ]
    stubs = [pb_grpc.PropertyServiceStub(channel) for channel in opened]
    try:
        async with asyncio.timeout(time_limit):
            await stubs[0].Set(pb.SetRequest(service=SERVICE, property=VALUE_PROPERTY, value="0"), timeout=10)
            await open_first(stubs)
            await asyncio.sleep(SETTLE_S)
            result.rss_before = server.rss_bytes()
            start = time.perf_counter()
            await open_rest(stubs)
            result.open_s = time.perf_counter() - start
            result.opened = result.streams
            await asyncio.sleep(SETTLE_S)
            result.rss_after = server.rss_bytes()
    finally:
        for call in held:
            call.cancel()
        for channel in opened:
            await channel.close(None)
    await asyncio.sleep(SETTLE_S)
    result.rss_closed = server.rss_bytes()
    server.check_alive()
    return result


async def run_memory(
    server: ServerProcess, *, streams: int, channels: int, time_limit: float
) -> MemoryResult:
    """Measure the server's RSS before and after opening ``streams`` idle Listen streams."""
    request = pb.ListenRequest(service=SERVICE, property=VALUE_PROPERTY)
    calls: list[Any] = []

    async def open_first(stubs: list[pb_grpc.PropertyServiceStub]) -> None:
        calls.extend(await asyncio.gather(*(_open(stub, request) for stub in stubs)))

    async def open_rest(stubs: list[pb_grpc.PropertyServiceStub]) -> None:
        for first in range(0, streams, WAVE):
            wave = range(first, min(first + WAVE, streams))
            calls.extend(await asyncio.gather(*(_open(stubs[n % channels], request) for n in wave)))

    result = MemoryResult(streams=streams, channels=channels)
    return await _measure(server, result, time_limit, open_first=open_first, open_rest=open_rest, held=calls)


async def _session_listens(session: Any, request: pb.ListenRequest, first_id: int, count: int) -> None:
    """Start ``count`` Listens in one SessionRequest and wait for the sync marker of each."""
    message = pb.SessionRequest()
    for number in range(first_id, first_id + count):
        message.requests.add(id=number, listen=request)
    await session.write(message)
    waiting = set(range(first_id, first_id + count))
    while waiting:
        response = await session.read()
        if response is STREAM_END:
            raise RuntimeError(f"a Session ended before its Listens were in sync: {await session.code()}")
        for reply in response.replies:
            if reply.status.code:
                raise RuntimeError(f"a Listen inside a Session failed: {reply.status.message}")
            if reply.listen.sync:
                waiting.discard(reply.id)


async def run_session_memory(
    server: ServerProcess, *, listens: int, channels: int, time_limit: float
) -> MemoryResult:
    """Like :func:`run_memory`, with the idle Listens carried as requests inside one Session per channel."""
    request = pb.ListenRequest(service=SERVICE, property=VALUE_PROPERTY)
    sessions: list[Any] = []

    async def open_first(stubs: list[pb_grpc.PropertyServiceStub]) -> None:
        sessions.extend(stub.Session() for stub in stubs)
        await asyncio.gather(*(_session_listens(session, request, 1, 1) for session in sessions))

    async def open_rest(stubs: list[pb_grpc.PropertyServiceStub]) -> None:
        share = [listens // channels + (n < listens % channels) for n in range(channels)]
        await asyncio.gather(
            *(
                _session_listens(session, request, 2, count)
                for session, count in zip(sessions, share, strict=True)
            )
        )

    result = MemoryResult(streams=listens, channels=channels, how="session")
    return await _measure(
        server, result, time_limit, open_first=open_first, open_rest=open_rest, held=sessions
    )
