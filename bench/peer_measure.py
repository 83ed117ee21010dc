"""What the peers' load loops share: a subscriber's tally, and the figures of one peer in one round.

The peers (OPC UA through asyncua, Zenoh through its Python binding) are
measured with the client patterns of parts (a)-(c) and (r), and their figures
are kept in the same shapes (:class:`bench.unary.UnaryResult`,
:class:`bench.listen.ListenResult`), so that the report reads them as it reads
the gRPC servers'.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from bench.listen import ListenResult
from bench.measure import Latencies, window
from bench.servers import ServerProcess
from bench.unary import UnaryResult

#: The exceptions that make a call an error (counted) rather than end the run.
Errors = tuple[type[BaseException], ...]

#: The value written before the subscribers open: it marks them as caught up (the gRPC ``sync``).
SYNC_VALUE = "sync"
#: How long subscribers may keep reading after the last Set before the run is declared incomplete.
DRAIN_TIMEOUT = 15.0
#: How long every subscriber may take to see :data:`SYNC_VALUE`.
SYNC_TIMEOUT = 30.0
#: How often a waiting loop looks at the tallies: they are written by another thread (zenoh) or task.
POLL_S = 0.005


class Receiver:
    """One subscriber: the events it read and the latest value.

    Values are ``str(time.perf_counter_ns())`` written by the setter in this
    process; each one's latency is taken on arrival into ``samples``, which
    the subscribers of one run share (a list append is atomic in CPython, so
    callbacks on several threads may append). :data:`SYNC_VALUE` only marks
    the subscriber as caught up and is not counted.
    """

    __slots__ = ("events", "last_ns", "latest", "samples", "synced")

    def __init__(self, samples: list[int]) -> None:
        self.samples = samples
        self.events = 0
        self.latest = ""
        self.last_ns = 0
        self.synced = False

    def note(self, value: str) -> None:
        now = time.perf_counter_ns()
        if value == SYNC_VALUE:
            self.synced = True
            return
        self.events += 1
        self.latest = value
        self.last_ns = now
        self.samples.append(now - int(value))

    def caught_up(self, expected: int, final: str | None) -> bool:
        """Whether it has read every Set, or at least the last value set."""
        return self.events >= expected or (final is not None and self.latest == final)


async def poll_until(check: Callable[[], bool], seconds: float) -> bool:
    """Poll ``check`` until it holds or ``seconds`` pass; whether it held."""
    deadline = time.monotonic() + seconds
    while not check():
        if time.monotonic() >= deadline:
            return False
        await asyncio.sleep(POLL_S)
    return True


async def drive_calls(
    call: Callable[[], Awaitable[Any]], calls: int, inflight: int, deadline: float, errors: Errors
) -> tuple[list[int], int, bool]:
    """Make ``calls`` calls, ``inflight`` at a time, in this loop; latencies (ns), errors, all made.

    The same loop as :func:`bench.unary._drive`, for a client whose calls are coroutines.
    """
    remaining = calls
    failed = 0
    samples: list[int] = []

    async def worker() -> None:
        nonlocal remaining, failed
        while remaining > 0 and time.monotonic() < deadline:
            remaining -= 1
            start = time.perf_counter_ns()
            try:
                await call()
            except errors:
                failed += 1
                continue
            samples.append(time.perf_counter_ns() - start)

    await asyncio.gather(*(worker() for _ in range(inflight)))
    return samples, failed, remaining == 0


async def drive_blocking(
    call: Callable[[], Any], calls: int, inflight: int, deadline: float, errors: Errors
) -> tuple[list[int], int, bool]:
    """The same with a blocking client: ``inflight`` threads, each making one call after another."""
    lock = threading.Lock()
    remaining = calls
    failed = 0
    samples: list[int] = []

    def worker() -> None:
        nonlocal remaining, failed
        while time.monotonic() < deadline:
            with lock:
                if remaining <= 0:
                    return
                remaining -= 1
            start = time.perf_counter_ns()
            try:
                call()
            except errors:
                with lock:
                    failed += 1
                continue
            samples.append(time.perf_counter_ns() - start)

    await asyncio.gather(*(asyncio.to_thread(worker) for _ in range(inflight)))
    return samples, failed, remaining == 0


Driver = Callable[[int, int, float], Awaitable[tuple[list[int], int, bool]]]


async def measure_calls(
    server: ServerProcess, drive: Driver, *, calls: int, inflight: int, warmup: int, time_limit: float
) -> UnaryResult:
    """Warm up, then ``drive(calls, inflight, deadline)`` inside a measured window: part (a)'s figures."""
    result = UnaryResult(calls=calls, inflight=inflight)
    await drive(warmup, inflight, time.monotonic() + time_limit)
    with window(server) as result.window:
        samples, result.errors, result.complete = await drive(calls, inflight, time.monotonic() + time_limit)
    result.done = len(samples) + result.errors
    result.latency = Latencies.of(samples)
    server.check_alive()
    return result


async def _set_all(
    write: Callable[[str], Awaitable[Any]],
    *,
    sets: int,
    set_rate: float,
    deadline: float,
    result: ListenResult,
    errors: Errors,
) -> str | None:
    """Write ``sets`` values one at a time (each awaited), paced at ``set_rate`` a second if not 0.

    Returns the last value written, as :func:`bench.listen.set_all` does for the gRPC servers.
    """
    final = None
    interval = 1.0 / set_rate if set_rate else 0.0
    next_at = time.monotonic()
    while result.sets_done < sets and time.monotonic() < deadline:
        value = str(time.perf_counter_ns())
        try:
            await write(value)
        except errors:
            result.set_errors += 1
        else:
            final = value
        result.sets_done += 1
        if interval:
            next_at += interval
            await asyncio.sleep(max(next_at - time.monotonic(), 0.0))
    return final


class Fanout:
    """One fan-out run on a peer: its figures (part (c)'s shape) and its subscribers' tallies.

    The peer's load opens its subscribers (one :class:`Receiver` each), waits
    until every one is :attr:`Receiver.synced`, then calls :meth:`measure`.
    """

    def __init__(  # noqa: PLR0917
        self, mode: str, subscribers: int, channels: int, sets: int, set_rate: float, time_limit: float
    ) -> None:
        self.result = ListenResult(
            mode=mode,
            subscribers=subscribers,
            sets=sets,
            properties=1,
            burst=1,
            set_rate=set_rate,
            channels=channels,
        )
        self.deadline = time.monotonic() + time_limit
        self.samples: list[int] = []
        self.receivers = [Receiver(self.samples) for _ in range(subscribers)]

    def synced(self) -> int:
        """How many subscribers have seen :data:`SYNC_VALUE`."""
        return sum(r.synced for r in self.receivers)

    async def measure(
        self, server: ServerProcess, write: Callable[[str], Awaitable[Any]], errors: Errors
    ) -> ListenResult:
        """Make the Sets with ``write``, let the subscribers drain, and fill in the figures."""
        result, receivers, sets = self.result, self.receivers, self.result.sets
        with window(server) as result.window:
            first_set_ns = time.perf_counter_ns()
            final = await _set_all(
                write,
                sets=sets,
                set_rate=result.set_rate,
                deadline=self.deadline,
                result=result,
                errors=errors,
            )
            result.setter_s = (time.perf_counter_ns() - first_set_ns) / 1e9
            await poll_until(
                lambda: all(r.caught_up(sets, final) for r in receivers),
                min(DRAIN_TIMEOUT, max(self.deadline - time.monotonic(), 0.0)),
            )
        last_ns = max((r.last_ns for r in receivers), default=0)
        result.delivery_s = max(last_ns - first_set_ns, 0) / 1e9
        result.events = sum(r.events for r in receivers)
        # A peer's message may carry several events (OPC UA's Publish responses), or reach several
        # subscribers at once (one zenoh message per session): events per message is not comparable.
        result.messages = 0
        result.complete_subscribers = sum(r.caught_up(sets, final) for r in receivers)
        result.latency = Latencies.of(self.samples)
        server.check_alive()
        return result


@dataclass
class PeerRound:
    """The four patterns measured on one peer in one round, each in its gRPC part's shape."""

    system: str
    #: How the client talks to the peer, for the report.
    client: str
    sequential: UnaryResult
    inflight: UnaryResult
    fanout: ListenResult
    paced: ListenResult
    notes: list[str] = field(default_factory=list)

    def as_dict(self) -> dict[str, Any]:
        parts = {
            "sequential": self.sequential.as_dict(),
            "unary": self.inflight.as_dict(),
            "listen": self.fanout.as_dict(),
            "paced": self.paced.as_dict(),
        }
        return {
            "system": self.system,
            "client": self.client,
            **parts,
            "complete": all(part["complete"] for part in parts.values()),
            "notes": self.notes,
        }


@dataclass(frozen=True)
class PeerSizes:
    """The sizes of part (s): those of parts (a) and (c), and of (r) for the paced Sets."""

    calls: int
    inflight: int
    warmup: int
    subscribers: int
    channels: int
    #: Unpaced Sets of the fan-out; ``paced_sets`` more at ``set_rate`` a second.
    sets: int
    paced_sets: int
    set_rate: float
    time_limit: float


async def measure_patterns(
    server: ServerProcess,
    sizes: PeerSizes,
    *,
    drive: Driver,
    fan_out: Callable[[Fanout], Awaitable[ListenResult]],
    system: str,
    client: str,
) -> PeerRound:
    """The four patterns on one peer: Gets one at a time and in flight with ``drive``, two fan-outs."""
    calls = {"calls": sizes.calls, "warmup": sizes.warmup, "time_limit": sizes.time_limit}
    sequential = await measure_calls(server, drive, inflight=1, **calls)
    concurrent = await measure_calls(server, drive, inflight=sizes.inflight, **calls)
    fanout = await fan_out(
        Fanout("one-by-one", sizes.subscribers, sizes.channels, sizes.sets, 0.0, sizes.time_limit)
    )
    paced = await fan_out(
        Fanout("paced", sizes.subscribers, sizes.channels, sizes.paced_sets, sizes.set_rate, sizes.time_limit)
    )
    return PeerRound(
        system=system, client=client, sequential=sequential, inflight=concurrent, fanout=fanout, paced=paced
    )
