"""One Listen stream: its selectors, wildcard expansion, conflating queue and pacing.

A stream (:class:`ListenStream`) is one client's Listen: its selectors
(``*`` may stand for the service or for one path segment), its options, and
one conflating queue (:class:`services.kernel.conflation.ConflatingQueue`) that
holds, per topic, the latest value not yet sent and how many values it
replaced. Memory is bounded by the number of topics the stream matches, never
by how fast values change. The stream's writer (the gRPC handler, or the
Session writer) is woken by ``on_ready`` and calls :meth:`ListenStream.take`
until it returns None; each call drains what is ready into one batch of events
(:mod:`gateway.engine.events`), or hands a marker (sync, heartbeat). A change is
queued as its :class:`~gateway.engine.events.SharedEvent`, made once for every
stream it reaches.

Wildcards follow the service: ``*`` as service follows the router's adds and
removes (the hub calls :meth:`ListenStream.service_added`); ``*`` in a path is
expanded by the service itself (``Backend.match_properties``: the model of each
match, never the ``properties`` list, which a registry of a few hundred services
makes longer than a value may be) and follows where the service's property list
changes (``Backend.listen_properties``, one topic per service shared by every
stream): below each name where it changed, the service is asked for the matches
again, so a registration costs a lookup of that one entry, not of the whole list.
A selector with ``*`` (service or path) matches only what a Listen may follow:
actions, queries and properties that need a parameter are skipped silently, as
the models of the matches say.

An expansion that cannot be made fails the stream with the service's error, naming the
service and the pattern (a remote list too long to read is INVALID_ARGUMENT), unless
the selector skips that error: a ``*`` service skips NOT_FOUND and INVALID_ARGUMENT for
good (logged), and every wildcard skips a service that cannot be reached (below).

A wildcard never fails because a service cannot be reached (UNAVAILABLE,
DEADLINE_EXCEEDED) when the stream opens or when it expands later: the part it
could not follow is skipped and tried again in the background (one task per
(selector, service), pauses from ``RETRY_FIRST_S`` doubling to ``RETRY_MAX_S``,
only while the stream is open and the service is still the router's); once it
answers, its current values are queued marked ``gap`` and followed from then on.
An exact selector (no ``*`` anywhere) fails with the service's error instead;
when its service joins the router again while it cannot answer yet (a proxy
still connecting), it is tried the same way for ``JOIN_RETRY_S`` before the
stream fails.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from itertools import islice

from gateway.config import Limits
from gateway.engine.events import Mark, Ready, Selector, SharedEvent, StreamOptions, Taken
from gateway.engine.listen.matched import MatchedPaths
from gateway.engine.listen.topics import (
    MISSING,
    NOTHING,
    PROPERTY_LIST,
    REFUSED,
    UNREACHABLE,
    Topic,
    TopicChange,
    TopicKey,
    Topics,
)
from gateway.engine.router import Router
from gateway.engine.rules import Subject
from gateway.engine.sizes import BATCH_BYTES, MAX_MESSAGE_BYTES
from services.kernel.backend import Backend, Change
from services.kernel.backoff import pauses, wait_to_retry
from services.kernel.conflation import ConflatingQueue
from services.kernel.errors import Code, PropertyError, ResourceExhausted
from services.kernel.model import PropertyModel
from services.kernel.paths import WILDCARD, is_pattern

log = logging.getLogger(__name__)

#: Seconds before a wildcard tries again a part it skipped because its service could not be
#: reached, doubled after each failed try up to ``RETRY_MAX_S``: the shape of the proxies' own
#: reconnect backoff (0.2 s to 10 s), so a device that is back is followed within about 10 s
#: of its proxy reconnecting, and a device that stays away costs one try per 10 s per stream.
RETRY_FIRST_S = 0.5
RETRY_MAX_S = 10.0
#: Seconds an exact selector keeps trying its service when it joins the router again while it
#: cannot answer yet (a proxy still connecting to its device) before the stream fails with the
#: service's error; the registry's register_timeout.
JOIN_RETRY_S = 10.0
#: What a wildcard skips: a property that is not there, a service that cannot be reached, and
#: what the rules refuse the stream's subject in a service that another reads for it.
WILDCARD_SKIPS = MISSING | UNREACHABLE | REFUSED
#: Names below which a service's property list changed that an expansion remembers until it asks
#: the service again; past this many (a burst of registrations) it asks for every match at once.
MAX_CHANGED_NAMES = 1024


def retry_pauses() -> Iterator[float]:
    """The pauses before each new try of a skipped part: ``RETRY_FIRST_S``, doubled up to ``RETRY_MAX_S``."""
    return pauses(RETRY_FIRST_S, RETRY_MAX_S)


def within(items: Iterable[Ready]) -> tuple[list[Ready], int]:
    """The first of ``items`` that add up to at most BATCH_BYTES (always at least one), and their size."""
    ready: list[Ready] = []
    size = 0
    for item in items:
        n = item[1].value.size
        if ready and size + n > BATCH_BYTES:
            break
        size += n
        ready.append(item)
    return ready, size


class _Expansion:
    """A path pattern expanded on one service; follows where the service's property list changes.

    It matches only the properties a Listen may follow (``Access.listenable``: never an
    action, nor a query, nor a property that needs a parameter), as the model of each match
    says; a name the service does not describe counts as listenable. Names the stream's
    subject may not read are skipped too.
    """

    __slots__ = (
        "changed",
        "gap",
        "list_topic",
        "matched",
        "matching",
        "ready",
        "selector",
        "service",
        "skip",
        "stream",
    )

    def __init__(self, stream: ListenStream, selector: Selector, service: str, skip: frozenset[Code]) -> None:
        self.stream = stream
        self.selector = selector
        self.service = service
        #: The errors of a later match that are skipped rather than ending the stream.
        self.skip = skip
        self.matched = MatchedPaths()
        self.list_topic: Topic | None = None
        #: Names below which the list changed since the service was last asked ("": anywhere),
        #: and whether one of those changes came after a gap.
        self.changed: set[str] = set()
        self.gap = False
        #: A task is asking the service about ``changed`` (one at a time per expansion).
        self.matching = False
        #: The first matches are followed: changes are asked about from now on.
        self.ready = False

    def accept(self, found: Iterable[PropertyModel]) -> set[str]:
        """The names among ``found`` this stream follows."""
        stream, service = self.stream, self.service
        return {
            p.name
            for p in found
            if p.access.listenable and not p.needs_parameters and stream.may_read(service, p.name)
        }

    def note(self, below: str, gap: bool) -> bool:
        """The list changed below ``below``; True when a task must start asking about it."""
        changed = self.changed
        if not below or "" in changed or len(changed) >= MAX_CHANGED_NAMES:
            changed.clear()
            changed.add("")
        else:
            changed.add(below)
        self.gap = self.gap or gap
        if self.matching or not self.ready:
            return False
        self.matching = True
        return True

    def take(self) -> tuple[list[str], bool]:
        """The names to ask about, and whether their changes came after a gap; forgotten here."""
        names, gap = sorted(self.changed), self.gap
        self.changed, self.gap = set(), False
        return names, gap

    def topic_changed(self, news: TopicChange) -> None:
        change = news[1]
        if change.removed:  # the service left the router: the stream forgets the expansion
            return
        self.stream.list_changed(self, change.path, change.gap)


class _Retry:
    """What a wildcard skipped on one service because it could not be reached, and the task
    that tries it again (see :meth:`ListenStream._retry`)."""

    __slots__ = ("backend", "below", "give_up_at", "paths", "task", "whole")

    def __init__(self, backend: Backend, give_up_at: float | None) -> None:
        self.backend = backend
        #: Loop time after which a try that fails ends the stream (an exact selector whose
        #: service joined again); None: never (a wildcard).
        self.give_up_at = give_up_at
        #: The selector's whole part on the service: an exact path, or the ``properties`` list.
        self.whole = False
        #: Matched paths of the service's expansion that could not be joined.
        self.paths: set[str] = set()
        #: Names below which the expansion could not ask the service for its matches.
        self.below: set[str] = set()
        self.task: asyncio.Task[None] | None = None

    @property
    def pending(self) -> bool:
        return self.whole or bool(self.paths) or bool(self.below)


class ListenStream:
    """One Listen: selectors, options and the conflating queue; see the module docstring."""

    __slots__ = (
        "_caller",
        "_expansions",
        "_heartbeat_due",
        "_heartbeat_timer",
        "_last_emit",
        "_last_sent",
        "_limits",
        "_live",
        "_may_read",
        "_on_close",
        "_on_ready",
        "_pending",
        "_refs",
        "_retries",
        "_router",
        "_sample_flush",
        "_sample_timer",
        "_sequence",
        "_signalled",
        "_sync_after",
        "_sync_due",
        "_throttle_timer",
        "_topics",
        "closed",
        "conflated",
        "ended",
        "error",
        "events_sent",
        "options",
        "selectors",
    )

    def __init__(
        self,
        router: Router,
        topics: Topics,
        limits: Limits,
        *,
        selectors: Sequence[Selector],
        options: StreamOptions,
        on_ready: Callable[[], None],
        on_close: Callable[[ListenStream], None],
        may_read: Callable[[str, str], bool] | None = None,
        caller: Subject | None = None,
    ) -> None:
        """Called by :meth:`gateway.engine.listen.ListenHub.open`; ``on_close`` tells the hub the
        stream is gone; ``may_read(service, path)`` says what the stream's subject may read
        (None: everything); ``caller``: that subject, when the rules are checked (what a service reads for the
        stream is checked as it, :mod:`gateway.engine.behalf`)."""
        self._may_read = may_read
        self._caller = caller
        self._router = router
        self._topics = topics
        self._limits = limits
        self._on_close = on_close
        self.selectors = tuple(selectors)
        self.options = options
        self._on_ready = on_ready
        self._pending: ConflatingQueue[Topic, SharedEvent] = ConflatingQueue()
        self._refs: dict[Topic, int] = {}
        #: Wildcard paths expanded per service; () until the first (most streams have none).
        self._expansions: Sequence[_Expansion] = ()
        #: One per (selector, service) with a skipped part that is tried again; cancelled at close.
        #: None until the first (most streams never retry): an idle stream stays small.
        self._retries: dict[tuple[Selector, str], _Retry] | None = None
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
        #: Events handed to the writer, and values replaced while waiting (read by the metrics).
        self.events_sent = 0
        self.conflated = 0

    def may_read(self, service: str, path: str) -> bool:
        """Whether the stream's subject may read ``service``/``path``: wildcards skip what it may not."""
        return self._may_read is None or self._may_read(service, path)

    # -- setting up ------------------------------------------------------

    async def start(self) -> None:
        """Expand the selectors, subscribe, read current values; then the stream is live.

        Raises NOT_FOUND for an unknown service or a concrete path that does
        not exist, RESOURCE_EXHAUSTED when a limit is passed, and for an exact
        selector the service's own error (UNAVAILABLE when it cannot be reached).
        """
        router = self._router
        for sel in self.selectors:
            if sel.service == WILDCARD:
                for name, backend in router.items():
                    await self._expand(sel, name, backend)
            elif is_pattern(sel.path):
                # A wildcard path skips a service the registry marked down, as it skips any it
                # cannot reach: the lookup that ignores the mark, and the service answers itself.
                await self._expand(sel, sel.service, router.lookup(sel.service))
            else:
                await self._expand(sel, sel.service, router.backend(sel.service))
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

    async def _expand(
        self, sel: Selector, service: str, backend: Backend, gap: bool = False, rejoined: bool = False
    ) -> None:
        """Follow what ``sel`` matches on ``service``; ``gap``: its first values are marked so.

        ``rejoined``: a named service that joined the router again while the stream is open;
        what it does not have is skipped then, as a wildcard skips it, not an error.
        """
        if self.closed:
            return
        named = sel.service != WILDCARD
        if not is_pattern(sel.path):
            # An exact selector was checked when the stream opened; a wildcard service skips.
            if named:
                skips = MISSING if rejoined else NOTHING
                await self._join((service, sel.path, sel.params), backend, skips, gap)
            elif self.may_read(service, sel.path):
                skipped = await self._join((service, sel.path, sel.params), backend, WILDCARD_SKIPS, gap)
                if skipped is not None:
                    self._skipped(sel, service, backend, None)
            return
        # A named service must answer; only a service that cannot be reached is skipped.
        skip = UNREACHABLE if named and not rejoined else WILDCARD_SKIPS
        exp = _Expansion(self, sel, service, skip)
        # Its list is followed before it is asked: no change can fall between the two.
        list_topic = await self._topics.subscribe(exp, (service, PROPERTY_LIST, ()), backend, skip)
        if not isinstance(list_topic, Topic):
            if list_topic.code in UNREACHABLE:
                self._skipped(sel, service, backend, None)
            return
        exp.list_topic = list_topic
        found: list[PropertyModel] | None = None
        if not self.closed:
            try:
                found = await self._topics.match(service, backend, sel.path, caller=self._caller)
            except PropertyError as exc:
                self._topics.unsubscribe(exp, list_topic)
                if exc.code not in skip:
                    raise
                if exc.code in UNREACHABLE:
                    self._skipped(sel, service, backend, None)
                else:
                    log.warning("a wildcard Listen on %s skips it: %s", service, exc.message)
                return
        if self.closed or found is None:
            self._topics.unsubscribe(exp, list_topic)
            return
        self._expansions = [*self._expansions, exp]
        exp.matched = MatchedPaths(exp.accept(found))
        await self._join_many(exp, list(exp.matched), gap)
        exp.ready = True
        if exp.changed and not exp.matching:
            exp.matching = True
            self._topics.spawn(self._follow_changes(exp))

    async def _join_many(self, exp: _Expansion, paths: Iterable[str], gap: bool) -> None:
        backend = exp.list_topic.backend if exp.list_topic else None
        if backend is None:
            return
        keys = [(exp.service, p, exp.selector.params) for p in paths]
        if len(keys) == 1:
            results = [await self._join(keys[0], backend, WILDCARD_SKIPS, gap)]
        elif keys:
            results = await asyncio.gather(*(self._join(k, backend, WILDCARD_SKIPS, gap) for k in keys))
        else:
            return
        for key, skipped in zip(keys, results, strict=True):
            if skipped is not None:
                self._skipped(exp.selector, exp.service, backend, key[1])

    async def _join(
        self, key: TopicKey, backend: Backend, skip: frozenset[Code], gap: bool = False
    ) -> PropertyError | None:
        """Share the topic ``key``; queue its current value unless updates only (and not yet live).

        Returns the error for which it was skipped when that says the service cannot be
        reached (the caller tries it again later); None when joined, or skipped for good.
        ``gap``: the value is queued marked as a gap, also with updates only (the client
        missed the time the service could not be reached).
        """
        if self.closed:
            return None
        topic = self._topics.get(key)
        if topic is not None and topic in self._refs:
            self._refs[topic] += 1
            return None
        limit = self._limits.max_stream_properties
        if len(self._refs) >= limit:
            raise self._too_many()
        joined = await self._topics.subscribe(self, key, backend, skip, self._caller)
        if not isinstance(joined, Topic):
            return joined if joined.code in UNREACHABLE else None
        topic = joined
        if self.closed or topic.dead:
            self._topics.unsubscribe(self, topic)
            return None
        if topic in self._refs:  # joined twice concurrently
            self._refs[topic] += 1
            self._topics.unsubscribe(self, topic)
            return None
        if len(self._refs) >= limit:
            self._topics.unsubscribe(self, topic)
            raise self._too_many()
        self._refs[topic] = 1
        # With updates only, a property that appears once the stream is live is a change (from
        # absent to its first value), as its going is (``removed``): it is sent.
        if (gap or self._live or not self.options.updates_only) and topic not in self._pending:
            now = time.time_ns()
            self._pending.put(topic, SharedEvent(topic.service, topic.path, topic.value, now), now, gap)
            if self._live:
                self._signal()
        return None

    # -- parts skipped because their service could not be reached ----------

    def _skipped(
        self,
        sel: Selector,
        service: str,
        backend: Backend,
        path: str | None,
        *,
        give_up_after: float | None = None,
        below: str | None = None,
    ) -> None:
        """Remember a part ``sel`` could not follow on ``service`` (None: all of it); try it later.

        ``give_up_after``: seconds after which a try that still fails ends the stream.
        ``below``: the part is the expansion's matches below that name (``path`` is None then).
        """
        if self.closed:
            return
        key = (sel, service)
        retries = self._retries
        if retries is None:
            retries = self._retries = {}
        retry = retries.get(key)
        if retry is None or retry.backend is not backend:
            if retry is not None and retry.task is not None:
                retry.task.cancel()
            give_up_at = None if give_up_after is None else asyncio.get_running_loop().time() + give_up_after
            retry = _Retry(backend, give_up_at)
            retries[key] = retry
            retry.task = self._topics.spawn(self._retry(key, retry))
        if below is not None:
            retry.below.add(below)
        elif path is None:
            retry.whole = True
        else:
            retry.paths.add(path)

    async def _retry(self, key: tuple[Selector, str], retry: _Retry) -> None:
        """Try the skipped parts again, less and less often, until they answer or the stream ends."""
        sel, service = key
        pauses = retry_pauses()
        loop = asyncio.get_running_loop()
        try:
            while retry.pending:
                pause = next(pauses)
                if retry.give_up_at is not None:  # the last try comes when it gives up, not later
                    pause = min(pause, max(retry.give_up_at - loop.time(), 0.0))
                await wait_to_retry(retry.backend, pause)
                if self.closed or not self._serves(service, retry.backend):
                    return
                whole, paths, below = retry.whole, retry.paths, retry.below
                retry.whole, retry.paths, retry.below = False, set(), set()
                # What a wildcard fails on again is put back into ``retry`` by ``_skipped``.
                try:
                    if whole:
                        rejoined = retry.give_up_at is not None
                        await self._expand(sel, service, retry.backend, gap=True, rejoined=rejoined)
                    else:
                        exp = self._expansion(sel, service)
                        if exp is not None and below:
                            await self._rematch(exp, sorted(below), gap=True)
                        if exp is not None and paths:
                            await self._join_many(exp, sorted(p for p in paths if p in exp.matched), gap=True)
                except PropertyError as exc:
                    # An exact selector raises; it is tried again until it gives up.
                    give_up_at = retry.give_up_at
                    if exc.code in UNREACHABLE and give_up_at is not None and loop.time() < give_up_at:
                        retry.whole = True
                        continue
                    self.fail(exc)  # or a limit passed now that the service answers
                    return
        finally:
            if self._retries is not None and self._retries.get(key) is retry:
                del self._retries[key]

    def _expansion(self, sel: Selector, service: str) -> _Expansion | None:
        for exp in self._expansions:
            if exp.selector == sel and exp.service == service:
                return exp
        return None

    @property
    def queued(self) -> int:
        """Properties whose latest value waits to be sent (at most one entry per property)."""
        return len(self._pending)

    @property
    def retrying(self) -> int:
        """How many (selector, service) parts skipped as unreachable are being tried again."""
        return len(self._retries) if self._retries is not None else 0

    def _too_many(self) -> ResourceExhausted:
        limit = self._limits.max_stream_properties
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
        if announce and not topic.removed:  # else the backend's own removal is queued or sent already
            # Told as a change of the topic is, to this stream alone: it is gone for this stream.
            self.topic_changed((topic, Change(topic.path, "", removed=True), time.time_ns()))
        del self._refs[topic]
        self._topics.unsubscribe(self, topic)
        if not announce:
            self._pending.discard(topic)

    # -- following where a service's property list changes ---------------------

    def list_changed(self, exp: _Expansion, below: str, gap: bool) -> None:
        """The property list of ``exp``'s service changed below ``below`` ("": anywhere)."""
        if not self.closed and exp.note(below, gap):
            self._topics.spawn(self._follow_changes(exp))

    async def _follow_changes(self, exp: _Expansion) -> None:
        """Ask the service about each change noted, until none is left (one task per expansion)."""
        try:
            while exp.changed and not self.closed and exp.list_topic is not None and not exp.list_topic.dead:
                names, gap = exp.take()
                await self._rematch(exp, names, gap)
        except PropertyError as exc:
            self.fail(exc)
        finally:
            exp.matching = False

    async def _rematch(self, exp: _Expansion, names: list[str], gap: bool) -> None:
        """Ask the service for the matches below each of ``names`` again; join the new ones, leave
        the ones gone. Below a name the service cannot be asked about now, it is asked again
        later (:meth:`_retry`); an error the selector does not skip is raised."""
        list_topic = exp.list_topic
        if list_topic is None:
            return
        backend = list_topic.backend
        for i, below in enumerate(names):
            try:
                found = await self._topics.match(
                    exp.service, backend, exp.selector.path, below, caller=self._caller
                )
            except PropertyError as exc:
                if exc.code in UNREACHABLE:
                    for name in names[i:]:
                        self._skipped(exp.selector, exp.service, backend, None, below=name)
                    return
                if exc.code not in exp.skip:
                    raise
                log.warning("a wildcard Listen on %s keeps what it matched: %s", exp.service, exc.message)
                continue
            if self.closed:
                return
            await self._reconcile(exp, below, exp.accept(found), gap)

    async def _reconcile(self, exp: _Expansion, below: str, found: set[str], gap: bool) -> None:
        """``found`` is what ``exp`` matches below ``below`` now: join what is new, leave what is gone."""
        before = exp.matched.below(below)
        for path in before - found:
            exp.matched.discard(path)
            topic = self._topics.get((exp.service, path, exp.selector.params))
            if topic is not None:
                self._leave(topic, announce=True)
        new = sorted(found - before)
        exp.matched.update(new)
        if not new:
            return
        await self._join_many(exp, new, gap)
        # A path may have gone again while joining.
        for path in new:
            if path not in exp.matched:
                topic = self._topics.get((exp.service, path, exp.selector.params))
                if topic is not None:
                    self._leave(topic, announce=True)

    def service_added(self, name: str, backend: Backend) -> None:
        """A service joined the router: a selector whose service is ``*`` expands on it too."""
        if not self._live:
            return
        for sel in self.selectors:
            if sel.matches_service(name):
                self._topics.spawn(self._expand_later(sel, name, backend))

    async def _expand_later(self, sel: Selector, name: str, backend: Backend) -> None:
        """Follow a service that joined; one that cannot be reached yet is tried again later."""
        try:
            await self._expand(sel, name, backend, rejoined=True)
        except PropertyError as exc:
            if exc.code in UNREACHABLE and sel.service != WILDCARD and not is_pattern(sel.path):
                # The named service joined again, its proxy still connecting: the stream waits
                # for it a while (a wildcard skips it and waits as long as the stream is open).
                self._skipped(sel, name, backend, None, give_up_after=JOIN_RETRY_S)
                return
            self.fail(exc)

    def _serves(self, name: str, backend: Backend) -> bool:
        try:
            return self._router.lookup(name) is backend
        except PropertyError:
            return False

    def service_removed(self, name: str) -> None:
        """A service left the router (its topics have told the stream ``removed``)."""
        for topic in [t for t in self._refs if t.service == name]:
            del self._refs[topic]
        if self._expansions:
            self._expansions = [e for e in self._expansions if e.service != name]
        retries = self._retries or {}
        for key in [k for k in retries if k[1] == name]:
            task = retries.pop(key).task
            if task is not None:
                task.cancel()

    # -- receiving -------------------------------------------------------

    def topic_changed(self, news: TopicChange) -> None:
        """A change on a topic this stream shares (called by :meth:`Topic.notify`), queued.

        Every stream the change reaches queues the same :class:`SharedEvent`: the first one makes
        it and leaves it on the topic, the others find it there (the same time, the same value).
        """
        topic, change, seen_ns = news
        if topic not in self._refs:
            return
        event = topic.event
        if event is None or event.stamp != seen_ns or event.value is not change.value:
            event = topic.event = SharedEvent(topic.service, topic.path, change.value, seen_ns)
        if not self._pending.put(topic, event, seen_ns, change.gap, change.removed):
            self.conflated += 1
        # _signal, written out: this runs for every stream a change reaches.
        if self._live and not self._sample_flush and not self._signalled:
            self._signalled = True
            self._on_ready()

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
        pending = self._pending
        for topic in self._refs:
            if topic not in pending:
                pending.put(topic, SharedEvent(topic.service, topic.path, topic.value, now), now)
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

    def take(self) -> Taken | None:
        """What the next response carries: a batch of events (the events ready and the stream's
        sequence number before the first), a marker, or None when nothing is ready.

        A value is the one every stream shares, not a copy: a front writes it from there.
        """
        self._signalled = False
        if not self._live or self.closed or self.error is not None:
            return None
        if not self._pending and not self._sync_due:
            return self._heartbeat()  # what the rest comes to with nothing queued: the commonest case
        if self._sync_due and (self._sync_after <= 0 or not self._pending):
            self._sync_due = False
            self._sent()
            return Mark.SYNC
        limit = self.options.max_batch
        if self._sync_due:
            limit = min(limit, self._sync_after)
        elif self._sample_flush:
            if self._sample_flush < 0:
                return self._heartbeat()
            limit = min(limit, self._sample_flush)
        ready = self._drain(limit)
        count = len(ready) if ready is not None else 0
        if self._sync_due:
            self._sync_after -= count
        elif self._sample_flush > 0:
            self._sample_flush = max(self._sample_flush - count, 0) or -1
        if ready is not None:
            self._sent()
            return ready, self._sequence - len(ready)
        if self._sync_due:
            self._sync_due = False
            self._sent()
            return Mark.SYNC
        return self._heartbeat()

    def _heartbeat(self) -> Mark | None:
        if self._heartbeat_due:
            self._sent()
            return Mark.HEARTBEAT
        return None

    def _sent(self) -> None:
        self._heartbeat_due = False
        if self._heartbeat_timer is not None:
            self._last_sent = asyncio.get_running_loop().time()

    def _drain(self, limit: int) -> list[Ready] | None:
        """The events ready, at most ``limit``, numbered; None when there are none."""
        pending = self._pending
        if not pending:
            return None
        ready: list[Ready]
        if self._last_emit is not None and self._sync_after <= 0:
            ready, size = self._ready_throttled(limit)
        elif len(pending) == 1:  # one change since the last response: the commonest case
            ready = pending.take()
            size = ready[0][1].value.size
        else:
            ready, size = within(islice(pending.items(), limit))
            if len(ready) == len(pending):
                pending.clear()  # all of it, as the commonest batch is: no list taken twice
            else:
                pending.take(len(ready))
        if not ready:
            return None
        if len(ready) == 1 and size > MAX_MESSAGE_BYTES:
            event = ready[0][1].value
            self.fail(
                ResourceExhausted(
                    f"{event.service}/{event.path}: a value of {size} bytes does not fit in one message "
                    f"(at most {MAX_MESSAGE_BYTES} bytes)"
                )
            )
            return None
        self._sequence += len(ready)
        self.events_sent += len(ready)
        return ready

    def _ready_throttled(self, limit: int) -> tuple[list[Ready], int]:
        """Like :func:`within`, but only topics whose ``min_interval`` has passed."""
        last_emit = self._last_emit
        assert last_emit is not None
        loop = asyncio.get_running_loop()
        now = loop.time()
        interval = self.options.min_interval
        next_due = 0.0

        def due() -> Iterator[Ready]:
            # The topics whose interval has passed; of the others, when the first is due again.
            nonlocal next_due
            for topic, entry in self._pending.items():
                last = last_emit.get(topic)
                if last is None or now - last >= interval:
                    yield topic, entry
                else:
                    next_due = last + interval if not next_due else min(next_due, last + interval)

        ready, size = within(islice(due(), limit))
        for topic, _ in ready:
            self._pending.discard(topic)
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
        for retry in (self._retries or {}).values():
            if retry.task is not None:
                retry.task.cancel()
        self._retries = None
        topics = self._topics
        for topic in self._refs:
            topics.unsubscribe(self, topic)
        for exp in self._expansions:
            if exp.list_topic is not None:
                topics.unsubscribe(exp, exp.list_topic)
        self._refs.clear()
        self._expansions = ()
        self._pending.clear()
        self._last_emit = None
        self._on_close(self)
