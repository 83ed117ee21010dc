"""The history of properties: what each kept property was, and since when, for the History call.

The :class:`HistoryKeeper` follows the ``[history]`` selectors (``scout1/location``,
``*/location``, ``bench/*``) through the engine's listen hub as the gateway's own work (a stream
of ``own_work``: no caller's rules, what a caller may see is checked when it asks), and keeps each matched
property's latest ``size`` changes in a ring of its own. The rings together hold at most
``max_entries`` changes and ``max_bytes`` of values: past either, the oldest change of all goes
first. Binary values are kept only with ``binary = true`` (a camera would fill the bound with a
few seconds of frames).

A change is drained from the keeper's streams the moment the hub hands it over (on the stream's
``on_ready``, in the same call: not on a task, as :class:`~gateway.engine.listen.follow.HubFollow`
drains for the recorder), so the keeper's streams never conflate: the history holds every change
a Listen that keeps up would see, with the same time.

:meth:`HistoryKeeper.query` answers a History call: the events of the matched properties whose
time lies in ``[since, until)``, oldest first, at most ``limit`` (``truncated`` when more lay in
the range). An exact path the caller may not read is refused (PERMISSION_DENIED, as a Get); a
wildcard skips what the caller may not read (as a Listen). When the rings do not reach back to
``since`` and an :data:`OlderEvents` source is given (the recordings of the recorder,
``services.apps.recorder.reading.events_between``), the part before the rings comes from it.
"""

from __future__ import annotations

import asyncio
import dataclasses
import heapq
import logging
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from gateway.engine.events import Event, Selector, StreamOptions, events
from gateway.engine.guard import Guard
from gateway.engine.listen.follow import parse_selector
from gateway.engine.listen.hub import ListenHub
from gateway.engine.listen.stream import ListenStream
from gateway.engine.rules import Operation, Subject
from gateway.engine.sizes import MAX_MESSAGE_BYTES
from services.kernel.backoff import pauses
from services.kernel.errors import FailedPrecondition, InvalidArgument, NotFound, PropertyError
from services.kernel.paths import WILDCARD, compile_pattern, is_pattern, validate_service_name
from services.kernel.values import Value

log = logging.getLogger(__name__)

#: Bytes a kept change costs besides its value (its event, its slot in the ring, its place in the
#: order of all): measured with tracemalloc, about 250 for 100,000 changes of 100 properties.
ENTRY_OVERHEAD_BYTES = 256
#: Bytes an event takes in the answer besides its value (the Event's other fields and tags).
EVENT_WIRE_BYTES = 64
#: Seconds before a selector whose stream could not start (its service is not there yet) or
#: failed is tried again, doubling up to the most: the listen streams' own retry shape.
RETRY_FIRST_S = 0.5
RETRY_MAX_S = 10.0


class RecordedLike(Protocol):
    """One change read back from a recording (``services.apps.recorder.reading.RecordedEvent``)."""

    @property
    def service(self) -> str: ...
    @property
    def path(self) -> str: ...
    @property
    def value(self) -> Value: ...
    @property
    def time_ns(self) -> int: ...
    @property
    def sequence(self) -> int: ...
    @property
    def conflated(self) -> int: ...
    @property
    def gap(self) -> bool: ...
    @property
    def removed(self) -> bool: ...


class OlderEvents(Protocol):
    """Where values older than the rings come from: ``events_between(directory, service_glob,
    path_glob, since_ns, until_ns, limit)``, oldest first, ``until_ns`` included (the recorder's
    reading of its files)."""

    def __call__(
        self,
        directory: Path,
        service_glob: str,
        path_glob: str,
        *,
        since_ns: int | None,
        until_ns: int | None,
        limit: int,
    ) -> Sequence[RecordedLike]: ...


def kept_size(event: Event) -> int:
    """What a kept change counts against ``max_bytes``."""
    return len(event.value) + ENTRY_OVERHEAD_BYTES


class Ring:
    """The kept changes of one property, oldest first, and what it has kept since the start."""

    __slots__ = ("complete_since", "entries", "sequence")

    def __init__(self, started_ns: int) -> None:
        #: Each change as a Listen event, its ``sequence`` the ring's own count.
        self.entries: deque[Event] = deque()
        #: Changes kept so far (the sequence number of the latest).
        self.sequence = 0
        #: Since when the ring holds every change: when the keeper began following the property,
        #: or the time of its oldest change still kept once older ones were let go.
        self.complete_since = started_ns


@dataclass(frozen=True, slots=True)
class HistoryQuery:
    """A History call in the engine's types; times in ns since the epoch (None: open)."""

    service: str
    path: str
    since_ns: int | None = None
    until_ns: int | None = None
    #: 0: the ``[history] default_limit``.
    limit: int = 0


@dataclass(frozen=True, slots=True)
class HistoryReply:
    """The events of a History call, oldest first, and whether more lay in the range."""

    events: list[Event]
    truncated: bool = False


class HistorySettings(Protocol):
    """What the keeper reads of its settings: ``[history]`` (``gateway.config.HistorySection``,
    docs/recording.md, "History")."""

    @property
    def selectors(self) -> Sequence[str]: ...
    @property
    def size(self) -> int: ...
    @property
    def binary(self) -> bool: ...
    @property
    def max_entries(self) -> int: ...
    @property
    def max_bytes(self) -> int: ...
    @property
    def default_limit(self) -> int: ...
    @property
    def max_limit(self) -> int: ...
    @property
    def recordings(self) -> str: ...


class HistoryKeeper:
    """Keeps the history of the ``[history]`` selectors; see the module docstring."""

    def __init__(
        self,
        hub: ListenHub,
        settings: HistorySettings,
        guard: Guard | None = None,
        older: OlderEvents | None = None,
        clock: Callable[[], int] = time.time_ns,
    ) -> None:
        """``older``: where values older than the rings come from (None: nowhere), read in
        ``settings.recordings``; ``clock``: now, in ns since the epoch (a test's own)."""
        self.hub = hub
        self.settings = settings
        self.guard = guard or hub.guard
        self.older = older
        self.clock = clock
        self.selectors = [parse_selector(text) for text in settings.selectors]
        self.rings: dict[tuple[str, str], Ring] = {}
        #: Every kept change in the order it was kept, with its property: the oldest of all goes
        #: first. Entries a ring let go already are skipped when they come up (``is`` its oldest?).
        self._order: deque[tuple[tuple[str, str], Event]] = deque()
        self.kept_entries = 0
        self.kept_bytes = 0
        #: Changes not kept: binary values with ``binary = false``.
        self.skipped_binary = 0
        self._streams: list[ListenStream] = []
        self._tasks: set[asyncio.Task[None]] = set()
        self._closed = False

    # -- following -------------------------------------------------------

    def start(self) -> None:
        """Follow every selector, each in a task that starts it again when it cannot (yet)."""
        for selector in self.selectors:
            task = asyncio.get_running_loop().create_task(self._follow(selector))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _follow(self, selector: Selector) -> None:
        waits = pauses(RETRY_FIRST_S, RETRY_MAX_S)
        while not self._closed and not self.hub.closing:
            done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
            stream = self._open(selector, done)
            self._streams.append(stream)
            try:
                await stream.start()
                self._drain(stream, done)
                await done  # until the stream fails or ends
                if stream.error is not None:
                    log.info(
                        "history of %s/%s: %s; following it again",
                        selector.service,
                        selector.path,
                        stream.error.message,
                    )
                waits = pauses(RETRY_FIRST_S, RETRY_MAX_S)
            except PropertyError as exc:
                # Its service is not there (yet), or cannot be reached: tried again, quietly.
                log.debug("history of %s/%s: %s; trying again", selector.service, selector.path, exc.message)
            finally:
                stream.close()
                self._streams.remove(stream)
            if stream.ended:
                return
            await asyncio.sleep(next(waits))

    def _open(self, selector: Selector, done: asyncio.Future[None]) -> ListenStream:
        def ready() -> None:
            self._drain(stream, done)

        # The gateway's own work: no caller's rules (a caller is checked when it asks).
        stream = self.hub.open([selector], StreamOptions(), ready, own_work=True)
        return stream

    def _drain(self, stream: ListenStream, done: asyncio.Future[None]) -> None:
        """Keep what ``stream`` has ready, now (called by the stream whenever it has some)."""
        while (taken := stream.take()) is not None:
            if not isinstance(taken, tuple):
                continue  # the sync marker
            for (topic, _), event in zip(taken[0], events(taken), strict=True):
                first = (event.service, event.path) not in self.rings
                if first and topic.value is event.value and topic.stamp:
                    # A property's first value is as old as the topic heard it (a Listen may have
                    # opened it before), as a Get of it says.
                    self.keep(dataclasses.replace(event, time_ns=min(event.time_ns, topic.stamp)))
                else:
                    self.keep(event)
        if (stream.error is not None or stream.ended) and not done.done():
            done.set_result(None)

    def keep(self, event: Event) -> None:
        """Keep one change (a Listen event of a kept property)."""
        value = event.value
        if isinstance(value, bytes) and not self.settings.binary:
            self.skipped_binary += 1
            return
        key = (event.service, event.path)
        ring = self.rings.get(key)
        if ring is None:
            ring = self.rings[key] = Ring(event.time_ns)
        ring.sequence += 1
        kept = dataclasses.replace(event, sequence=ring.sequence)
        ring.entries.append(kept)
        self._order.append((key, kept))
        self.kept_entries += 1
        self.kept_bytes += kept_size(kept)
        if len(ring.entries) > self.settings.size:
            self._let_go(key, ring)
        settings = self.settings
        order = self._order
        while order and (
            self.kept_entries > settings.max_entries
            or self.kept_bytes > settings.max_bytes
            or len(order) > settings.max_entries
        ):
            old_key, old = order.popleft()
            old_ring = self.rings.get(old_key)
            if old_ring is not None and old_ring.entries and old_ring.entries[0] is old:
                self._let_go(old_key, old_ring)

    def _let_go(self, key: tuple[str, str], ring: Ring) -> None:
        """Let the oldest change of ``ring`` go; a ring left empty goes too."""
        old = ring.entries.popleft()
        self.kept_entries -= 1
        self.kept_bytes -= kept_size(old)
        if ring.entries:
            ring.complete_since = ring.entries[0].time_ns
        else:
            del self.rings[key]

    async def aclose(self) -> None:
        """Stop following; what is kept stays readable."""
        self._closed = True
        for stream in list(self._streams):
            stream.end()
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)

    # -- answering -------------------------------------------------------

    def query(self, query: HistoryQuery, subject: Subject) -> HistoryReply:
        """The kept events the query asks for (see the module docstring); raises InvalidArgument
        for a bad selector, PERMISSION_DENIED or UNAUTHENTICATED for an exact path the subject may
        not read, NOT_FOUND when nothing kept matches and no recordings are there to ask."""
        settings = self.settings
        service, path = query.service, query.path
        if not service:
            raise InvalidArgument("History needs a service (or * for every service)")
        if not path:
            raise InvalidArgument("History needs a property path (* segments allowed)")
        if service != WILDCARD:
            validate_service_name(service)
        matches_path = compile_pattern(path)
        exact = service != WILDCARD and not is_pattern(path)
        guard = self.guard
        if exact:
            guard.require(subject, service, path, Operation.READ)
        if query.limit < 0:
            raise InvalidArgument("limit must not be negative")
        limit = min(query.limit or settings.default_limit, settings.max_limit)
        since, until = query.since_ns, query.until_ns
        if since is not None and until is not None and until < since:
            raise InvalidArgument("until is before since")
        checks = guard.checks
        matched = [
            (key, ring)
            for key, ring in self.rings.items()
            if (service in (WILDCARD, key[0]))
            and matches_path(key[1])
            and (not checks or guard.may(subject, key[0], key[1], Operation.READ))
        ]
        if not matched and self.older is None and not self._follows(service, path):
            raise NotFound(f"{service}/{path}: no kept history matches ([history] selectors)")
        # The rings hold everything since the latest of their starts; before it, the recordings.
        boundary = max((ring.complete_since for _, ring in matched), default=self.clock())
        older: list[Event] = []
        since_in_rings: int | None = since
        if self.older is not None and (since is None or since < boundary):
            older_until = boundary if until is None else min(until, boundary)
            older = self._older(
                service, path, since=since, until=older_until, limit=limit + 1, subject=subject
            )
            since_in_rings = boundary
        recent = heapq.merge(
            *(self._between(ring, since_in_rings, until) for _, ring in matched),
            key=lambda e: e.time_ns,
        )
        out: list[Event] = []
        size = 0
        truncated = False
        for event in _chain(older, recent):
            n = len(event.value) + len(event.service) + len(event.path) + EVENT_WIRE_BYTES
            if len(out) >= limit or (out and size + n > MAX_MESSAGE_BYTES):
                truncated = True
                break
            out.append(event)
            size += n
        return HistoryReply(out, truncated)

    def _follows(self, service: str, path: str) -> bool:
        """Whether a ``[history]`` selector could match ``service``/``path`` (a property kept but
        not changed yet is an empty history, not an unknown one)."""
        for sel in self.selectors:
            if sel.service not in (WILDCARD, service) and service != WILDCARD:
                continue
            if is_pattern(path) or is_pattern(sel.path) or sel.path == path:
                return True
        return False

    @staticmethod
    def _between(ring: Ring, since: int | None, until: int | None) -> Iterable[Event]:
        for kept in ring.entries:
            t = kept.time_ns
            if since is not None and t < since:
                continue
            if until is not None and t >= until:
                return
            yield kept

    def _older(
        self, service: str, path: str, *, since: int | None, until: int | None, limit: int, subject: Subject
    ) -> list[Event]:
        """Events before the rings, from the recordings, that ``subject`` may read."""
        assert self.older is not None
        # ``until`` is excluded here, included by the recordings' reader.
        last = None if until is None else until - 1
        found = self.older(
            Path(self.settings.recordings), service, path, since_ns=since, until_ns=last, limit=limit
        )
        guard = self.guard
        binary = self.settings.binary
        return [
            Event(e.service, e.path, e.value, e.sequence, e.time_ns, e.conflated, e.gap, e.removed)
            for e in found
            if (binary or not isinstance(e.value, bytes))
            and guard.may(subject, e.service, e.path, Operation.READ)
        ]


def kept_history(keeper: HistoryKeeper | None, query: HistoryQuery, subject: Subject) -> HistoryReply:
    """``keeper``'s answer to ``query``; FAILED_PRECONDITION when the gateway keeps no history."""
    if keeper is None:
        raise FailedPrecondition(
            "this gateway keeps no history: give [history] selectors in its config (docs/recording.md)"
        )
    return keeper.query(query, subject)


def _chain(first: list[Event], then: Iterable[Event]) -> Iterable[Event]:
    yield from first
    yield from then
