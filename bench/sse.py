"""Part (k): Server-Sent-Events fan-out beside gRPC Listen fan-out, on one gateway, in the same run.

One gateway process serves the bench service on its gRPC port and its HTTP front end.
The same setter (one gRPC client, one unary Set at a time, the value being
``str(time.perf_counter_ns())``) drives, one after the other:

* ``grpc``: ``subscribers`` gRPC Listen streams on ``bench/value`` (part (c)'s one-by-one run);
* ``sse``: ``subscribers`` event streams (``GET /api/v1/events?sel=bench/value``), each on its
  own HTTP connection, as that many browser tabs would hold them (from several loopback
  addresses, 50 each, below the front end's ``max_streams_per_client``).

Then, on a fresh gateway, ``idle`` event streams are opened and left idle (below the front
end's ``max_streams``, 4,096): the gateway's RSS before and after, divided by the streams, is the
memory one idle SSE client costs (its connection, its request, its stream of the hub).

A subscriber subtracts the value from its own ``perf_counter_ns`` when an event arrives
(both run in this process: one clock). Events/s is what all subscribers read, first Set
to last event. The two ways take turns over the rounds (in the first round gRPC goes
first, in the second SSE), each on a fresh gateway, and each reports its best round.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import re
import time
from typing import Any

import aiohttp
import grpc

from bench.listen import (
    CALL_TIMEOUT,
    CHANNEL_OPTIONS,
    ListenResult,
    Run,
    count_delivery,
    measure_delivery,
    run_listen,
)
from bench.servers import ServerError, ServerProcess
from bench.target import SERVICE, VALUE_PROPERTY
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

ARGV = ["bench.gateway_server", "--listen", "127.0.0.1:0", "--http", "127.0.0.1:0"]
_HTTP = re.compile(r"HTTP front end and console on (https?://\S+/)")
_EVENT = b'data: {"service"'


def http_url(server: ServerProcess) -> str:
    """The HTTP front end's base URL, from the line the server printed before ``listening on``."""
    match = _HTTP.search(server.log_tail)
    if match is None:
        raise ServerError(f"{server.kind} printed no HTTP front end address:\n{server.log_tail}")
    return match.group(1)


class _SseSubscriber:
    """One event stream and what it has read."""

    def __init__(self, response: aiohttp.ClientResponse, run: Run) -> None:
        self.response = response
        self.run = run
        self.latest: dict[str, str] = {}
        self.events = 0
        self.conflated = 0
        self.last_ns = 0
        self.done = asyncio.Event()

    async def wait_sync(self) -> None:
        """Read the current value and the ``sync`` marker."""
        content = self.response.content
        while (line := await content.readline()) != b"event: sync\n":
            if not line:
                raise RuntimeError("an event stream ended before its sync marker")

    def check_done(self) -> None:
        final = self.run.final
        if self.events + self.conflated >= self.run.expected or (
            final is not None and all(self.latest.get(p) == v for p, v in final.items())
        ):
            self.done.set()

    async def consume(self) -> None:
        content = self.response.content
        samples = self.run.samples
        while line := await content.readline():
            if not line.startswith(_EVENT):
                continue
            now = time.perf_counter_ns()
            event = json.loads(line[6:])
            self.events += 1
            self.conflated += event["conflated"]
            self.latest[event["path"]] = event["value"]
            samples.append(now - int(event["value"]))
            self.last_ns = now
            self.check_done()


#: Event streams opened from one loopback address (below http.max_streams_per_client, 64).
STREAMS_PER_SOURCE = 50


async def sessions_from_sources(
    stack: contextlib.AsyncExitStack, streams: int
) -> list[aiohttp.ClientSession]:
    """HTTP sessions from several loopback addresses (127.0.0.10, .11, ...), enough for ``streams``
    event streams at STREAMS_PER_SOURCE each, as that many clients would open them."""
    sources = [f"127.0.0.{10 + n}" for n in range(math.ceil(streams / STREAMS_PER_SOURCE))]
    return [
        await stack.enter_async_context(
            aiohttp.ClientSession(
                connector=aiohttp.TCPConnector(limit=0, force_close=True, local_addr=(source, 0)),
                timeout=aiohttp.ClientTimeout(total=None),
            )
        )
        for source in sources
    ]


async def run_sse_listen(
    server: ServerProcess, base_url: str, *, subscribers: int, sets: int, set_rate: float, time_limit: float
) -> ListenResult:
    """Open ``subscribers`` event streams on ``bench/value``, make ``sets`` Sets over gRPC, count arrivals."""
    result = ListenResult(
        mode="sse",
        subscribers=subscribers,
        sets=sets,
        properties=1,
        burst=1,
        set_rate=set_rate,
        channels=subscribers,
    )
    run = Run(expected=sets)
    deadline = time.monotonic() + time_limit
    url = f"{base_url}api/v1/events?sel={SERVICE}/{VALUE_PROPERTY}"
    subs: list[_SseSubscriber] = []
    tasks: list[asyncio.Task[None]] = []
    first_set_ns = 0
    async with (
        contextlib.AsyncExitStack() as stack,
        grpc.aio.insecure_channel(server.address, options=CHANNEL_OPTIONS) as setter_channel,
    ):
        sessions = await sessions_from_sources(stack, subscribers)
        try:
            setter = pb_grpc.PropertyServiceStub(setter_channel)
            await setter.Set(
                pb.SetRequest(service=SERVICE, property=VALUE_PROPERTY, value="0"), timeout=CALL_TIMEOUT
            )
            async with asyncio.timeout(CALL_TIMEOUT * 3):
                responses = await asyncio.gather(
                    *(sessions[n % len(sessions)].get(url) for n in range(subscribers))
                )
                subs = [_SseSubscriber(response, run) for response in responses]
                await asyncio.gather(*(sub.wait_sync() for sub in subs))
            tasks = [asyncio.create_task(sub.consume()) for sub in subs]
            first_set_ns = await measure_delivery(
                server,
                setter,
                subs,
                run,
                result,
                properties=(VALUE_PROPERTY,),
                sets=sets,
                set_rate=set_rate,
                deadline=deadline,
            )
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            for sub in subs:
                sub.response.close()
    count_delivery(result, subs, run, first_set_ns)
    result.conflated = sum(sub.conflated for sub in subs)
    result.messages = result.events
    result.complete_subscribers = sum(sub.done.is_set() for sub in subs)
    server.check_alive()
    return result


#: Seconds the gateway gets to settle before its memory is read.
SETTLE_S = 1.0


async def idle_memory(streams: int) -> dict[str, Any]:
    """RSS of a fresh gateway before and after ``streams`` idle event streams; KiB per stream."""
    server = await ServerProcess.start("gateway with HTTP", ARGV)
    url = f"{http_url(server)}api/v1/events?sel={SERVICE}/{VALUE_PROPERTY}"
    responses: list[aiohttp.ClientResponse] = []
    try:
        async with contextlib.AsyncExitStack() as stack:
            sessions = await sessions_from_sources(stack, streams + 1)
            # One stream first: the first request's one-time allocations are not counted.
            first = await sessions[0].get(url)
            await _SseSubscriber(first, Run(expected=0)).wait_sync()
            await asyncio.sleep(SETTLE_S)
            before = server.rss_bytes()
            try:
                async with asyncio.timeout(CALL_TIMEOUT * 3):
                    responses = list(
                        await asyncio.gather(
                            *(sessions[(n + 1) % len(sessions)].get(url) for n in range(streams))
                        )
                    )
                    await asyncio.gather(*(_SseSubscriber(r, Run(expected=0)).wait_sync() for r in responses))
                await asyncio.sleep(SETTLE_S)
                after = server.rss_bytes()
            finally:
                for response in [first, *responses]:
                    response.close()
        server.check_alive()
    finally:
        await server.stop()
    return {
        "streams": streams,
        "rss_before_mib": round(before / 2**20, 2),
        "rss_after_mib": round(after / 2**20, 2),
        "per_stream_kib": round((after - before) / streams / 1024, 2),
    }


async def run_sse(
    *, subscribers: int, sets: int, set_rate: float, rounds: int, time_limit: float, idle: int = 250
) -> dict[str, Any]:
    """gRPC Listen and SSE fan-out on the same gateway, taking turns (the best round of each),
    then the memory of ``idle`` idle event streams on a fresh gateway."""
    best: dict[str, Any] = {}
    for number in range(rounds):
        server = await ServerProcess.start("gateway with HTTP", ARGV)
        try:
            base_url = http_url(server)
            ways = ["grpc", "sse"] if number % 2 == 0 else ["sse", "grpc"]
            for way in ways:
                if way == "grpc":
                    measured = await run_listen(
                        server,
                        mode="one-by-one",
                        properties=(VALUE_PROPERTY,),
                        subscribers=subscribers,
                        sets=sets,
                        channels=math.ceil(subscribers / 25),
                        set_rate=set_rate,
                        time_limit=time_limit,
                    )
                else:
                    measured = await run_sse_listen(
                        server,
                        base_url,
                        subscribers=subscribers,
                        sets=sets,
                        set_rate=set_rate,
                        time_limit=time_limit,
                    )
                data = measured.as_dict()
                if way not in best or data["events_per_s"] > best[way]["events_per_s"]:
                    best[way] = data
        finally:
            await server.stop()
    best["idle"] = await idle_memory(idle)
    return best
