"""Dormant services: declared in the config, started when a call needs them, stopped when idle.

A ``[[services]]`` entry with ``dormant = true`` is served by a
:class:`DormantBackend` from the start: the router, the registry and every
client see the service (its availability is ``dormant``), but the service
itself is not built and started until a Get, Set, Listen or Describe reaches
it, or the registry's ``wake`` (the scheduler choosing it) asks. The first
call waits while it starts; then the backend forwards every call. After
``idle_stop`` seconds with no call in flight and no Listen open, it is stopped
again (dormant once more), unless a licence is held on it; the next call
starts a fresh one.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Mapping

from services.kernel.backend import (
    NO_PARAMS,
    Backend,
    BackendInfo,
    LinkCounts,
    Notify,
    Subscription,
    close_quietly,
)
from services.kernel.errors import PropertyError, Unavailable
from services.kernel.model import PropertyModel, ServiceModel
from services.kernel.values import Value

__all__ = ["DormantBackend"]

log = logging.getLogger(__name__)


class DormantBackend(Backend):
    """Serves ``name`` by starting ``open()`` on demand; see the module docstring.

    ``awake(name, running)`` is told each time the service starts (True) or
    stops (False); ``connect_wait`` bounds how long a start waits for a proxy's
    device to answer; while ``held(name)`` (a licence is held on it: a consumer
    is bound to it) it is not stopped for being idle.
    """

    on_demand = True

    def __init__(
        self,
        name: str,
        open: Callable[[], Backend],
        *,
        info: BackendInfo,
        idle_stop: float,
        awake: Callable[[str, bool], None],
        connect_wait: float,
        held: Callable[[str], bool] = lambda name: False,
    ) -> None:
        self.name = name
        self.info = info
        self.idle_stop = idle_stop
        self._open = open
        self._awake = awake
        self._held = held
        self._connect_wait = connect_wait
        self._backend: Backend | None = None
        self._lock = asyncio.Lock()
        #: Calls in flight and Listens open: while any, the service is in use.
        self._users = 0
        self._last_used = time.monotonic()
        self._idle: asyncio.Task[None] | None = None
        self._closed = False
        #: Times the service was started (for logs and tests of the idle stop).
        self.starts = 0

    @property
    def running(self) -> bool:
        """The service is started (not dormant)."""
        return self._backend is not None

    # -- waking and sleeping ---------------------------------------------------------

    async def wake(self) -> None:
        await self._running()

    async def _running(self) -> Backend:
        backend = self._backend
        if backend is not None:
            return backend
        async with self._lock:
            if self._backend is not None:
                return self._backend
            if self._closed:
                raise Unavailable(f"service {self.name!r} is shutting down")
            log.info("service %s: dormant, starting it for a call", self.name)
            backend = self._open()
            try:
                await backend.start()
                await backend.wait_connected(self._connect_wait)
            except PropertyError as exc:
                await backend.aclose()
                raise Unavailable(
                    f"service {self.name!r} is dormant and could not be started: {exc.message}"
                ) from None
            except BaseException:
                await backend.aclose()
                raise
            self._backend = backend
            self.starts += 1
            self._last_used = time.monotonic()
            if self.idle_stop > 0:
                self._idle = asyncio.get_running_loop().create_task(
                    self._stop_when_idle(), name=f"dormant: idle stop of {self.name}"
                )
        self._awake(self.name, True)
        return backend

    def touch(self) -> None:
        """Count now as a use: a licence on it was granted, renewed or ended (its idle time runs
        from the end of its last licence, not from its last call)."""
        self._last_used = time.monotonic()

    async def _stop_when_idle(self) -> None:
        while True:
            quiet = time.monotonic() - self._last_used
            await asyncio.sleep(max(0.0, self.idle_stop - quiet) + 0.01)
            if self._held(self.name):
                self._last_used = time.monotonic()  # bound to a consumer: idle from the licence's end
                continue
            if self._users == 0 and time.monotonic() - self._last_used >= self.idle_stop:
                async with self._lock:
                    if self._users != 0:
                        continue
                    backend, self._backend = self._backend, None
                    self._idle = None
                if backend is not None:
                    log.info("service %s: idle for %g s, stopping it (dormant)", self.name, self.idle_stop)
                    try:
                        await backend.aclose()
                    finally:
                        self._awake(self.name, False)
                return

    @contextlib.asynccontextmanager
    async def _use(self) -> AsyncIterator[Backend]:
        self._users += 1
        try:
            yield await self._running()
        finally:
            self._users -= 1
            self._last_used = time.monotonic()

    # -- the calls -------------------------------------------------------------------

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
        async with self._use() as backend:
            return await backend.get(path, params)

    async def set(self, path: str, value: Value, params: Mapping[str, str] = NO_PARAMS) -> Value:
        async with self._use() as backend:
            return await backend.set(path, value, params)

    async def describe(self) -> ServiceModel:
        async with self._use() as backend:
            return await backend.describe()

    async def properties(self) -> list[str]:
        async with self._use() as backend:
            return await backend.properties()

    async def match_properties(self, pattern: str, under: str = "") -> list[PropertyModel]:
        async with self._use() as backend:
            return await backend.match_properties(pattern, under)

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        sub, _ = await self._hold(lambda backend: _no_value(backend.listen(path, notify, params)))
        return sub

    async def listen_properties(self, notify: Notify) -> Subscription:
        sub, _ = await self._hold(lambda backend: _no_value(backend.listen_properties(notify)))
        return sub

    async def listen_current(
        self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS
    ) -> tuple[Subscription, Value]:
        # The running service's own way (a line device's LISTEN brings the value: no Get after it).
        return await self._hold(lambda backend: backend.listen_current(path, notify, params))

    async def _hold(
        self, open_listen: Callable[[Backend], Awaitable[tuple[Subscription, Value]]]
    ) -> tuple[Subscription, Value]:
        """Start the service if need be and open a Listen on it, which keeps it awake until closed."""
        self._users += 1
        try:
            sub, value = await open_listen(await self._running())
        except BaseException:
            self._users -= 1
            self._last_used = time.monotonic()
            raise
        return _Held(self, sub), value

    async def check(self) -> None:
        """Alive when dormant (nothing to check: a call would start it); else the service's own check."""
        backend = self._backend
        if backend is not None:
            await backend.check()

    def link_counts(self) -> LinkCounts | None:
        backend = self._backend  # while dormant there is no connection to count
        return backend.link_counts() if backend is not None else None

    def serves(self, obj: object) -> bool:
        backend = self._backend
        return backend is not None and backend.serves(obj)

    async def aclose(self) -> None:
        self._closed = True
        idle, self._idle = self._idle, None
        if idle is not None:
            idle.cancel()
            await asyncio.gather(idle, return_exceptions=True)
        async with self._lock:
            backend, self._backend = self._backend, None
        if backend is not None:
            await backend.aclose()

    def _released(self) -> None:
        self._users -= 1
        self._last_used = time.monotonic()


async def _no_value(opening: Awaitable[Subscription]) -> tuple[Subscription, Value]:
    return await opening, ""


class _Held(Subscription):
    """A Listen on a woken service: keeps it awake until closed."""

    def __init__(self, owner: DormantBackend, sub: Subscription) -> None:
        self._owner = owner
        self._sub: Subscription | None = sub

    async def close(self) -> None:
        sub, self._sub = self._sub, None
        if sub is None:
            return
        try:
            await close_quietly(sub)
        finally:
            self._owner._released()
