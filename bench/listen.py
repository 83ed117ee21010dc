"""Part (c): Listen fan-out — many subscribers, one setter, events delivered and set-to-delivery latency.

Every subscriber opens a Listen stream (current values first), waits for the
``sync`` marker, and from then on counts every event it reads. The setter is
one client on its own connection writing ``str(time.perf_counter_ns())`` as
the value, as fast as the server answers (or paced at ``set_rate``); the
subscriber subtracts that from its own ``perf_counter_ns`` on arrival. Both
run in this process, so the clock is shared (it is CLOCK_MONOTONIC on Linux,
the same for every process of the machine anyway).

Two modes:

* ``one-by-one``: every subscriber listens to one property; the setter makes
  one Set at a time. This is the plain fan-out of part (c).
* ``batched``: every subscriber listens to ``len(properties)`` properties in
  one stream; the setter writes bursts over one Session stream: one
  SessionRequest carrying one Set to each property, then, once all its
  replies are back, the next. The server applies a burst's Sets together, so
  several events are ready for each subscriber at once, and a server that
  batches sends them in one ListenResponse; the subscribers count events per
  message. The bare server sends one event per message whatever is ready.

Events/s is the number of events all subscribers read, divided by the time
from the first Set to the last event read. A server that conflates (drops
intermediate values for a slow reader, counting them in ``conflated``)
delivers fewer events; those are reported, never counted as delivered.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import grpc

from bench.measure import STREAM_END, Latencies, Window, read_until_sync, window
from bench.servers import ServerProcess
from bench.target import SERVICE
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

CALL_TIMEOUT = 10.0
#: How long subscribers may keep reading after the last Set before the run is declared incomplete.
DRAIN_TIMEOUT = 15.0
#: Each channel gets its own TCP connection (grpc otherwise shares one between
#: channels to the same address).
CHANNEL_OPTIONS = [("grpc.use_local_subchannel_pool", 1)]


@dataclass
class ListenResult:
    """What part (c) measured on one server in one mode."""

    mode: str
    subscribers: int
    sets: int
    properties: int
    burst: int
    set_rate: float
    channels: int
    sets_done: int = 0
    set_errors: int = 0
    events: int = 0
    conflated: int = 0
    messages: int = 0
    complete_subscribers: int = 0
    delivery_s: float = 0.0
    setter_s: float = 0.0
    latency: Latencies = field(default_factory=Latencies)
    window: Window = field(default_factory=Window)

    @property
    def events_per_s(self) -> float:
        """Events read by all subscribers per second, first Set to last event."""
        return self.events / self.delivery_s if self.delivery_s else 0.0

    @property
    def events_per_message(self) -> float:
        return self.events / self.messages if self.messages else 0.0

    @property
    def complete(self) -> bool:
        return self.complete_subscribers == self.subscribers and self.sets_done == self.sets

    def as_dict(self) -> dict[str, Any]:
        return {
            "mode": self.mode,
            "subscribers": self.subscribers,
            "sets": self.sets,
            "properties": self.properties,
            "burst": self.burst,
            "set_rate_per_s": self.set_rate or "as fast as possible",
            "channels": self.channels,
            "sets_done": self.sets_done,
            "set_errors": self.set_errors,
            "events": self.events,
            "expected_events": self.sets * self.subscribers,
            "conflated": self.conflated,
            "messages": self.messages,
            "events_per_message": round(self.events_per_message, 2),
            "complete": self.complete,
            "complete_subscribers": self.complete_subscribers,
            "setter_s": round(self.setter_s, 4),
            "delivery_s": round(self.delivery_s, 4),
            "events_per_s": round(self.events_per_s, 1),
            "sets_per_s": round(self.sets_done / self.setter_s, 1) if self.setter_s else 0.0,
            "server_cpu_us_per_event": round(1e6 * self.window.server_cpu_s / max(self.events, 1), 2),
            "latency": self.latency.as_dict(),
            "window": self.window.as_dict(),
        }


class Run:
    """State shared by the setter and the subscribers of one run."""

    def __init__(self, expected: int) -> None:
        self.expected = expected
        self.final: dict[str, str] | None = None
        self.samples: list[int] = []


class _Subscriber:
    """One Listen stream and what it has read."""

    #: Subscribers this one stands for (a Session carries several).
    listens = 1

    def __init__(self, call: Any, run: Run) -> None:
        self.call = call
        self.run = run
        #: The latest value of each (listen, property); a Listen stream is listen 1.
        self.latest: dict[tuple[int, str], str] = {}
        self.events = 0
        self.conflated = 0
        self.messages = 0
        self.last_ns = 0
        self.done = asyncio.Event()

    async def wait_sync(self) -> None:
        """Read the current values and the ``sync`` marker."""
        await read_until_sync(self.call)

    def check_done(self) -> None:
        final = self.run.final
        if self.events + self.conflated >= self.run.expected * self.listens or (
            final is not None
            and all(
                self.latest.get((n, p)) == v for n in range(1, self.listens + 1) for p, v in final.items()
            )
        ):
            self.done.set()

    def listened(self, message: Any) -> Iterator[tuple[int, pb.ListenResponse]]:
        """The Listen responses ``message`` carries, each with the number of its listen."""
        yield 1, message

    async def consume(self) -> None:
        samples = self.run.samples
        while True:
            message = await self.call.read()
            if message is STREAM_END:
                return
            now = time.perf_counter_ns()
            before = self.events
            for number, response in self.listened(message):
                for event in response.events:
                    self.events += 1
                    self.conflated += event.conflated
                    self.latest[(number, event.property)] = event.value
                    samples.append(now - int(event.value))
            if self.events > before:
                self.messages += 1
                self.last_ns = now
                self.check_done()


class _SessionSubscribers(_Subscriber):
    """``listens`` subscribers carried as Listen requests (ids 1 to ``listens``) inside one Session."""

    def __init__(self, call: Any, listens: int, run: Run) -> None:
        super().__init__(call, run)
        self.listens = listens

    async def wait_sync(self) -> None:
        """Read until every Listen of the Session has sent its ``sync`` marker."""
        synced: set[int] = set()
        while len(synced) < self.listens:
            message = await self.call.read()
            if message is STREAM_END:
                raise RuntimeError(f"a Session ended before its listens' sync: {await self.call.code()}")
            for reply in message.replies:
                if reply.status.code:
                    raise RuntimeError(f"listen {reply.id} failed: {reply.status.message}")
                if reply.listen.sync:
                    synced.add(reply.id)

    def listened(self, message: Any) -> Iterator[tuple[int, pb.ListenResponse]]:
        for reply in message.replies:
            yield reply.id, reply.listen


async def set_all(
    stub: pb_grpc.PropertyServiceStub,
    *,
    properties: Sequence[str],
    sets: int,
    set_rate: float,
    deadline: float,
    result: ListenResult,
) -> dict[str, str]:
    """Make ``sets`` Sets; return the last value written to each property.

    With one property: one unary Set at a time. With several: each burst is
    one SessionRequest carrying one Set per property, and the next burst
    goes when all its replies are back.
    """
    final: dict[str, str] = {}
    interval = len(properties) / set_rate if set_rate else 0.0
    next_at = time.monotonic()
    session = stub.Session() if len(properties) > 1 else None
    try:
        while result.sets_done < sets and time.monotonic() < deadline:
            group = properties[: sets - result.sets_done]
            if session is None:
                value = str(time.perf_counter_ns())
                request = pb.SetRequest(service=SERVICE, property=group[0], value=value)
                try:
                    await stub.Set(request, timeout=CALL_TIMEOUT)
                except grpc.aio.AioRpcError:
                    result.set_errors += 1
                else:
                    final[group[0]] = value
                result.sets_done += 1
            else:
                await _burst(session, group, result.sets_done, final, result)
            if interval:
                next_at += interval
                await asyncio.sleep(max(next_at - time.monotonic(), 0.0))
    finally:
        if session is not None:
            session.cancel()
    return final


async def _burst(
    session: Any, group: Sequence[str], first_id: int, final: dict[str, str], result: ListenResult
) -> None:
    """One SessionRequest with a Set to each property of ``group``; wait for every reply."""
    message = pb.SessionRequest()
    values: dict[int, tuple[str, str]] = {}
    for number, prop in enumerate(group, start=first_id + 1):
        value = str(time.perf_counter_ns())
        values[number] = (prop, value)
        message.requests.add(id=number, set=pb.SetRequest(service=SERVICE, property=prop, value=value))
    async with asyncio.timeout(CALL_TIMEOUT):
        await session.write(message)
        while values:
            response = await session.read()
            if response is STREAM_END:
                raise RuntimeError(f"the setter's Session ended: {await session.code()}")
            for reply in response.replies:
                prop, value = values.pop(reply.id)
                result.sets_done += 1
                if reply.status.code:
                    result.set_errors += 1
                else:
                    final[prop] = value


class Hearing(Protocol):
    """A subscriber of a run, on whatever front: what :func:`measure_delivery` reads of it."""

    done: asyncio.Event
    last_ns: int
    events: int

    def check_done(self) -> None: ...


async def measure_delivery(
    server: ServerProcess,
    setter: pb_grpc.PropertyServiceStub,
    subs: Sequence[Hearing],
    run: Run,
    result: ListenResult,
    *,
    properties: Sequence[str],
    sets: int,
    set_rate: float,
    deadline: float,
) -> int:
    """The measured window of a run: ``sets`` Sets at ``set_rate``, then until every subscriber has
    heard the last (at most DRAIN_TIMEOUT, never past ``deadline``). Fills the result's window and
    setter time; returns when the first Set was sent (``time.perf_counter_ns``)."""
    with window(server) as result.window:
        first_set_ns = time.perf_counter_ns()
        run.final = await set_all(
            setter, properties=properties, sets=sets, set_rate=set_rate, deadline=deadline, result=result
        )
        result.setter_s = (time.perf_counter_ns() - first_set_ns) / 1e9
        for sub in subs:
            sub.check_done()
        drain_until = min(deadline, time.monotonic() + DRAIN_TIMEOUT)
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(max(drain_until - time.monotonic(), 0.0)):
                await asyncio.gather(*(sub.done.wait() for sub in subs))
    return first_set_ns


def count_delivery(result: ListenResult, subs: Sequence[Hearing], run: Run, first_set_ns: int) -> None:
    """What the subscribers heard, into ``result``: the delivery time, the events, the latencies."""
    last_ns = max((sub.last_ns for sub in subs), default=0)
    result.delivery_s = max(last_ns - first_set_ns, 0) / 1e9
    result.events = sum(sub.events for sub in subs)
    result.latency = Latencies.of(run.samples)


async def run_listen(
    server: ServerProcess,
    *,
    mode: str,
    properties: Sequence[str],
    subscribers: int,
    sets: int,
    channels: int,
    set_rate: float,
    time_limit: float,
    per_session: int = 0,
) -> ListenResult:
    """Open ``subscribers`` Listen streams on ``properties``, make ``sets`` Sets, count what arrives.

    ``per_session``: the subscribers are Listen requests inside Sessions instead, this many to a
    Session (the Sessions spread over the channels as the streams are), ``subscribers // per_session``
    Sessions in all.
    """
    result = ListenResult(
        mode=mode,
        subscribers=subscribers,
        sets=sets,
        properties=len(properties),
        burst=len(properties),
        set_rate=set_rate,
        channels=channels,
    )
    run = Run(expected=sets)
    deadline = time.monotonic() + time_limit
    opened = [grpc.aio.insecure_channel(server.address, options=CHANNEL_OPTIONS) for _ in range(channels)]
    setter_channel = grpc.aio.insecure_channel(server.address, options=CHANNEL_OPTIONS)
    tasks: list[asyncio.Task[None]] = []
    subs: list[_Subscriber] = []
    first_set_ns = 0
    try:
        setter = pb_grpc.PropertyServiceStub(setter_channel)
        for prop in properties:
            await setter.Set(pb.SetRequest(service=SERVICE, property=prop, value="0"), timeout=CALL_TIMEOUT)
        request = pb.ListenRequest(
            service=SERVICE,
            property=properties[0],
            more=[pb.PropertyRef(service=SERVICE, property=prop) for prop in properties[1:]],
        )
        if per_session:
            # Listens inside Sessions, per_session to a Session, the Sessions spread as the streams.
            in_session = [pb.Request(id=n + 1, listen=request) for n in range(per_session)]
            for number in range(subscribers // per_session):
                call = pb_grpc.PropertyServiceStub(opened[number % channels]).Session()
                await call.write(pb.SessionRequest(requests=in_session))
                subs.append(_SessionSubscribers(call, per_session, run))
        else:
            for number in range(subscribers):
                stub = pb_grpc.PropertyServiceStub(opened[number % channels])
                subs.append(_Subscriber(stub.Listen(request), run))
        async with asyncio.timeout(CALL_TIMEOUT * 3):
            await asyncio.gather(*(sub.wait_sync() for sub in subs))
        tasks = [asyncio.create_task(sub.consume()) for sub in subs]

        first_set_ns = await measure_delivery(
            server,
            setter,
            subs,
            run,
            result,
            properties=properties,
            sets=sets,
            set_rate=set_rate,
            deadline=deadline,
        )
    finally:
        for task in tasks:
            task.cancel()
        for sub in subs:
            sub.call.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for channel in [*opened, setter_channel]:
            await channel.close(None)

    count_delivery(result, subs, run, first_set_ns)
    result.conflated = sum(sub.conflated for sub in subs)
    result.messages = sum(sub.messages for sub in subs)
    result.complete_subscribers = sum(sub.listens for sub in subs if sub.done.is_set())
    server.check_alive()
    return result
