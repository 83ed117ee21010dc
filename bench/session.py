"""Part (b): the same Gets over the bidirectional Session RPC, many requests per message.

One Session stream; the writer packs ``batch`` Get requests into each
SessionRequest (as a client library batching what its callers have ready
would) and keeps at most ``window`` batches unanswered. A batch's latency is
from writing its message to reading the reply of each of its requests.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from typing import Any

import grpc

from bench.measure import STREAM_END, CallRun, Latencies, window
from bench.servers import Metadata, ServerProcess, open_channel
from bench.target import SERVICE, VALUE_PROPERTY
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc


@dataclass
class SessionResult(CallRun):
    """What part (b) measured on one server (a call here is one Get inside the Session)."""

    gets: int
    batch: int
    window_batches: int
    messages_in: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "gets": self.gets,
            "batch": self.batch,
            "window_batches": self.window_batches,
            "done": self.done,
            "errors": self.errors,
            "complete": self.complete,
            "replies_per_response": round(self.done / max(self.messages_in, 1), 2),
            "throughput_per_s": round(self.throughput, 1),
            "server_cpu_us_per_get": round(1e6 * self.window.server_cpu_s / max(self.done, 1), 2),
            "latency": self.latency.as_dict(),
            "window": self.window.as_dict(),
        }


async def _drive(  # noqa: PLR0917
    stub: pb_grpc.PropertyServiceStub,
    gets: int,
    batch: int,
    window_batches: int,
    deadline: float,
    metadata: Metadata = (),
) -> tuple[list[int], int, int, int]:
    """Make ``gets`` Gets over one Session; return latencies (ns), replies, errors, response messages."""
    call = stub.Session(metadata=metadata)
    credit = asyncio.Semaphore(window_batches)
    sent_at: dict[int, int] = {}
    waiting: dict[int, int] = {}
    samples: list[int] = []
    replies = errors = messages = 0
    batches = -(-gets // batch)

    async def writer() -> None:
        next_id = 0
        for number in range(batches):
            await credit.acquire()
            if time.monotonic() >= deadline:
                break
            size = min(batch, gets - number * batch)
            message = pb.SessionRequest()
            for _ in range(size):
                next_id += 1
                message.requests.add(id=next_id, get=pb.GetRequest(service=SERVICE, property=VALUE_PROPERTY))
            waiting[number] = size
            sent_at[number] = time.perf_counter_ns()
            await call.write(message)
        await call.done_writing()

    async def reader() -> None:
        nonlocal replies, errors, messages
        while replies < gets:
            response = await call.read()
            if response is STREAM_END:
                return
            messages += 1
            now = time.perf_counter_ns()
            for reply in response.replies:
                replies += 1
                if reply.status.code:
                    errors += 1
                number = (reply.id - 1) // batch
                samples.append(now - sent_at[number])
                waiting[number] -= 1
                if not waiting[number]:
                    del waiting[number]
                    credit.release()

    writing = asyncio.create_task(writer())
    try:
        async with asyncio.timeout(max(deadline - time.monotonic(), 0.0)):
            await asyncio.gather(writing, reader())
    except TimeoutError:
        pass
    finally:
        writing.cancel()
        call.cancel()
    return samples, replies, errors, messages


async def run_session(
    server: ServerProcess,
    *,
    gets: int,
    batch: int,
    window_batches: int,
    warmup: int,
    time_limit: float,
    credentials: grpc.ChannelCredentials | None = None,
    metadata: Metadata = (),
) -> SessionResult:
    """Warm up, then make ``gets`` Gets over one Session stream, ``batch`` requests per message.

    With ``credentials`` the channel is TLS; ``metadata`` goes with the Session call (a bearer token).
    """
    result = SessionResult(gets=gets, batch=batch, window_batches=window_batches)
    async with open_channel(server.address, credentials) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        await stub.Set(
            pb.SetRequest(service=SERVICE, property=VALUE_PROPERTY, value="0"), timeout=10, metadata=metadata
        )
        await _drive(stub, warmup, batch, window_batches, time.monotonic() + time_limit, metadata)
        with window(server) as result.window:
            samples, result.done, result.errors, result.messages_in = await _drive(
                stub, gets, batch, window_batches, time.monotonic() + time_limit, metadata
            )
    result.complete = result.done == gets
    result.latency = Latencies.of(samples)
    server.check_alive()
    return result
