"""Fan-out of backend changes to Listen streams, with bounded memory.

Vocabulary:

* A **topic** is one backend subscription: (service, concrete path,
  parameters). It is shared by every stream that wants it and closed when
  the last one leaves. It caches the property's latest value, so a stream
  joining a busy topic gets the current value without a backend call.
* A **stream** (:class:`ListenStream`) is one client's Listen: its selectors
  (``*`` may stand for the service or for one path segment), its options,
  and one conflating queue: ``pending`` maps a topic to the latest value not
  yet sent and how many values it replaced. Memory is bounded by the number
  of topics the stream matches, never by how fast values change.
* The stream's writer (the gRPC handler, or the Session writer) is woken by
  ``on_ready`` and calls :meth:`ListenStream.take` until it returns None;
  each call drains what is ready into one ``ListenResponse``.

Wildcards follow the service: ``*`` as service follows the router's adds and
removes; ``*`` in a path is expanded against the service's ``properties`` and
follows a listen on ``properties``.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from itertools import islice
from typing import Any, Protocol

from google.protobuf.duration_pb2 import Duration

from gateway.config import Limits
from gateway.router import Router, bounded_call, check_pattern
from gateway.sizes import BATCH_BYTES, MAX_MESSAGE_BYTES
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.backend import NO_PARAMS, Backend, Change, Subscription
from services.errors import Code, InvalidArgument, NotFound, PropertyError, ResourceExhausted
from services.paths import WILDCARD, compile_pattern, is_pattern, validate_service_name
from services.values import parse_names

log = logging.getLogger(__name__)

PROPERTIES = "properties"
#: Seconds a Listen keeps trying a service that joined but cannot answer yet (a proxy still
#: connecting to its device) before the stream fails; the registry's register_timeout.
JOIN_RETRY_S = 10.0

TopicKey = tuple[str, str, tuple[tuple[str, str], ...]]


@dataclass(frozen=True, slots=True)
class Selector:
    """What a Listen asks for: a service (or ``*``), a path (``*`` segments allowed), parameters."""

    service: str
    path: str
    params: tuple[tuple[str, str], ...] = ()

    def matches_service(self, name: str) -> bool:
        return self.service in (WILDCARD, name)


@dataclass(frozen=True, slots=True)
class StreamOptions:
    """Parsed ``ListenOptions``; intervals in seconds, 0 = off."""

    updates_only: bool = False
    min_interval: float = 0.0
    sample_interval: float = 0.0
    heartbeat_interval: float = 0.0
    max_batch: int = 256


def _seconds(d: Duration, name: str, floor: float) -> float:
    if d.seconds < 0 or d.nanos < 0:
        raise InvalidArgument(f"options.{name} must not be negative")
    s = d.seconds + d.nanos / 1e9
    if 0 < s < floor:
        raise InvalidArgument(f"options.{name} of {s * 1000:g} ms is below the floor of {floor * 1000:g} ms")
    return s


def parse_options(opts: pb.ListenOptions, limits: Limits) -> StreamOptions:
    """Check ``ListenOptions`` against the limits; raises InvalidArgument."""
    floor = limits.min_interval_floor
    max_batch = limits.max_batch if opts.max_batch == 0 else min(opts.max_batch, limits.max_batch)
    return StreamOptions(
        updates_only=opts.updates_only,
        min_interval=_seconds(opts.min_interval, "min_interval", floor),
        sample_interval=_seconds(opts.sample_interval, "sample_interval", floor),
        heartbeat_interval=_seconds(opts.heartbeat_interval, "heartbeat_interval", floor),
        max_batch=max_batch,
    )


def _selector(service: str, path: str, params: Mapping[str, str], default_service: str) -> Selector:
    service = service or default_service
    if not service:
        raise InvalidArgument("a Listen selector needs a service (or * for every service)")
    if service != WILDCARD:
        validate_service_name(service)
    check_pattern(path)
    return Selector(service, path, tuple(sorted(params.items())))


def parse_selectors(request: pb.ListenRequest, limits: Limits) -> list[Selector]:
    """The request's selectors (its own and ``more``; an empty service in ``more`` = the request's)."""
    count = 1 + len(request.more)
    if count > limits.max_selectors:
        raise ResourceExhausted(
            f"a Listen may have at most {limits.max_selectors} selectors, this one has {count}"
        )
    selectors = [_selector(request.service, request.property, request.parameters, "")]
    for ref in request.more:
        selectors.append(_selector(ref.service, ref.property, ref.parameters, request.service))
    # The same selector twice would only double the bookkeeping.
    return list(dict.fromkeys(selectors))


class _Sink(Protocol):
    def topic_changed(self, topic: Topic, change: Change, seen_ns: int) -> None: ...


class Topic:
    """One shared backend subscription and the latest value seen on it."""

    __slots__ = (
        "backend",
        "dead",
        "key",
        "opening",
        "params",
        "path",
        "removed",
        "service",
        "sinks",
        "subscription",
        "value",
    )

    def __init__(self, key: TopicKey, backend: Backend) -> None:
        self.key = key
        self.service, self.path, params = key
        self.params: Mapping[str, str] = dict(params) if params else NO_PARAMS
        self.backend = backend
        self.sinks: set[_Sink] = set()
        self.subscription: Subscription | None = None
        self.value = ""
        #: The last change was the property's removal (every sink has been told).
        self.removed = False
        self.dead = False
        self.opening: asyncio.Task[None] | None = None

    def notify(self, change: Change) -> None:
        """The backend's callback: remember the value, hand it to every sink."""
        if self.dead:
            return
        self.value = change.value
        self.removed = change.removed
        seen = time.time_ns()
        for sink in list(self.sinks):
            try:
                sink.topic_changed(self, change, seen)
            except Exception:
                log.exception("delivering a change of %s %s failed", self.service, self.path)

    def __repr__(self) -> str:
        return f"Topic({self.service}/{self.path}, {len(self.sinks)} sinks)"


class _Pending:
    __slots__ = ("conflated", "gap", "removed", "seen", "value")

    def __init__(self, value: str, seen: int, gap: bool = False, removed: bool = False) -> None:
        self.value = value
        self.conflated = 0
        self.seen = seen
        self.gap = gap
        self.removed = removed


class _Expansion:
    """A path pattern expanded against one service's ``properties``; follows its changes."""

    __slots__ = ("list_topic", "matched", "matches", "selector", "service", "stream")

    def __init__(self, stream: ListenStream, selector: Selector, service: str) -> None:
        self.stream = stream
        self.selector = selector
        self.service = service
        self.matches = compile_pattern(selector.path)
        self.matched: set[str] = set()
        self.list_topic: Topic | None = None

    def paths(self, listing: str) -> set[str]:
        try:
            names = parse_names(listing)
        except PropertyError as exc:
            log.warning("%s: cannot read its properties list: %s", self.service, exc.message)
            return set(self.matched)
        return {n for n in names if self.matches(n)}

    def topic_changed(self, topic: Topic, change: Change, seen_ns: int) -> None:
        if change.removed:
            return
        self.stream._reconcile(self, self.paths(change.value))


class ListenStream:
    """One Listen: selectors, options and the conflating queue; see the module docstring."""

    __slots__ = (
        "_expansions",
        "_heartbeat_due",
        "_heartbeat_timer",
        "_hub",
        "_last_emit",
        "_last_sent",
        "_live",
        "_on_ready",
        "_pending",
        "_refs",
        "_sample_flush",
        "_sample_timer",
        "_sequence",
        "_signalled",
        "_sync_after",
        "_sync_due",
        "_throttle_timer",
        "closed",
        "ended",
        "error",
        "options",
        "selectors",
    )

    def __init__(
        self,
        hub: ListenHub,
        selectors: Sequence[Selector],
        options: StreamOptions,
        on_ready: Callable[[], None],
    ) -> None:
        self._hub = hub
        self.selectors = tuple(selectors)
        self.options = options
        self._on_ready = on_ready
        self._pending: dict[Topic, _Pending] = {}
        self._refs: dict[Topic, int] = {}
        self._expansions: list[_Expansion] = []
        self._last_emit: dict[Topic, float] | None = {} if options.min_interval else None
        self._sequence = 0
        self._signalled = False
        self._live = False
        self._sync_due = False
        self._sync_after = 0
        self._sample_flush = -1 if options.sample_interval else 0
        self._heartbeat_due = False
        self._last_sent = 0.0
        self._throttle_timer: asyncio.TimerHandle | None = None
        self._sample_timer: asyncio.TimerHandle | None = None
        self._heartbeat_timer: asyncio.TimerHandle | None = None
        #: The stream must end: closed by the client, or ended by the gateway.
        self.closed = False
        #: Set when the gateway ends the stream (shutdown); the writer then stops with OK.
        self.ended = False
        #: Set when the stream must end with this error (e.g. a limit was passed).
        self.error: PropertyError | None = None

    @property
    def property_count(self) -> int:
        """How many properties the stream matches right now."""
        return len(self._refs)

    # -- setting up ------------------------------------------------------

    async def start(self) -> None:
        """Expand the selectors, subscribe, read current values; then the stream is live.

        Raises NOT_FOUND for an unknown service or a concrete path that does
        not exist, RESOURCE_EXHAUSTED when a limit is passed.
        """
        router = self._hub.router
        for sel in self.selectors:
            if sel.service == WILDCARD:
                for name, backend in router.items():
                    await self._expand(sel, name, backend, strict=False)
            else:
                await self._expand(sel, sel.service, router.backend(sel.service), strict=True)
        if self.closed:
            return
        self._live = True
        self._sync_due = True
        self._sync_after = 0 if self.options.updates_only else len(self._pending)
        loop = asyncio.get_running_loop()
        if self.options.sample_interval:
            self._sample_timer = loop.call_later(self.options.sample_interval, self._sample_tick)
        if self.options.heartbeat_interval:
            self._last_sent = loop.time()
            self._heartbeat_timer = loop.call_later(self.options.heartbeat_interval, self._heartbeat_check)
        self._signal()

    async def _expand(self, sel: Selector, service: str, backend: Backend, strict: bool) -> None:
        if self.closed:
            return
        if not is_pattern(sel.path):
            await self._join((service, sel.path, sel.params), backend, strict)
            return
        exp = _Expansion(self, sel, service)
        list_topic = await self._hub._subscribe(exp, (service, PROPERTIES, ()), backend, strict)
        if list_topic is None:
            return
        if self.closed:
            self._hub._unsubscribe(exp, list_topic)
            return
        exp.list_topic = list_topic
        self._expansions.append(exp)
        exp.matched = exp.paths(list_topic.value)
        await self._join_many(exp, sorted(exp.matched))

    async def _join_many(self, exp: _Expansion, paths: Iterable[str]) -> None:
        backend = exp.list_topic.backend if exp.list_topic else None
        if backend is None:
            return
        keys = [(exp.service, p, exp.selector.params) for p in paths]
        if len(keys) == 1:
            await self._join(keys[0], backend, strict=False)
        elif keys:
            await asyncio.gather(*(self._join(k, backend, strict=False) for k in keys))

    async def _join(self, key: TopicKey, backend: Backend, strict: bool) -> None:
        """Share the topic ``key``; queue its current value unless updates only."""
        if self.closed:
            return
        topic = self._hub._topics.get(key)
        if topic is not None and topic in self._refs:
            self._refs[topic] += 1
            return
        limit = self._hub.limits.max_stream_properties
        if len(self._refs) >= limit:
            raise self._too_many()
        topic = await self._hub._subscribe(self, key, backend, strict)
        if topic is None:
            return
        if self.closed or topic.dead:
            self._hub._unsubscribe(self, topic)
            return
        if topic in self._refs:  # joined twice concurrently
            self._refs[topic] += 1
            self._hub._unsubscribe(self, topic)
            return
        if len(self._refs) >= limit:
            self._hub._unsubscribe(self, topic)
            raise self._too_many()
        self._refs[topic] = 1
        if not self.options.updates_only and topic not in self._pending:
            self._pending[topic] = _Pending(topic.value, time.time_ns())
            if self._live:
                self._signal()

    def _too_many(self) -> ResourceExhausted:
        limit = self._hub.limits.max_stream_properties
        return ResourceExhausted(
            f"this Listen matches more than {limit} properties (limits.max_stream_properties)"
        )

    def _leave(self, topic: Topic, announce: bool) -> None:
        n = self._refs.get(topic)
        if n is None:
            return
        if n > 1:
            self._refs[topic] = n - 1
            return
        del self._refs[topic]
        self._hub._unsubscribe(self, topic)
        if not announce:
            self._pending.pop(topic, None)
        elif not topic.removed:  # else the backend's own removal is queued or sent already
            self._enqueue(topic, "", time.time_ns(), gap=False, removed=True)

    def _reconcile(self, exp: _Expansion, paths: set[str]) -> None:
        """The service's properties changed: join new matches, leave the ones gone."""
        if self.closed:
            return
        gone = exp.matched - paths
        new = paths - exp.matched
        exp.matched = paths
        for path in gone:
            topic = self._hub._topics.get((exp.service, path, exp.selector.params))
            if topic is not None:
                self._leave(topic, announce=True)
        if new:
            self._hub._spawn(self._join_new(exp, sorted(new)))

    async def _join_new(self, exp: _Expansion, paths: list[str]) -> None:
        try:
            await self._join_many(exp, [p for p in paths if p in exp.matched])
        except PropertyError as exc:
            self.fail(exc)
            return
        # A path may have gone again while joining.
        for path in paths:
            if path not in exp.matched:
                topic = self._hub._topics.get((exp.service, path, exp.selector.params))
                if topic is not None:
                    self._leave(topic, announce=True)

    def _service_added(self, name: str, backend: Backend) -> None:
        for sel in self.selectors:
            if sel.matches_service(name):
                self._hub._spawn(self._expand_later(sel, name, backend))

    async def _expand_later(self, sel: Selector, name: str, backend: Backend) -> None:
        """Follow a service that joined; one whose device is not connected yet is asked again."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + JOIN_RETRY_S
        pause = 0.05
        while True:
            try:
                await self._expand(sel, name, backend, strict=False)
                return
            except PropertyError as exc:
                transient = exc.code in (Code.UNAVAILABLE, Code.DEADLINE_EXCEEDED)
                # Only a try that set nothing up can be repeated as a whole.
                untouched = not any(e.selector == sel and e.service == name for e in self._expansions)
                if not (transient and untouched) or loop.time() + pause > deadline:
                    self.fail(exc)
                    return
            await asyncio.sleep(pause)
            pause = min(pause * 2, 1.0)
            if self.closed or not self._serves(name, backend):
                return

    def _serves(self, name: str, backend: Backend) -> bool:
        try:
            return self._hub.router.lookup(name) is backend
        except PropertyError:
            return False

    def _service_removed(self, name: str) -> None:
        for topic in [t for t in self._refs if t.service == name]:
            del self._refs[topic]
        self._expansions = [e for e in self._expansions if e.service != name]

    # -- receiving -------------------------------------------------------

    def topic_changed(self, topic: Topic, change: Change, seen_ns: int) -> None:
        """A change on a topic this stream shares (called by :meth:`Topic.notify`)."""
        if topic in self._refs:
            self._enqueue(topic, change.value, seen_ns, change.gap, change.removed)

    def _enqueue(self, topic: Topic, value: str, seen: int, gap: bool, removed: bool) -> None:
        entry = self._pending.get(topic)
        if entry is None:
            self._pending[topic] = _Pending(value, seen, gap, removed)
        else:
            if not (removed and entry.removed):
                entry.conflated += 1
            entry.value = value
            entry.seen = seen
            entry.gap = entry.gap or gap
            entry.removed = removed
        if self._live and not self._sample_flush:
            self._signal()

    def _signal(self) -> None:
        if not self._signalled:
            self._signalled = True
            self._on_ready()

    def fail(self, err: PropertyError) -> None:
        """End the stream with ``err`` (the writer sends the status)."""
        if self.error is None and not self.closed:
            self.error = err
            self._signalled = False
            self._signal()

    def end(self) -> None:
        """End the stream cleanly (gateway shutdown): the writer flushes nothing more and stops with OK."""
        self.ended = True
        self._signalled = False
        self._signal()

    # -- timers ----------------------------------------------------------

    def _sample_tick(self) -> None:
        if self.closed:
            return
        loop = asyncio.get_running_loop()
        self._sample_timer = loop.call_later(self.options.sample_interval, self._sample_tick)
        now = time.time_ns()
        for topic in self._refs:
            if topic not in self._pending:
                self._pending[topic] = _Pending(topic.value, now)
        self._sample_flush = len(self._pending) or -1
        self._signal()

    def _heartbeat_check(self) -> None:
        if self.closed:
            return
        loop = asyncio.get_running_loop()
        interval = self.options.heartbeat_interval
        quiet = loop.time() - self._last_sent
        if quiet >= interval * 0.999:
            self._heartbeat_due = True
            self._signal()
            quiet = 0.0
        self._heartbeat_timer = loop.call_later(interval - quiet, self._heartbeat_check)

    def _throttle_wake(self) -> None:
        self._throttle_timer = None
        self._signal()

    # -- sending ---------------------------------------------------------

    def take(self) -> pb.ListenResponse | None:
        """Drain what is ready into one response; None when nothing is ready."""
        self._signalled = False
        if not self._live or self.closed or self.error is not None:
            return None
        if self._sync_due and (self._sync_after <= 0 or not self._pending):
            self._sync_due = False
            return self._sent(pb.ListenResponse(sync=True))
        limit = self.options.max_batch
        if self._sync_due:
            limit = min(limit, self._sync_after)
        elif self._sample_flush:
            if self._sample_flush < 0:
                return self._heartbeat()
            limit = min(limit, self._sample_flush)
        response = self._drain(limit)
        count = len(response.events) if response is not None else 0
        if self._sync_due:
            self._sync_after -= count
        elif self._sample_flush > 0:
            self._sample_flush = max(self._sample_flush - count, 0) or -1
        if response is not None:
            return self._sent(response)
        if self._sync_due:
            self._sync_due = False
            return self._sent(pb.ListenResponse(sync=True))
        return self._heartbeat()

    def _heartbeat(self) -> pb.ListenResponse | None:
        if self._heartbeat_due:
            return self._sent(pb.ListenResponse(heartbeat=True))
        return None

    def _sent(self, response: pb.ListenResponse) -> pb.ListenResponse:
        self._heartbeat_due = False
        if self._heartbeat_timer is not None:
            self._last_sent = asyncio.get_running_loop().time()
        return response

    def _drain(self, limit: int) -> pb.ListenResponse | None:
        """The events ready, at most ``limit``, in one response; None when there are none."""
        pending = self._pending
        if not pending:
            return None
        ready: list[tuple[Topic, _Pending]]
        if self._last_emit is not None and self._sync_after <= 0:
            ready, size = self._ready_throttled(limit)
        else:
            ready, size = _within(islice(pending.items(), limit))
            if len(ready) == len(pending):
                self._pending = {}
            else:
                for topic, _ in ready:
                    del pending[topic]
        if not ready:
            return None
        if len(ready) == 1 and size > MAX_MESSAGE_BYTES:
            topic = ready[0][0]
            self.fail(
                ResourceExhausted(
                    f"{topic.service}/{topic.path}: a value of {size} bytes does not fit in one message "
                    f"(at most {MAX_MESSAGE_BYTES} bytes)"
                )
            )
            return None
        # Events are added in place: built apart, each would be copied into the response.
        response = pb.ListenResponse()
        add = response.events.add
        seq = self._sequence
        for topic, entry in ready:
            seq += 1
            ev = add(
                service=topic.service,
                property=topic.path,
                value=entry.value,
                sequence=seq,
                conflated=entry.conflated,
                gap=entry.gap,
                removed=entry.removed,
            )
            ev.time.seconds, ev.time.nanos = divmod(entry.seen, 1_000_000_000)
        self._sequence = seq
        return response

    def _ready_throttled(self, limit: int) -> tuple[list[tuple[Topic, _Pending]], int]:
        """Like :func:`_within`, but only topics whose ``min_interval`` has passed."""
        last_emit = self._last_emit
        assert last_emit is not None
        loop = asyncio.get_running_loop()
        now = loop.time()
        interval = self.options.min_interval
        ready: list[tuple[Topic, _Pending]] = []
        next_due = 0.0
        size = 0
        for topic, entry in self._pending.items():
            last = last_emit.get(topic)
            if last is None or now - last >= interval:
                n = _event_size(topic, entry)
                if ready and size + n > BATCH_BYTES:
                    break
                size += n
                ready.append((topic, entry))
                if len(ready) >= limit:
                    break
            else:
                due = last + interval
                next_due = due if not next_due else min(next_due, due)
        for topic, _ in ready:
            del self._pending[topic]
            last_emit[topic] = now
        if len(last_emit) > 2 * len(self._refs) + 16:
            for topic in [t for t in last_emit if t not in self._refs]:
                del last_emit[topic]
        if next_due and self._throttle_timer is None:
            self._throttle_timer = loop.call_at(next_due, self._throttle_wake)
        return ready, size

    # -- ending ----------------------------------------------------------

    def close(self) -> None:
        """Release everything at once: topics, timers, the queue. Idempotent."""
        if self.closed:
            return
        self.closed = True
        for timer in (self._throttle_timer, self._sample_timer, self._heartbeat_timer):
            if timer is not None:
                timer.cancel()
        self._throttle_timer = self._sample_timer = self._heartbeat_timer = None
        hub = self._hub
        for topic in self._refs:
            hub._unsubscribe(self, topic)
        for exp in self._expansions:
            if exp.list_topic is not None:
                hub._unsubscribe(exp, exp.list_topic)
        self._refs.clear()
        self._expansions.clear()
        self._pending.clear()
        self._last_emit = None
        hub._streams.discard(self)


def _event_size(topic: Topic, entry: _Pending) -> int:
    """About the bytes ``entry`` takes as an Event (exact for the value, which is what can be big)."""
    value = entry.value
    n = len(value) if value.isascii() else len(value.encode())
    return n + len(topic.service) + len(topic.path) + 40


def _within(items: Iterable[tuple[Topic, _Pending]]) -> tuple[list[tuple[Topic, _Pending]], int]:
    """The first of ``items`` that add up to at most BATCH_BYTES (always at least one), and their size."""
    ready: list[tuple[Topic, _Pending]] = []
    size = 0
    for item in items:
        n = _event_size(*item)
        if ready and size + n > BATCH_BYTES:
            break
        size += n
        ready.append(item)
    return ready, size


class ListenHub:
    """Shares backend subscriptions among Listen streams; see the module docstring."""

    def __init__(self, router: Router, limits: Limits, call_timeout: float) -> None:
        self.router = router
        self.limits = limits
        self.call_timeout = call_timeout
        self._topics: dict[TopicKey, Topic] = {}
        self._streams: set[ListenStream] = set()
        self._tasks: set[asyncio.Task[Any]] = set()
        self._closing = False
        self._unwatch = router.watch(self._service_changed)

    @property
    def topic_count(self) -> int:
        """Backend subscriptions open right now."""
        return len(self._topics)

    @property
    def stream_count(self) -> int:
        """Listen streams open right now."""
        return len(self._streams)

    def open(
        self, selectors: Sequence[Selector], options: StreamOptions, on_ready: Callable[[], None]
    ) -> ListenStream:
        """A new stream (then ``start`` it, and ``close`` it when done); raises RESOURCE_EXHAUSTED."""
        if self._closing:
            from services.errors import Unavailable

            raise Unavailable("the gateway is shutting down")
        if len(self._streams) >= self.limits.max_streams:
            raise ResourceExhausted(
                f"too many Listen streams open ({self.limits.max_streams}, limits.max_streams)"
            )
        stream = ListenStream(self, selectors, options, on_ready)
        self._streams.add(stream)
        return stream

    # -- topics ----------------------------------------------------------

    async def _subscribe(self, sink: _Sink, key: TopicKey, backend: Backend, strict: bool) -> Topic | None:
        """Add ``sink`` to topic ``key``, opening it if needed; None when it does not exist (not strict)."""
        topic = self._topics.get(key)
        if topic is None or topic.dead:
            topic = Topic(key, backend)
            self._topics[key] = topic
            topic.opening = asyncio.get_running_loop().create_task(self._open(topic))
        topic.sinks.add(sink)
        opening = topic.opening
        assert opening is not None
        try:
            if not opening.done():
                await asyncio.shield(opening)
            else:
                opening.result()
        except PropertyError as exc:
            self._unsubscribe(sink, topic)
            if strict or exc.code not in (NotFound.default_code, InvalidArgument.default_code):
                raise
            log.debug("skipping %s %s: %s", key[0], key[1], exc.message)
            return None
        except BaseException:
            self._unsubscribe(sink, topic)
            raise
        return topic

    async def _open(self, topic: Topic) -> None:
        backend, path, params = topic.backend, topic.path, topic.params
        timeout = self.call_timeout
        try:
            topic.subscription = await bounded_call(
                backend.listen(path, topic.notify, params), timeout, lambda: f"{topic.service}: listen {path}"
            )
            topic.value = await bounded_call(
                backend.get(path, params), timeout, lambda: f"{topic.service}: get {path}"
            )
        except BaseException as exc:
            if self._topics.get(topic.key) is topic:
                del self._topics[topic.key]
            topic.dead = True
            if topic.subscription is not None:
                self._spawn(self._close_subscription(topic))
            if isinstance(exc, PropertyError | asyncio.CancelledError):
                raise
            from gateway.status import to_property_error

            raise to_property_error(exc, f"{topic.service}: listen {path}") from exc
        if not topic.sinks or topic.dead:
            self._drop(topic)

    def _unsubscribe(self, sink: _Sink, topic: Topic) -> None:
        topic.sinks.discard(sink)
        if not topic.sinks and topic.opening is not None and topic.opening.done():
            self._drop(topic)

    def _drop(self, topic: Topic) -> None:
        if self._topics.get(topic.key) is topic:
            del self._topics[topic.key]
        topic.dead = True
        if topic.subscription is not None:
            self._spawn(self._close_subscription(topic))

    async def _close_subscription(self, topic: Topic) -> None:
        sub, topic.subscription = topic.subscription, None
        if sub is None:
            return
        try:
            await asyncio.wait_for(sub.close(), self.call_timeout)
        except Exception:
            log.warning("closing the listen on %s %s failed", topic.service, topic.path, exc_info=True)

    def _spawn(self, coro: Any) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)

    def _task_done(self, task: asyncio.Task[Any]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("listen hub task failed", exc_info=task.exception())

    # -- services coming and going -----------------------------------------

    def _service_changed(self, name: str, backend: Backend | None) -> None:
        if backend is not None:
            for stream in list(self._streams):
                if stream._live:
                    stream._service_added(name, backend)
            return
        gone = [t for t in self._topics.values() if t.service == name]
        for topic in gone:
            del self._topics[topic.key]
            topic.notify(Change(topic.path, "", removed=True))
            topic.dead = True
        for stream in list(self._streams):
            stream._service_removed(name)
        for topic in gone:
            topic.sinks.clear()
            if topic.subscription is not None:
                self._spawn(self._close_subscription(topic))

    # -- shutting down ----------------------------------------------------

    def end_all(self) -> None:
        """End every stream cleanly (writers stop with OK); refuse new ones."""
        self._closing = True
        for stream in list(self._streams):
            stream.end()

    async def aclose(self) -> None:
        """End every stream and close every backend subscription."""
        self.end_all()
        self._unwatch()
        for stream in list(self._streams):
            stream.close()
        opening = []
        for topic in list(self._topics.values()):
            if topic.opening is not None and not topic.opening.done():
                topic.opening.cancel()
                opening.append(topic.opening)
            self._drop(topic)
        await asyncio.gather(*opening, return_exceptions=True)
        while self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
