"""Part (q): Gets one at a time, unary and over a bidirectional stream, beside grpc.aio's own floor.

With one call in flight a Get's latency is the whole cost of a round trip,
so this is where the gateway's work per call shows most. Each way makes
``calls`` Gets of ``bench/value``, the next one when the last has been
answered, on one channel:

* ``unary``: unary Gets;
* ``session``: Gets over one Session stream, one request per message (the
  shape a client that has one Get ready at a time sends);
* ``echo`` (the bare server only): the same messages over the bare server's
  ``/bench.Floor/Echo`` (:data:`bench.baseline.ECHO_METHOD`), a stream that
  answers each request with its id and the stored value and does nothing
  else. That is the floor a Session Get is judged against: p50 within 5 %
  of it, p99 within 2 × its p50.

Latency is from writing the request to reading its reply, client side.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from bench.baseline import ECHO_METHOD
from bench.measure import STREAM_END, CallRun, Latencies, window
from bench.servers import ServerProcess, open_channel
from bench.target import SERVICE, VALUE_PROPERTY
from bench.unary import CALL_TIMEOUT
from bench.unary import _drive as drive_unary
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

#: Ways measured on every server; the bare server adds ``echo``.
WAYS = ("unary", "session")
FLOOR_WAY = "echo"


@dataclass
class SequentialResult:
    """What part (q) measured on one server: one :class:`CallRun` per way."""

    calls: int
    ways: dict[str, CallRun] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        ways: dict[str, dict[str, Any]] = {
            name: {
                "done": run.done,
                "errors": run.errors,
                "complete": run.complete,
                "throughput_per_s": round(run.throughput, 1),
                "server_cpu_us_per_call": round(1e6 * run.window.server_cpu_s / max(run.done, 1), 1),
                "latency": run.latency.as_dict(),
                "window": run.window.as_dict(),
            }
            for name, run in self.ways.items()
        }
        return {
            "calls": self.calls,
            "complete": all(run.complete for run in self.ways.values()),
            # The figure that picks the best round: the floor's rate (one over its mean latency) on the bare
            # server, so that the floor is its least disturbed round; the Session's on the gateway.
            "throughput_per_s": ways.get(FLOOR_WAY, ways["session"])["throughput_per_s"],
            # Each way's p50 at the top, so that every round's figure is kept (the unary target is per round).
            **{f"{name}_p50_us": figures["latency"]["p50_us"] for name, figures in ways.items()},
            "ways": ways,
        }


def _get_message(number: int) -> pb.SessionRequest:
    message = pb.SessionRequest()
    message.requests.add(id=number, get=pb.GetRequest(service=SERVICE, property=VALUE_PROPERTY))
    return message


async def _drive_stream(call: Any, calls: int, deadline: float) -> tuple[list[int], int, bool]:
    """One Get a message over ``call``, the next when its reply is read; latencies (ns), errors, all made."""
    samples: list[int] = []
    errors = 0
    for number in range(1, calls + 1):
        if time.monotonic() >= deadline:
            return samples, errors, False
        message = _get_message(number)
        start = time.perf_counter_ns()
        await call.write(message)
        while True:
            response = await call.read()
            if response is STREAM_END:
                raise RuntimeError(f"the stream ended after {number - 1} Gets: {await call.code()}")
            reply = next((r for r in response.replies if r.id == number), None)
            if reply is not None:
                break
        elapsed = time.perf_counter_ns() - start
        if reply.status.code:
            errors += 1
        else:
            samples.append(elapsed)
    return samples, errors, True


async def _stream_way(
    server: ServerProcess, open_call: Callable[..., Any], calls: int, warmup: int, deadline: float
) -> CallRun:
    run = CallRun()
    call = open_call()
    try:
        await _drive_stream(call, warmup, deadline)
        with window(server) as run.window:
            samples, run.errors, run.complete = await _drive_stream(call, calls, deadline)
        await call.done_writing()
    finally:
        call.cancel()
    run.done = len(samples) + run.errors
    run.latency = Latencies.of(samples)
    return run


async def run_sequential(
    server: ServerProcess, *, calls: int, warmup: int, time_limit: float, floor: bool
) -> SequentialResult:
    """Make ``calls`` Gets one at a time each way (and over the echo floor when ``floor``)."""
    result = SequentialResult(calls=calls)
    ways = (*WAYS, FLOOR_WAY) if floor else WAYS
    share = time_limit / len(ways)
    async with open_channel(server.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        await stub.Set(
            pb.SetRequest(service=SERVICE, property=VALUE_PROPERTY, value="0"), timeout=CALL_TIMEOUT
        )
        echo = channel.stream_stream(
            ECHO_METHOD,
            request_serializer=pb.SessionRequest.SerializeToString,
            response_deserializer=pb.SessionResponse.FromString,
        )
        for way in ways:
            deadline = time.monotonic() + share
            if way == "unary":
                request = pb.GetRequest(service=SERVICE, property=VALUE_PROPERTY)
                run = CallRun()
                await drive_unary(stub, request, warmup, 1, deadline)
                with window(server) as run.window:
                    samples, run.errors, run.complete = await drive_unary(stub, request, calls, 1, deadline)
                run.done = len(samples) + run.errors
                run.latency = Latencies.of(samples)
            elif way == "session":
                run = await _stream_way(server, stub.Session, calls, warmup, deadline)
            else:
                run = await _stream_way(server, echo, calls, warmup, deadline)
            result.ways[way] = run
    server.check_alive()
    return result
