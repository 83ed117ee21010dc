"""What every load loop records: wall time, CPU of both sides, latencies."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import grpc
import numpy as np

from bench.servers import ServerProcess

#: What ``read()`` of a streaming call returns once the stream has ended.
STREAM_END: object = grpc.aio.EOF  # type: ignore[attr-defined]


async def read_until_sync(call: Any) -> None:
    """Read a Listen stream's current values up to its ``sync`` marker; RuntimeError if it ends first."""
    while True:
        response = await call.read()
        if response is STREAM_END:
            raise RuntimeError(f"a Listen stream ended before its sync marker: {await call.code()}")
        if response.sync:
            return


@dataclass
class Window:
    """Wall and CPU time spent over one measured stretch of load."""

    wall_s: float = 0.0
    client_cpu_s: float = 0.0
    server_cpu_s: float = 0.0

    @property
    def client_busy(self) -> float:
        """Fraction of one core the load generator used."""
        return self.client_cpu_s / self.wall_s if self.wall_s else 0.0

    @property
    def server_busy(self) -> float:
        """Fraction of one core the server used."""
        return self.server_cpu_s / self.wall_s if self.wall_s else 0.0

    def as_dict(self) -> dict[str, float]:
        return {
            "wall_s": round(self.wall_s, 4),
            "client_cpu_s": round(self.client_cpu_s, 4),
            "server_cpu_s": round(self.server_cpu_s, 4),
            "client_busy": round(self.client_busy, 3),
            "server_busy": round(self.server_busy, 3),
        }


@contextmanager
def window(server: ServerProcess) -> Iterator[Window]:
    """Measure wall time and the CPU time of this process and of ``server`` over the block."""
    result = Window()
    server_cpu = server.cpu_seconds()
    client_cpu = time.process_time()
    start = time.perf_counter()
    try:
        yield result
    finally:
        result.wall_s = time.perf_counter() - start
        result.client_cpu_s = time.process_time() - client_cpu
        result.server_cpu_s = server.cpu_seconds() - server_cpu


@dataclass
class Latencies:
    """Percentiles of a set of latencies, in microseconds."""

    count: int = 0
    p50_us: float = float("nan")
    p99_us: float = float("nan")
    max_us: float = float("nan")
    samples_ns: list[int] = field(default_factory=list, repr=False)

    @classmethod
    def of(cls, samples_ns: list[int]) -> Latencies:
        if not samples_ns:
            return cls()
        array = np.asarray(samples_ns, dtype=np.float64) / 1000.0
        p50, p99 = np.percentile(array, [50, 99])
        return cls(len(samples_ns), float(p50), float(p99), float(array.max()))

    def as_dict(self) -> dict[str, float]:
        return {
            "count": self.count,
            "p50_us": round(self.p50_us, 1),
            "p99_us": round(self.p99_us, 1),
            "max_us": round(self.max_us, 1),
        }


@dataclass(kw_only=True)
class CallRun:
    """A measured run of calls: how many were made, how many failed, their latencies, the window."""

    done: int = 0
    errors: int = 0
    #: False when the time limit stopped the run before every call was made.
    complete: bool = True
    latency: Latencies = field(default_factory=Latencies)
    window: Window = field(default_factory=Window)

    @property
    def throughput(self) -> float:
        """Successful calls per second."""
        return (self.done - self.errors) / self.window.wall_s if self.window.wall_s else 0.0
