"""Service name → backend, and bounded calls into backends.

The :class:`Router` is the gateway's live set of services; watchers (the
listen hub, the registry) hear every join and leave. A service the registry
marks ``down`` (:meth:`Router.set_down`) still holds its place, but
:meth:`Router.backend` — the lookup of every client call — answers
UNAVAILABLE for it. System services (the registry, groups) are handed
:attr:`Router.directory`, a :class:`services.kernel.directory.Directory` whose
lookups ignore that mark: the registry must keep probing a service that is
down to see it come back. With rules configured, the backends that directory
hands out check every call as the client it is made for (:mod:`gateway.engine.behalf`),
and its watchers hear joins and leaves as the services' own work.

:func:`bounded_call` runs one backend coroutine under a timeout without
creating a task, and without even arming a timer when the backend answers
at once (a local service reading an attribute).
"""

from __future__ import annotations

import asyncio
import difflib
import functools
import logging
from collections.abc import Callable, Coroutine, Mapping
from typing import Any, TypeVar

from gateway.backends import open_proxy
from gateway.engine.behalf import OnBehalf, on_behalf
from gateway.engine.guard import Guard
from gateway.engine.licensing import check_set
from gateway.engine.rules import Subject
from services.apps.registry import Licences
from services.kernel.backend import Backend, BackendInfo
from services.kernel.directory import DirectoryListener, own_context
from services.kernel.eager import Started, step
from services.kernel.errors import AlreadyExists, DeadlineExceeded, InvalidArgument, NotFound, Unavailable
from services.kernel.paths import validate_path, validate_pattern, validate_service_name

log = logging.getLogger(__name__)

T = TypeVar("T")

#: Validated paths are cached: the Get path must not re-run the validator for
#: the same few hundred paths a client reads over and over. Failures are not
#: cached (lru_cache does not cache exceptions), so the cache holds only good paths.
check_path: Callable[[str], str] = functools.lru_cache(maxsize=4096)(validate_path)
check_pattern: Callable[[str], str] = functools.lru_cache(maxsize=1024)(validate_pattern)

_SUGGESTIONS = 5


class Router:
    """The live map from service name to :class:`~services.kernel.backend.Backend`."""

    def __init__(self, guard: Guard | None = None) -> None:
        """``guard``: the rules the calls system services make on a client's behalf are checked by."""
        self._backends: dict[str, Backend] = {}
        self._watchers: list[DirectoryListener] = []
        #: name → why it is down, for the services the registry marked down.
        self._down: dict[str, str] = {}
        #: The view of this router that system services get (lookups ignore ``down``).
        self.directory = RouterDirectory(self, guard)

    # -- lookups ---------------------------------------------------------

    def backend(self, name: str) -> Backend:
        """The backend serving ``name`` for a client call.

        Raises NotFound (with suggestions) for a well-formed unknown name,
        InvalidArgument for a malformed one, Unavailable for a service marked down.
        """
        backend = self._backends.get(name)
        if backend is None:
            raise self._unknown(name)
        if self._down:
            reason = self._down.get(name)
            if reason is not None:
                raise Unavailable(reason)
        return backend

    def lookup(self, name: str) -> Backend:
        """The backend serving ``name``, down or not; raises NotFound or InvalidArgument."""
        backend = self._backends.get(name)
        if backend is None:
            raise self._unknown(name)
        return backend

    def set_down(self, name: str, reason: str | None) -> None:
        """Mark ``name`` down (its client calls get UNAVAILABLE with ``reason``), or up again with None."""
        if reason is None:
            self._down.pop(name, None)
        elif name in self._backends:
            self._down[name] = reason

    def names(self) -> list[str]:
        """Names of every service right now, sorted."""
        return sorted(self._backends)

    def items(self) -> list[tuple[str, Backend]]:
        """(name, backend) of every service right now."""
        return list(self._backends.items())

    def __contains__(self, name: object) -> bool:
        return name in self._backends

    def __len__(self) -> int:
        return len(self._backends)

    def _unknown(self, name: str) -> Exception:
        # Only a name that is not served is checked: known names cost one dict lookup.
        if not name:
            return InvalidArgument("no service named: the request's service is empty")
        try:
            validate_service_name(name)
        except InvalidArgument as bad:
            return bad
        known = sorted(self._backends)
        close = difflib.get_close_matches(name, known, n=3)
        hint = f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""
        shown = ", ".join(known[:_SUGGESTIONS]) + (", ..." if len(known) > _SUGGESTIONS else "")
        listing = f" (known services: {shown})" if known else " (no services are running)"
        return NotFound(f"unknown service {name[:80]!r}{hint}{listing}")

    # -- changes ---------------------------------------------------------

    def add(self, name: str, backend: Backend) -> None:
        """Serve ``backend`` as ``name`` (already started); raises AlreadyExists or InvalidArgument."""
        validate_service_name(name)
        if name in self._backends:
            raise AlreadyExists(f"a service named {name!r} already exists")
        self._backends[name] = backend
        self._notify(name, backend)

    def remove(self, name: str) -> Backend:
        """Stop serving ``name`` and return its backend (the caller closes it); raises NotFound."""
        backend = self._backends.pop(name, None)
        if backend is None:
            raise self._unknown(name)
        self._down.pop(name, None)
        self._notify(name, None)
        return backend

    def watch(self, listener: DirectoryListener) -> Callable[[], None]:
        """Call ``listener(name, backend)`` on every add, ``listener(name, None)`` on every remove."""
        self._watchers.append(listener)

        def unwatch() -> None:
            if listener in self._watchers:
                self._watchers.remove(listener)

        return unwatch

    def _notify(self, name: str, backend: Backend | None) -> None:
        for listener in list(self._watchers):
            try:
                listener(name, backend)
            except Exception:
                log.exception(
                    "a watcher of the service list failed on %s of %r", "add" if backend else "remove", name
                )

    # -- Directory: dynamic registration ----------------------------------

    async def register(self, name: str, url: str, options: Mapping[str, Any] | None = None) -> BackendInfo:
        """Open a proxy backend for ``url``, start it and serve it as ``name``."""
        validate_service_name(name)
        if name in self._backends:
            raise AlreadyExists(f"a service named {name!r} already exists")
        backend = open_proxy(name, url, options or {})
        await self.serve(name, backend)
        log.info("service %s registered at %s", name, url)
        return backend.info

    async def serve(self, name: str, backend: Backend) -> None:
        """Start ``backend`` and serve it as ``name``; it is closed when it cannot be served."""
        try:
            validate_service_name(name)
            if name in self._backends:
                raise AlreadyExists(f"a service named {name!r} already exists")
            await backend.start()
            self.add(name, backend)
        except BaseException:
            await backend.aclose()
            raise

    async def unregister(self, name: str) -> None:
        """Stop serving ``name`` and close its backend; raises NotFound."""
        backend = self.remove(name)
        await backend.aclose()
        log.info("service %s unregistered", name)


class RouterDirectory:
    """A router as a :class:`services.kernel.directory.Directory`: the same services, down ones included.

    With a guard that checks (rules, or tokens whose scopes narrow), or once it has the
    registry's licences (:attr:`licences`: a Set made for a client is checked against them),
    each backend it hands out is an :class:`~gateway.engine.behalf.OnBehalf`: the same one for a name
    as long as the name is served by the same backend, so that a service can tell its members
    apart by identity. With neither it hands out the router's own backends.
    """

    def __init__(self, router: Router, guard: Guard | None = None) -> None:
        self.router = router
        self.guard = guard
        #: The registry's licences, given before any service that reaches others is added (the
        #: gateway does it when its registry starts); None: no licences to check.
        self.licences: Licences | None = None
        #: Whether the call being served was forwarded by another gateway of this one's cluster: its
        #: Sets were checked against the licences where the client called, and come as that gateway
        #: (which holds none); None: not in a cluster.
        self.peer_forwarded: Callable[[], bool] | None = None
        #: name → the OnBehalf handed out for it; one per name served (a leave forgets it).
        self._handed: dict[str, OnBehalf] = {}
        router.watch(self._forget)

    def _forget(self, name: str, backend: Backend | None) -> None:
        if backend is None:
            self._handed.pop(name, None)

    def _checked(self, name: str, backend: Backend) -> Backend:
        guard = self.guard
        if guard is None or not (guard.checks or self.licences is not None):
            return backend
        handed = self._handed.get(name)
        if handed is None or handed.inner is not backend:
            licensed = self._check_licence if self.licences is not None else None
            handed = self._handed[name] = on_behalf(name, backend, guard, licensed)
        return handed

    def _check_licence(self, subject: Subject, service: str, path: str) -> None:
        """Refuse a Set made for ``subject`` on what someone else holds a licence on."""
        forwarded = self.peer_forwarded
        if forwarded is None or not forwarded():
            check_set(self.licences, subject, service, path)

    def names(self) -> list[str]:
        return self.router.names()

    def __contains__(self, name: object) -> bool:
        return name in self.router

    def backend(self, name: str) -> Backend:
        return self._checked(name, self.router.lookup(name))

    def watch(self, listener: DirectoryListener) -> Callable[[], None]:
        """Tell ``listener`` of every join and leave, as the service's own work (a registration by
        a client makes the services that react to it act for themselves, not for that client)."""

        def heard(name: str, backend: Backend | None) -> None:
            checked = None if backend is None else self._checked(name, backend)
            own_context().run(listener, name, checked)

        return self.router.watch(heard)

    async def register(self, name: str, url: str, options: Mapping[str, Any] | None = None) -> BackendInfo:
        return await self.router.register(name, url, options)

    async def serve(self, name: str, backend: Backend) -> None:
        await self.router.serve(name, backend)
        log.info("service %s started (%s)", name, backend.info.url)

    async def unregister(self, name: str) -> None:
        await self.router.unregister(name)


async def bounded_call(coro: Coroutine[Any, Any, T], time_limit: float, what: Callable[[], str]) -> T:
    """Await ``coro`` for at most ``time_limit`` seconds; raise DeadlineExceeded naming ``what()`` after.

    The coroutine is first stepped directly: a backend that answers without
    waiting costs no timer and no task. Only when it has to wait is the rest
    run under ``asyncio.timeout`` in the calling task (never in another task,
    so timeouts the backend itself sets stay attached to the right task).
    """
    first = step(coro)
    if isinstance(first, Started):
        return await finish_call(first, time_limit, what)
    return first


async def finish_call(started: Started[T], time_limit: float, what: Callable[[], str]) -> T:
    """Run the rest of a call stepped once already, under ``time_limit``."""
    scope = asyncio.timeout(time_limit)
    try:
        async with scope:
            return await started.rest()
    except TimeoutError:
        if scope.expired():
            raise DeadlineExceeded(f"{what()} took longer than {time_limit:g} s") from None
        raise
