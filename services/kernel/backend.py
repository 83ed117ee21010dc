"""The one async interface every backend implements.

A backend is one Property Service as the gateway sees it: a local Python
object served by the core, a proxy to a raw-TCP or serial device, or a proxy
to another gateway. The gateway's router, listen hub and Session code speak
only this interface; they never ask which kind of backend they hold.

Paths are dotted property paths (``location.x``, ``robots.scout1.location``)
without wildcards: wildcard selectors are expanded by the listen hub using
:meth:`Backend.match_properties` and followed with :meth:`Backend.listen_properties`,
never by reading the ``properties`` value, which a big service (a registry of a few
hundred services) makes longer than one value may be.
"""

from __future__ import annotations

import abc
import asyncio
import enum
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, ClassVar, Protocol, TypeVar

from services.kernel.model import Access, PropertyModel, ServiceModel
from services.kernel.paths import compile_pattern, is_below
from services.kernel.values.binary import Value

NO_PARAMS: Mapping[str, str] = MappingProxyType({})

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Change:
    """One change of one property, pushed by a backend to a listener."""

    path: str
    #: Text, or bytes for a binary property.
    value: Value
    #: Values may have been lost before this one (a device reconnected);
    #: ``value`` is the current value.
    gap: bool = False
    #: The property no longer exists; ``value`` is empty.
    removed: bool = False


#: Called by a backend, on the event loop's thread, for each change. It must
#: not block and must not raise; the listen hub's implementation only
#: enqueues into bounded, conflating queues.
Notify = Callable[[Change], None]


class OnRaise(enum.Enum):
    """What :func:`tell_each` does with a listener that raises (after logging it)."""

    #: Take it out of the listeners: it is told nothing more (a backend's own listeners, whose
    #: subscription forgets a token that is already gone).
    DROP = "it is dropped"
    #: Leave it in place: its owner takes it out (a shared listen, a topic, a followed file, whose
    #: last listener to leave closes what they share: dropping it here would leave that open).
    KEEP = "it keeps its place"


#: What a fan-out tells each of its listeners: a :class:`Change` (a backend's), or what a listen hub
#: topic tells its sinks.
News = TypeVar("News")


def tell_each(
    listeners: dict[Any, Callable[[News], None]],
    news: News,
    *,
    what: object,
    on_raise: OnRaise = OnRaise.DROP,
) -> None:
    """Call every listener (key → callback) with ``news``; one that raises is logged, as a listener
    of ``what`` (formatted only then), and dropped or kept as ``on_raise`` says (dropped: a
    backend's :data:`Notify` must not raise), and the others are told all the same.

    The one fan-out of the project: a backend's listeners, a shared upstream listen's, a listen
    hub topic's sinks and a followed file's all go through it. It runs once per listener for every
    change (the Listen fan-out's hot path; ``python -m bench.instructions --parts
    fanout,batched-fanout`` guards it), so each listener takes one argument: Python 3.11 runs a
    call of a fixed number of arguments in the caller's own evaluation loop, where one that
    unpacks them (``notify(*args)``) goes through the C call protocol, about 200 instructions more
    a call.
    """
    # The callbacks alone: a (key, callback) pair each would cost an allocation per listener, and
    # a key is needed only to drop one.
    for notify in list(listeners.values()):
        try:
            notify(news)
        except Exception:
            log.exception("a listener of %s failed; %s", what, on_raise.value)
            if on_raise is OnRaise.DROP:
                _drop(listeners, notify)


def _drop(listeners: dict[Any, Callable[[News], None]], notify: Callable[[News], None]) -> None:
    """Take ``notify`` out of ``listeners`` (its first key; a listener that holds two keys raises
    again at the next, and goes then)."""
    for key, held in listeners.items():
        if held is notify:
            del listeners[key]
            return


class Subscription(abc.ABC):
    """A live listen on one backend property; ``close`` ends it (idempotent)."""

    @abc.abstractmethod
    async def close(self) -> None: ...


async def close_quietly(sub: Subscription) -> None:
    """Close ``sub``; a failure (the device vanished) is logged at debug level, never raised."""
    try:
        await sub.close()
    except Exception:
        log.debug("closing a listen failed", exc_info=True)


#: The type of a backend that has not been reached yet (a proxy before its device greets, or
#: before another gateway's registry answered): the registry shows it, and its state "connecting".
UNKNOWN_TYPE = "unknown"


@dataclass(slots=True)
class BackendInfo:
    """What the registry knows of a backend."""

    #: Resource type: ``mobile_robot``, ``sensor``, ``registry``, ``group``, ...
    type: str = "resource"
    #: Contact URL: ``local``, ``tcp://host:port``, ``serial:///dev/ttyUSB0?baudrate=115200``, ``grpc://...``.
    url: str = "local"
    extra: dict[str, str] = field(default_factory=dict)


class Answer(Protocol):
    """A reply that carries a value (a line-protocol ``OK`` frame, say)."""

    @property
    def value(self) -> Value: ...


@dataclass(slots=True)
class LinkCounts:
    """What a backend that keeps a connection to a device has seen of it (the metrics read it).

    Plain counters, raised by the proxy where it connects, loses the device and misses a keep-alive.
    """

    #: How the device is reached: "tcp", "serial" or "dial-in" (a fixed, small set).
    transport: str
    connected: bool = False
    #: Connections made (greeted), the first included.
    connects: int = 0
    #: Connections lost after they were made (each is followed by a reconnect or a wait for one).
    disconnects: int = 0
    #: Keep-alive PINGs that went unanswered in time (each drops the connection).
    keepalive_failures: int = 0


def _no_link() -> None:
    """Stop watching the link of a backend that has none: nothing to stop."""


class Backend(abc.ABC):
    """One Property Service, whatever it runs on.

    Errors are raised as :class:`services.kernel.errors.PropertyError` subclasses
    (NOT_FOUND for an unknown property, INVALID_ARGUMENT for a bad value,
    FAILED_PRECONDITION for a read-only property, UNAVAILABLE when a device
    cannot be reached, DEADLINE_EXCEEDED when it is too slow).

    Besides the calls every backend answers, a few capabilities only some
    backends have are declared here with defaults that do without them, so
    that callers never ask which kind of backend they hold:
    :attr:`answers_inline`, :meth:`start_get`, :meth:`flush`, :meth:`listen_current`,
    :meth:`match_properties`, :meth:`listen_properties`,
    :meth:`wait_connected`, :meth:`watch_link`, :meth:`serves`, :meth:`wake`, :attr:`on_demand`.
    """

    info: BackendInfo

    #: Calls usually finish without waiting (an in-process object): callers may run
    #: the first step of a call in their own task (:func:`services.kernel.eager.step`) and
    #: pay for a task or a timer only when it has to wait. False for a proxy, whose
    #: calls always wait and may arm timeouts that must belong to the task awaiting them.
    answers_inline: ClassVar[bool] = False

    #: The service is started on demand (a dormant service, :meth:`wake`): a watcher that only
    #: follows it (the registry's locations) must not call it, or it would never sleep again.
    on_demand: ClassVar[bool] = False

    @abc.abstractmethod
    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
        """Return the value of ``path``: text, or bytes for a binary property."""

    @abc.abstractmethod
    async def set(self, path: str, value: Value, params: Mapping[str, str] = NO_PARAMS) -> Value:
        """Write ``value`` to ``path`` (or call a functional property); return the service's answer.

        ``value`` is bytes for a binary property; text on a binary property, or bytes on a
        text one, is INVALID_ARGUMENT.
        """

    @abc.abstractmethod
    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        """Call ``notify`` for every later change of ``path``.

        The current value is not sent: the caller subscribes first and then
        Gets, so no change can fall between the two. Raises NOT_FOUND for an
        unknown path. ``listen("properties", ...)`` reports changes of the
        property list itself.
        """

    async def listen_current(
        self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS
    ) -> tuple[Subscription, Value]:
        """Listen to ``path`` and return the subscription with the value current once it is in place.

        The default Listens, then Gets (no change can fall between the two).
        A backend whose listen already brings the value (a line-protocol
        device answers LISTEN with it) overrides this and spares the Get.
        """
        sub = await self.listen(path, notify, params)
        try:
            value = await self.get(path, params)
        except BaseException:
            await close_quietly(sub)
            raise
        return sub, value

    async def properties(self) -> list[str]:
        """The property names the service offers right now (the ``properties`` property)."""
        from services.kernel.values import as_text, parse_names

        return parse_names(as_text(await self.get("properties"), "properties"))

    async def describe(self) -> ServiceModel:
        """The typed model of every property the service offers right now (one call).

        The default knows only the names: each property is of type and access
        ``unknown``. Backends that know more (the class wrapper, a device that
        describes itself, another gateway) override it.
        """
        names = await self.properties()
        return ServiceModel(
            type=self.info.type,
            properties=tuple(PropertyModel(name, "unknown", Access.UNKNOWN) for name in names),
        )

    async def match_properties(self, pattern: str, under: str = "") -> list[PropertyModel]:
        """The model of every property whose name matches ``pattern`` (``*`` matches one segment),
        in the order ``properties`` lists them; with ``under``, only ``under`` itself and the
        names below it (``services.scout7``: ``services.scout7.state``, ...).

        How the listen hub expands a wildcard selector and the gateway a wildcard Get. The
        default filters :meth:`describe`: a device's own model, another gateway's Describe, or,
        for a backend that does not describe itself, the ``properties`` list (which holds at most
        what one value holds, ``services.kernel.values.MAX_VALUE_LENGTH``: a longer list is
        INVALID_ARGUMENT). ``LocalService`` walks only the part of its tree the pattern names,
        and answers at any size.
        """
        matches = compile_pattern(pattern)
        return [
            p
            for p in (await self.describe()).properties
            if matches(p.name) and (not under or is_below(p.name, under))
        ]

    async def listen_properties(self, notify: Notify) -> Subscription:
        """Call ``notify`` whenever properties appear or go; each ``Change``'s ``path`` names where
        (the name of a property or namespace that came or went, everything below it with it),
        "" for anywhere; its ``value`` is empty, ``gap`` as for any change.

        A listener asks :meth:`match_properties` again for what it follows, ``under`` that
        path. The default listens to ``properties`` and reports each change as "anywhere"; a
        service that knows where its tree changed (``LocalService``) overrides it and never
        formats its list for it.
        """

        def changed(change: Change) -> None:
            if not change.removed:
                notify(Change("", "", gap=change.gap))

        return await self.listen("properties", changed)

    async def check(self) -> None:
        """Return when the service is alive; raise a PropertyError (UNAVAILABLE, ...) when it is not.

        The registry's liveness check. By default a Get of ``properties``;
        a backend that can tell more cheaply (a proxy that heard from its
        device a moment ago) overrides it.
        """
        await self.properties()

    def start_get(
        self,
        path: str,
        params: Mapping[str, str],
        time_limit: float,
        then: Callable[[Answer], None] | None = None,
    ) -> asyncio.Future[Answer] | None:
        """Send a Get of ``path`` now and return a future of its reply, or None to say "await :meth:`get`".

        A shortcut for callers that would otherwise wrap :meth:`get` in a task
        and a timer of their own: a proxy resolves the future straight from its
        connection's reader, under the one timer of its connection. The future
        fails with the call's PropertyError (DEADLINE_EXCEEDED after at most
        ``time_limit``). ``then``, when given, is called with a successful
        reply in the reader itself, just before the future is resolved: a
        loop turn sooner than the future's done-callbacks run. The default
        has no shortcut and returns None.
        """
        return None

    def flush(self) -> None:  # noqa: B027 - optional hook, nothing held by default
        """Send now what the backend holds for the end of this loop turn.

        A proxy batches the requests started in one loop turn into one write to its device,
        made at the turn's end; a caller that knows no more requests of its batch come this
        turn (a Session, once it has started a message's requests) calls this, so that the
        device has them a turn sooner, still in one write. A backend that holds nothing has
        nothing to send (the default).
        """

    def link_counts(self) -> LinkCounts | None:
        """The counts of a backend that keeps a connection to a device; None for any other (the default)."""
        return None

    def watch_link(self, listener: Callable[[bool], None]) -> Callable[[], None]:
        """Call ``listener(False)`` as soon as the backend loses its device, ``listener(True)`` when
        it has it back; returns a function that stops it. A backend with no link of its own never
        calls it (the default)."""
        return _no_link

    async def wait_connected(self, wait_s: float) -> None:  # noqa: B027 - optional hook, at once by default
        """Return once the backend can serve calls; raise Unavailable, saying why, after ``wait_s``.

        A proxy connects in the background: this waits for its first
        connection (and greeting). A backend that is ready once started
        returns at once.
        """

    def serves(self, obj: object) -> bool:
        """True when this backend serves ``obj`` itself (a group refuses itself as a member)."""
        return False

    async def wake(self) -> None:  # noqa: B027 - optional hook, at once by default
        """Start the service if it is dormant (declared, not running) and return once it serves.

        The registry's ``wake`` (a call or the scheduler needs a dormant
        provider). A backend that always runs returns at once.
        """

    async def start(self) -> None:  # noqa: B027 - optional hook, empty by default
        """Start background work (simulation ticks, connections). Called once by the gateway."""

    async def aclose(self) -> None:  # noqa: B027 - optional hook, empty by default
        """Stop background work and release resources. Idempotent."""
