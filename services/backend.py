"""The one async interface every backend implements.

A backend is one Property Service as the gateway sees it: a local Python
object served by the core, a proxy to a raw-TCP or serial device, or a proxy
to another gateway. The gateway's router, listen hub and Session code speak
only this interface; they never ask which kind of backend they hold.

Paths are dotted property paths (``location.x``, ``robots.scout1.location``)
without wildcards: wildcard selectors are expanded by the listen hub using
:meth:`Backend.properties` and a listen on ``properties``.
"""

from __future__ import annotations

import abc
import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

NO_PARAMS: Mapping[str, str] = MappingProxyType({})

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Change:
    """One change of one property, pushed by a backend to a listener."""

    path: str
    value: str
    #: Values may have been lost before this one (a device reconnected);
    #: ``value`` is the current value.
    gap: bool = False
    #: The property no longer exists; ``value`` is empty.
    removed: bool = False


#: Called by a backend, on the event loop's thread, for each change. It must
#: not block and must not raise; the listen hub's implementation only
#: enqueues into bounded, conflating queues.
Notify = Callable[[Change], None]


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


@dataclass(slots=True)
class BackendInfo:
    """What the registry knows of a backend."""

    #: Resource type: ``mobile_robot``, ``sensor``, ``registry``, ``group``, ...
    type: str = "resource"
    #: Contact URL: ``local``, ``tcp://host:port``, ``serial:///dev/ttyUSB0?baudrate=115200``, ``grpc://...``.
    url: str = "local"
    extra: dict[str, str] = field(default_factory=dict)


class Backend(abc.ABC):
    """One Property Service, whatever it runs on.

    Errors are raised as :class:`services.errors.PropertyError` subclasses
    (NOT_FOUND for an unknown property, INVALID_ARGUMENT for a bad value,
    FAILED_PRECONDITION for a read-only property, UNAVAILABLE when a device
    cannot be reached, DEADLINE_EXCEEDED when it is too slow).
    """

    info: BackendInfo

    @abc.abstractmethod
    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        """Return the value of ``path`` as text."""

    @abc.abstractmethod
    async def set(self, path: str, value: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        """Write ``value`` to ``path`` (or call a functional property); return the service's answer."""

    @abc.abstractmethod
    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        """Call ``notify`` for every later change of ``path``.

        The current value is not sent: the caller subscribes first and then
        Gets, so no change can fall between the two. Raises NOT_FOUND for an
        unknown path. ``listen("properties", ...)`` reports changes of the
        property list itself.
        """

    async def properties(self) -> list[str]:
        """The property names the service offers right now (the ``properties`` property)."""
        from services.values import parse_names

        return parse_names(await self.get("properties"))

    async def check(self) -> None:
        """Return when the service is alive; raise a PropertyError (UNAVAILABLE, ...) when it is not.

        The registry's liveness check. By default a Get of ``properties``;
        a backend that can tell more cheaply (a proxy that heard from its
        device a moment ago) overrides it.
        """
        await self.properties()

    async def start(self) -> None:  # noqa: B027 - optional hook, empty by default
        """Start background work (simulation ticks, connections). Called once by the gateway."""

    async def aclose(self) -> None:  # noqa: B027 - optional hook, empty by default
        """Stop background work and release resources. Idempotent."""
