"""Part (a): unary Get latency and throughput with a fixed number of calls in flight."""

from __future__ import annotations

import asyncio
import time
from dataclasses import dataclass
from typing import Any

import grpc

from bench.measure import CallRun, Latencies, window
from bench.servers import Metadata, ServerProcess, open_channel
from bench.target import SERVICE, VALUE_PROPERTY
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

#: Deadline of one call; a call slower than this counts as an error.
CALL_TIMEOUT = 10.0


@dataclass
class UnaryResult(CallRun):
    """What part (a) measured on one server."""

    calls: int
    inflight: int

    def as_dict(self) -> dict[str, Any]:
        return {
            "calls": self.calls,
            "inflight": self.inflight,
            "done": self.done,
            "errors": self.errors,
            "complete": self.complete,
            "throughput_per_s": round(self.throughput, 1),
            "server_cpu_us_per_call": round(1e6 * self.window.server_cpu_s / max(self.done, 1), 1),
            "latency": self.latency.as_dict(),
            "window": self.window.as_dict(),
        }


async def _drive(  # noqa: PLR0917
    stub: pb_grpc.PropertyServiceStub,
    request: pb.GetRequest,
    calls: int,
    inflight: int,
    deadline: float,
    metadata: Metadata = (),
) -> tuple[list[int], int, bool]:
    """Make ``calls`` Gets, ``inflight`` at a time; return latencies (ns), errors, whether all were made."""
    remaining = calls
    errors = 0
    samples: list[int] = []

    async def worker() -> None:
        nonlocal remaining, errors
        while remaining > 0 and time.monotonic() < deadline:
            remaining -= 1
            start = time.perf_counter_ns()
            try:
                await stub.Get(request, timeout=CALL_TIMEOUT, metadata=metadata)
            except grpc.aio.AioRpcError:
                errors += 1
                continue
            samples.append(time.perf_counter_ns() - start)

    await asyncio.gather(*(worker() for _ in range(inflight)))
    return samples, errors, remaining == 0


async def run_unary(
    server: ServerProcess,
    *,
    calls: int,
    inflight: int,
    warmup: int,
    time_limit: float,
    credentials: grpc.ChannelCredentials | None = None,
    metadata: Metadata = (),
) -> UnaryResult:
    """Warm up, then make ``calls`` unary Gets of one property with ``inflight`` calls in flight.

    With ``credentials`` the channel is TLS; ``metadata`` goes with every call (a bearer token).
    """
    result = UnaryResult(calls=calls, inflight=inflight)
    request = pb.GetRequest(service=SERVICE, property=VALUE_PROPERTY)
    async with open_channel(server.address, credentials) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        await stub.Set(
            pb.SetRequest(service=SERVICE, property=VALUE_PROPERTY, value="0"),
            timeout=CALL_TIMEOUT,
            metadata=metadata,
        )
        await _drive(stub, request, warmup, inflight, time.monotonic() + time_limit, metadata)
        with window(server) as result.window:
            samples, result.errors, result.complete = await _drive(
                stub, request, calls, inflight, time.monotonic() + time_limit, metadata
            )
    result.done = len(samples) + result.errors
    result.latency = Latencies.of(samples)
    server.check_alive()
    return result
