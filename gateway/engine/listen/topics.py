"""Topics: one backend subscription per (service, path, parameters), shared by every stream.

A topic is opened by the first stream that wants it (a Listen on the backend
that brings the current value, :meth:`Backend.listen_current`: a device's
LISTEN answers with it, other backends Get it once the Listen is in place), caches
the latest value, so a stream joining a busy topic needs no backend call, and
is closed when its last sink leaves.

A topic whose path is :data:`PROPERTY_LIST` follows where a service's property list changes
(:meth:`Backend.listen_properties`) and carries no value: each change's ``path`` names where.
The wildcard expansions of every stream on that service share it, and each asks the service
for its own matches there (:meth:`Topics.match`).

A wildcard does not fail on what it cannot follow: :meth:`Topics.subscribe` takes the codes
to skip (``MISSING``: not there or not listenable; ``UNREACHABLE``: the service cannot be
reached now, which the stream tries again later; ``REFUSED``: the rules refuse it) and hands
back the error instead of raising.

**Checked as each stream's subject.** With rules, a topic opens as the subject of the stream
that opens it (:data:`services.kernel.directory.CALLER`), so that what a service reads for it (a
group's member) is checked as that subject, and those reads are noted
(:class:`gateway.engine.behalf.Trail`); a stream of another subject that joins the topic later is
checked for each of them before it hears anything.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable, Collection, Coroutine, Mapping
from typing import Any, Protocol

from gateway.engine.behalf import TRAIL, Trail
from gateway.engine.events import SharedEvent
from gateway.engine.guard import Guard
from gateway.engine.router import bounded_call
from gateway.engine.rules import Subject
from gateway.engine.status import to_property_error
from services.kernel.backend import NO_PARAMS, Backend, Change, OnRaise, Subscription, tell_each
from services.kernel.directory import CALLER, context_for
from services.kernel.errors import Code, PropertyError
from services.kernel.model import PropertyModel
from services.kernel.values import Value

log = logging.getLogger(__name__)

TopicKey = tuple[str, str, tuple[tuple[str, str], ...]]

#: A wildcard skips a property that is not there (or cannot be listened to) for good.
MISSING: frozenset[Code] = frozenset({Code.NOT_FOUND, Code.INVALID_ARGUMENT})
#: A wildcard skips a service that cannot be reached now, and tries it again in the background.
UNREACHABLE: frozenset[Code] = frozenset({Code.UNAVAILABLE, Code.DEADLINE_EXCEEDED})
#: A wildcard skips what the rules refuse its subject (what a service reads for a topic, too).
REFUSED: frozenset[Code] = frozenset({Code.PERMISSION_DENIED, Code.UNAUTHENTICATED})
#: An exact selector skips nothing: the caller asked for exactly that.
NOTHING: frozenset[Code] = frozenset()
#: The path of the topic that follows a service's property list: never a property's path (no
#: concrete path has a ``*`` segment).
PROPERTY_LIST = "*"


#: What a topic tells each of its sinks of a change, in one object: the topic, the change, and when
#: the gateway heard it (nanoseconds since the epoch). Made once per change; each sink is called
#: with it alone (the fan-out's calls take one argument: :func:`services.kernel.backend.tell_each`).
TopicChange = tuple["Topic", Change, int]


class Sink(Protocol):
    """Who hears a topic's changes: a stream, or a stream's wildcard expansion."""

    def topic_changed(self, news: TopicChange) -> None: ...


class Topic:
    """One shared backend subscription and the latest value seen on it."""

    __slots__ = (
        "backend",
        "dead",
        "event",
        "heard",
        "key",
        "opener",
        "opening",
        "params",
        "path",
        "removed",
        "service",
        "sinks",
        "stamp",
        "subscription",
        "trail",
        "value",
    )

    def __init__(self, key: TopicKey, backend: Backend) -> None:
        self.key = key
        self.service, self.path, params = key
        self.params: Mapping[str, str] = dict(params) if params else NO_PARAMS
        self.backend = backend
        #: Each sink and its ``topic_changed``, called with each change (:data:`TopicChange`).
        self.sinks: dict[Sink, Callable[[TopicChange], None]] = {}
        self.subscription: Subscription | None = None
        self.value: Value = ""
        #: When the gateway heard ``value`` (ns since the epoch): the opening Listen's answer or
        #: the latest change; 0 until then. What a Get of the property answers as its time.
        self.stamp = 0
        #: The last change was the property's removal (every sink has been told).
        self.removed = False
        self.dead = False
        #: A change came from the backend: it is newer than the value the opening Listen brought.
        self.heard = False
        self.opening: asyncio.Task[None] | None = None
        #: The subject the topic opened as (None: unchecked), and the reads a service made for it
        #: then, which every other subject joining it is checked for.
        self.opener: Subject | None = None
        self.trail: tuple[tuple[str, str], ...] = ()
        #: The latest change as every stream's event shares it: made by the first stream told of
        #: it, found here by the others (gateway.engine.listen.stream).
        self.event: SharedEvent | None = None

    def notify(self, change: Change) -> None:
        """The backend's callback: remember the value, hand it to every sink."""
        if self.dead:
            return
        self.value = change.value
        self.removed = change.removed
        self.heard = True
        self.stamp = now = time.time_ns()
        # A sink that raises keeps its place: its stream leaves the topic when it ends.
        tell_each(self.sinks, (self, change, now), what=self, on_raise=OnRaise.KEEP)

    def __str__(self) -> str:
        return f"{self.service}/{self.path}"

    def __repr__(self) -> str:
        return f"Topic({self.service}/{self.path}, {len(self.sinks)} sinks)"


def _failure_seen(opening: asyncio.Task[None]) -> None:
    """An opening's failure is handled where it happens (the topic is dropped, each waiting sink
    hears it); one whose sinks all left meanwhile (their Listens cancelled) has nobody to read it,
    and asyncio would log it as never retrieved."""
    if not opening.cancelled():
        opening.exception()


class Topics:
    """The open topics of one hub, and the background work of opening and closing them."""

    def __init__(self, call_timeout: float, guard: Guard | None = None) -> None:
        self.call_timeout = call_timeout
        self.guard = guard or Guard()
        self._topics: dict[TopicKey, Topic] = {}
        self._tasks: set[asyncio.Task[Any]] = set()
        #: Services a wildcard skipped as unreachable, until one of their topics opens again: the
        #: log says so once per service, not once per stream. At most one entry per service.
        self._unreachable: set[str] = set()

    def __len__(self) -> int:
        return len(self._topics)

    def get(self, key: TopicKey) -> Topic | None:
        """The open topic ``key``, or None."""
        return self._topics.get(key)

    def heard_at(self, service: str, path: str, value: Value) -> int:
        """When the gateway heard ``value`` become the value of ``path`` of ``service``, as the
        open topic of that property (no parameters) knows it; 0 when no topic follows it, or its
        latest value is another (the value read is newer than what the topic heard)."""
        topics = self._topics
        if not topics:  # nothing followed at all: the commonest case of a gateway serving Gets
            return 0
        topic = topics.get((service, path, ()))
        if topic is None or topic.removed:
            return 0
        held = topic.value
        return topic.stamp if held is value or held == value else 0

    async def subscribe(
        self,
        sink: Sink,
        key: TopicKey,
        backend: Backend,
        skip: Collection[Code],
        caller: Subject | None = None,
    ) -> Topic | PropertyError:
        """Add ``sink`` to topic ``key``, opening it if needed.

        An error whose code is in ``skip`` is handed back instead of raised (the topic was
        skipped, ``sink`` is not in it); any other error is raised. ``caller``: the subject of
        the sink's stream when the rules are checked (None: they are not).
        """
        topic = self._topics.get(key)
        if topic is None or topic.dead:
            topic = Topic(key, backend)
            self._topics[key] = topic
            loop = asyncio.get_running_loop()
            if caller is None:
                topic.opening = loop.create_task(self._open(topic))
            else:
                topic.opener = caller
                trail = Trail()
                context = context_for(caller)
                context.run(TRAIL.set, trail)
                topic.opening = loop.create_task(self._open(topic, trail), context=context)
            topic.opening.add_done_callback(_failure_seen)
        topic.sinks[sink] = sink.topic_changed
        opening = topic.opening
        assert opening is not None
        try:
            if not opening.done():
                await asyncio.shield(opening)
            else:
                opening.result()
        except PropertyError as exc:
            self.unsubscribe(sink, topic)
            if exc.code in REFUSED and caller is not None and topic.opener not in (None, caller):
                # Refused to the stream that opened it, not to this one: open it again as this one.
                return await self.subscribe(sink, key, backend, skip, caller)
            return self._skipped(key, exc, skip)
        except BaseException:
            self.unsubscribe(sink, topic)
            raise
        if topic.trail and caller is not None and caller != topic.opener:
            refused = self.guard.refused_read(caller, topic.trail, audit=Code.PERMISSION_DENIED not in skip)
            if refused is not None:
                self.unsubscribe(sink, topic)
                return self._skipped(key, refused, skip)
        return topic

    def _skipped(self, key: TopicKey, exc: PropertyError, skip: Collection[Code]) -> PropertyError:
        """``exc``, handed back when its code is in ``skip``; raised otherwise."""
        if exc.code not in skip:
            raise exc
        if exc.code in UNREACHABLE:
            self._note_unreachable(key[0], exc)
        else:
            log.debug("skipping %s %s: %s", key[0], key[1], exc.message)
        return exc

    def _note_unreachable(self, service: str, exc: PropertyError) -> None:
        if service in self._unreachable:
            return
        self._unreachable.add(service)
        log.info(
            "%s cannot be reached (%s: %s): wildcard Listens skip it and try it again in the background",
            service,
            exc.code.name,
            exc.message,
        )

    async def match(
        self, service: str, backend: Backend, pattern: str, under: str = "", caller: Subject | None = None
    ) -> list[PropertyModel]:
        """``backend.match_properties(pattern, under)`` under the call timeout, as ``caller`` (what a
        service matches for it in another service is what that subject may read); any failure is
        a PropertyError naming the service and the pattern."""
        if caller is None:
            return await self._match(service, backend, pattern, under)
        # The old value is put back, not reset by token: a call stepped first in one context may
        # finish in another (a task's copy), where a token of the first is refused.
        before = CALLER.get()
        CALLER.set(caller)
        try:
            return await self._match(service, backend, pattern, under)
        finally:
            CALLER.set(before)

    async def _match(self, service: str, backend: Backend, pattern: str, under: str) -> list[PropertyModel]:
        what = f"{service}: match {pattern}" + (f" below {under}" if under else "")
        try:
            return await bounded_call(
                backend.match_properties(pattern, under), self.call_timeout, lambda: what
            )
        except PropertyError as exc:
            if exc.message.startswith(what):
                raise
            raise type(exc)(f"{what}: {exc.message}", exc.code) from None
        except Exception as exc:
            raise to_property_error(exc, what) from exc

    async def _open(self, topic: Topic, trail: Trail | None = None) -> None:
        backend, path, params = topic.backend, topic.path, topic.params
        timeout = self.call_timeout
        if path == PROPERTY_LIST:
            listening = _listen_to_list(backend, topic)
        else:
            listening = backend.listen_current(path, topic.notify, params)
        try:
            try:
                topic.subscription, value = await bounded_call(
                    listening, timeout, lambda: f"{topic.service}: listen {path}"
                )
            finally:
                if trail is not None:
                    topic.trail = trail.close()
            if not topic.heard:
                topic.value = value
                topic.stamp = time.time_ns()
        except BaseException as exc:
            if self._topics.get(topic.key) is topic:
                del self._topics[topic.key]
            topic.dead = True
            if topic.subscription is not None:
                self.spawn(self._close_subscription(topic))
            if isinstance(exc, PropertyError | asyncio.CancelledError):
                raise
            raise to_property_error(exc, f"{topic.service}: listen {path}") from exc
        if topic.service in self._unreachable:
            self._unreachable.discard(topic.service)
            log.info("%s answers again: wildcard Listens that skipped it follow it now", topic.service)
        if not topic.sinks or topic.dead:
            self.drop(topic)

    def unsubscribe(self, sink: Sink, topic: Topic) -> None:
        """``sink`` leaves ``topic``; the last one to leave closes it."""
        topic.sinks.pop(sink, None)
        if not topic.sinks and topic.opening is not None and topic.opening.done():
            self.drop(topic)

    def drop(self, topic: Topic) -> None:
        """Close ``topic`` now, whoever still listens."""
        if self._topics.get(topic.key) is topic:
            del self._topics[topic.key]
        topic.dead = True
        if topic.subscription is not None:
            self.spawn(self._close_subscription(topic))

    def service_removed(self, name: str) -> None:
        """Service ``name`` left the router: every sink of its topics hears ``removed``; they close."""
        self._unreachable.discard(name)
        gone = [t for t in self._topics.values() if t.service == name]
        for topic in gone:
            del self._topics[topic.key]
            topic.notify(Change(topic.path, "", removed=True))
            topic.dead = True
            topic.sinks.clear()
            if topic.subscription is not None:
                self.spawn(self._close_subscription(topic))

    async def _close_subscription(self, topic: Topic) -> None:
        sub, topic.subscription = topic.subscription, None
        if sub is None:
            return
        try:
            await asyncio.wait_for(sub.close(), self.call_timeout)
        except Exception:
            log.warning("closing the listen on %s %s failed", topic.service, topic.path, exc_info=True)

    def spawn(self, coro: Coroutine[Any, Any, None]) -> asyncio.Task[None]:
        """Run ``coro`` in a task the hub waits for at shutdown; a failure is logged."""
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Task[Any]) -> None:
        self._tasks.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("listen hub task failed", exc_info=task.exception())

    async def aclose(self) -> None:
        """Close every topic (cancelling those still opening) and wait for the background work."""
        opening = []
        for topic in list(self._topics.values()):
            if topic.opening is not None and not topic.opening.done():
                topic.opening.cancel()
                opening.append(topic.opening)
            self.drop(topic)
        await asyncio.gather(*opening, return_exceptions=True)
        while self._tasks:
            tasks = list(self._tasks)
            await asyncio.gather(*tasks, return_exceptions=True)
            # Since Python 3.12 a gather of tasks already done returns without yielding to the loop,
            # so their done callbacks may not have run yet: forget them here, or this would spin.
            self._tasks.difference_update(tasks)


async def _listen_to_list(backend: Backend, topic: Topic) -> tuple[Subscription, Value]:
    """Open a :data:`PROPERTY_LIST` topic: it has no value of its own."""
    return await backend.listen_properties(topic.notify), ""
