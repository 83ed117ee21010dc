"""The resource service: which services exist, how to reach them, whether they are alive.

``services`` lists the known service names; ``services.<name>`` is the
contact URL and ``services.<name>.type``, ``.url``, ``.state``,
``.last_seen``, ``.misses``, ``.lease`` and ``.location`` tell more. A Listen
on ``services`` hears every join and leave, one on ``services.*.state``
every change of state.

Served by :class:`RegistryService` (a LocalService that also takes Sets on
``services.<name>``), the registry changes the set of services itself,
through the :class:`~services.directory.Directory` it is given:

* **Register**: Set ``services.<name>`` to ``tcp://host:port``,
  ``serial:///dev/ttyUSB0?baudrate=115200`` or ``grpc://host:port`` (request
  parameters: ``type`` to declare the resource type, ``lease`` in seconds).
  The backend is created and must answer a Get of ``properties`` within
  ``register_timeout``; otherwise nothing is registered.
* **Unregister**: Set ``services.<name>`` to the empty value.
* **Liveness**: every ``period`` seconds each service that is not in-process
  is checked (``Backend.check``: a Get of ``properties``, or less for a
  line-protocol device) under ``timeout``; after ``misses`` misses in a
  row it is ``down``, and a registered one (not from the config) is removed
  after ``grace`` seconds down. A service with a lease is not polled: it Sets
  ``services.<name>.lease`` to renew it, and is ``down`` when it lapses.
* **Search**: Get ``find`` with parameters ``type``, ``near``, ``radius``,
  ``state``, ``limit``, ``where`` (see :mod:`services.query`).

The gateway's router keeps the plain methods :meth:`Registry.add`,
:meth:`Registry.remove` and :meth:`Registry.set_state` working as before; with
a directory, the registry also follows joins and leaves by itself.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import os
import tempfile
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import urlsplit

import numpy as np

from services.backend import NO_PARAMS, Backend, BackendInfo, Change, Subscription, close_quietly
from services.core import LocalService, Prop, Resource, functional
from services.directory import Directory
from services.errors import (
    AlreadyExists,
    Code,
    DeadlineExceeded,
    InvalidArgument,
    NotFound,
    PropertyError,
    Unavailable,
)
from services.group import run_bounded
from services.paths import validate_service_name
from services.query import Query, ServiceIndex, values_equal
from services.values import ValueFormatError, Vector, format_number, parse_number, parse_vector

__all__ = [
    "DEFAULT_REGISTER_TIMEOUT",
    "REGISTRABLE_SCHEMES",
    "STATES",
    "Registry",
    "RegistryService",
    "ServiceEntry",
    "ServiceList",
    "check_url",
]

log = logging.getLogger(__name__)

#: What ``services.<name>.state`` can be.
STATES = ("up", "down")
#: URL schemes a Set on ``services.<name>`` may register (``local`` services come from the config).
REGISTRABLE_SCHEMES = ("tcp", "serial", "grpc")
#: Liveness checks running at once; a registry of thousands of devices does not dial them all at once.
MAX_CONCURRENT_CHECKS = 64
#: Property Gets running at once for a ``find`` with ``where``.
MAX_CONCURRENT_PROPERTY_GETS = 256
#: A lease longer than a day is a mistake rather than a plan.
MAX_LEASE = 86_400.0
#: Seconds a Set on ``services.<name>`` waits for the device by default (the gateway passes less
#: when its call timeout is shorter, so that the caller hears why nothing was registered).
DEFAULT_REGISTER_TIMEOUT = 10.0
#: Seconds a burst of registrations is gathered before the persistence file is written once.
_SAVE_DELAY = 0.2

_REGISTER_PARAMS = ("type", "lease")


def check_url(url: str) -> str:
    """Return ``url`` when a Set may register it, else raise InvalidArgument saying what is wrong."""
    shown = repr(url[:120])
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as e:
        raise InvalidArgument(f"malformed URL {shown}: {e}") from None
    if parts.scheme == "local" or url == "local":
        raise InvalidArgument("in-process (local) services come from the gateway's config; register a URL")
    if parts.scheme not in REGISTRABLE_SCHEMES:
        known = ", ".join(f"{s}://" for s in REGISTRABLE_SCHEMES)
        raise InvalidArgument(f"malformed URL {shown}: expected one of {known}")
    if any(c.isspace() for c in url):
        raise InvalidArgument(f"malformed URL {shown}: it contains whitespace")
    if parts.scheme == "serial":
        if not parts.path or parts.path == "/":
            raise InvalidArgument(f"malformed URL {shown}: expected serial:///dev/ttyUSB0?baudrate=115200")
        return url
    if not parts.hostname or port is None or port == 0:
        raise InvalidArgument(
            f"malformed URL {shown}: expected {parts.scheme}://host:port with a port 1-65535"
        )
    if parts.path not in ("", "/"):
        if parts.scheme == "grpc":
            # grpc://host:port/SERVICE names the service on the other gateway.
            try:
                validate_service_name(parts.path[1:])
            except InvalidArgument as e:
                expected = "grpc://host:port or grpc://host:port/SERVICE"
                raise InvalidArgument(f"malformed URL {shown}: expected {expected}: {e.message}") from None
            return url
        raise InvalidArgument(f"malformed URL {shown}: expected {parts.scheme}://host:port with no path")
    return url


#: The type a backend has before its device says what it is (a proxy before the greeting).
_PLACEHOLDER_TYPE = BackendInfo().type


class ServiceEntry(Resource):
    """One known service; its own value is its contact URL."""

    type: Annotated[str, Prop(readonly=True, doc="resource type: mobile_robot, sensor, registry, group, ...")]
    url: Annotated[
        str, Prop(readonly=True, doc="contact URL: local, tcp://host:port, serial://..., grpc://...")
    ]
    state: Annotated[str, Prop(readonly=True, doc="up or down")]
    last_seen: Annotated[float, Prop(readonly=True, doc="when it was last heard of, unix seconds")]
    misses: Annotated[int, Prop(readonly=True, doc="liveness checks missed in a row")]
    location: Annotated[Vector, Prop(readonly=True, gui="pose", doc="the service's own location; () if none")]

    def __init__(self, info: BackendInfo, state: str = "up", registry: Registry | None = None) -> None:
        self.type = info.type
        self.url = info.url
        self.state = state
        self.last_seen = round(time.time(), 3)
        self.misses = 0
        self.location = np.zeros(0)
        self._registry = registry
        self._lease_until: float | None = None  # time.monotonic()
        self._down_since: float | None = None  # time.monotonic()

    def _value(self) -> str:
        return self.url

    @property
    def lease(
        self,
    ) -> Annotated[float, Prop(doc="seconds left on the lease; 0: no lease (polled). Set to renew")]:
        if self._lease_until is None:
            return 0.0
        return round(max(0.0, self._lease_until - time.monotonic()), 3)

    @lease.setter
    def lease(self, seconds: float) -> None:
        if self._registry is None:
            raise Unavailable("this registry holds no leases")
        self._registry.renew(self._ps_name, seconds)


class ServiceList(Resource):
    """The known services, one child namespace each."""


class Registry(Resource):
    """The resource service: who exists, how to reach them, are they alive, find them by parameters."""

    resource_type = "registry"

    services: ServiceList
    period: Annotated[float, Prop(readonly=True, doc="seconds between liveness checks; 0: no checks")]
    timeout: Annotated[float, Prop(readonly=True, doc="seconds a service gets to answer a liveness check")]
    misses: Annotated[int, Prop(readonly=True, doc="missed checks in a row before a service is down")]
    grace: Annotated[float, Prop(readonly=True, doc="seconds a registered service may stay down")]
    revision: Annotated[
        int, Prop(readonly=True, doc="counts joins, leaves and changes of type or state (Listen to follow)")
    ]

    def __init__(
        self,
        *,
        directory: Directory | None = None,
        period: float = 5.0,
        timeout: float = 2.0,
        misses: int = 3,
        grace: float = 60.0,
        register_timeout: float = DEFAULT_REGISTER_TIMEOUT,
        static: Iterable[str] = (),
        persist: str | os.PathLike[str] | None = None,
    ) -> None:
        for what, value in (("period", period), ("grace", grace)):
            if not (math.isfinite(value) and value >= 0):
                raise InvalidArgument(f"{what} must be zero or a positive number of seconds, got {value}")
        for what, value in (("timeout", timeout), ("register_timeout", register_timeout)):
            if not (math.isfinite(value) and value > 0):
                raise InvalidArgument(f"{what} must be a positive number of seconds, got {value}")
        if isinstance(misses, bool) or not isinstance(misses, int) or misses < 1:
            raise InvalidArgument(f"misses must be a positive whole number, got {misses!r}")
        self.services = ServiceList()
        self.period = float(period)
        self.timeout = float(timeout)
        self.misses = misses
        self.grace = float(grace)
        self.revision = 0
        self._register_timeout = float(register_timeout)
        self._directory = directory
        self._static = set(static)
        self._persist = Path(persist) if persist else None
        #: name → (url, options) of registrations that go into the persistence file.
        self._dynamic: dict[str, tuple[str, dict[str, str]]] = {}
        self._index = ServiceIndex()
        self._locating: dict[str, asyncio.Task[None]] = {}
        self._location_subs: dict[str, Subscription] = {}
        self._state_watchers: list[Callable[[str, str], None]] = []
        self._unwatch: Callable[[], None] | None = None
        self._liveness: asyncio.Task[None] | None = None
        self._save_handle: asyncio.TimerHandle | None = None
        self._busy: set[str] = set()  # names being registered or unregistered right now

    # -- the plain methods the gateway calls ------------------------------

    def names(self) -> list[str]:
        """The known service names, in the order they joined."""
        return list(self.services.children())

    def add(self, name: str, info: BackendInfo) -> None:
        """Record service ``name``, or refresh it: new type and URL, state up, ``last_seen`` now."""
        validate_service_name(name)
        existing = self.services.children().get(name)
        if isinstance(existing, ServiceEntry):
            url_changed = existing.url != info.url
            existing.type = info.type
            existing.url = info.url
            existing.last_seen = round(time.time(), 3)
            self._set_state(name, existing, "up")
            self._index.set_type(name, info.type)
            if url_changed:
                existing.changed()
            self.revision += 1
            return
        self.services.attach(name, ServiceEntry(info, registry=self))
        self._index.put(name, info.type, True)
        self.revision += 1

    def remove(self, name: str) -> None:
        """Forget service ``name``; NotFound if it is not known."""
        self._entry(name)
        self._forget(name)

    def set_state(self, name: str, state: str) -> None:
        """Mark ``name`` up or down; going (or staying) up also refreshes ``last_seen``."""
        if state not in STATES:
            raise InvalidArgument(f"bad state {state!r}: use one of {', '.join(STATES)}")
        entry = self._entry(name)
        if state == "up":
            entry.last_seen = round(time.time(), 3)
            entry.misses = 0
        self._set_state(name, entry, state)

    def state_of(self, name: str) -> str:
        """``up`` or ``down``; NotFound when ``name`` is not known."""
        return self._entry(name).state

    def watch_states(self, listener: Callable[[str, str], None]) -> Callable[[], None]:
        """Call ``listener(name, state)`` on every change of state; returns a function that stops it."""
        self._state_watchers.append(listener)

        def unwatch() -> None:
            if listener in self._state_watchers:
                self._state_watchers.remove(listener)

        return unwatch

    # -- internals of the table --------------------------------------------

    def _entry(self, name: str) -> ServiceEntry:
        entry = self.services.children().get(name)
        if not isinstance(entry, ServiceEntry):
            raise NotFound(f"no service named {name!r} in the registry")
        return entry

    def _forget(self, name: str) -> None:
        if name not in self.services.children():
            return
        self.services.detach(name)
        self._index.remove(name)
        self.revision += 1
        task = self._locating.pop(name, None)
        if task is not None:
            task.cancel()
        sub = self._location_subs.pop(name, None)
        if sub is not None:
            self._spawn(close_quietly(sub), f"registry: unlisten {name}")
        if self._dynamic.pop(name, None) is not None:
            self._schedule_save()

    def _set_state(self, name: str, entry: ServiceEntry, state: str) -> None:
        if entry.state == state:
            return
        entry.state = state
        entry._down_since = _now() if state == "down" else None
        self._index.set_up(name, state == "up")
        self.revision += 1
        for listener in list(self._state_watchers):
            try:
                listener(name, state)
            except Exception:
                log.exception("a watcher of service states failed on %s -> %s", name, state)

    def _spawn(self, coro: Any, what: str) -> asyncio.Task[None]:
        task: asyncio.Task[None] = asyncio.get_running_loop().create_task(coro, name=what)
        self._ps_tasks.add(task)
        task.add_done_callback(self._ps_tasks.discard)
        return task

    # -- following the directory --------------------------------------------

    async def start(self) -> None:
        directory = self._directory
        if directory is None:
            return
        self._unwatch = directory.watch(self._on_directory)
        for name in directory.names():
            try:
                self._on_directory(name, directory.backend(name))
            except PropertyError:
                continue
        if self._persist is not None:
            await self._restore()
        if self.period > 0:
            self._liveness = self._spawn(self._liveness_loop(), "registry: liveness")

    async def stop(self) -> None:
        if self._unwatch is not None:
            self._unwatch()
            self._unwatch = None
        if self._save_handle is not None:
            self._save_handle.cancel()
            self._save_handle = None
            self._save()
        for sub in list(self._location_subs.values()):
            await close_quietly(sub)
        self._location_subs.clear()

    def _on_directory(self, name: str, backend: Backend | None) -> None:
        if backend is None:
            self._forget(name)
            return
        self.add(name, backend.info)
        if name not in self._locating:
            self._locating[name] = self._spawn(self._locate(name, backend), f"registry: locate {name}")

    async def _locate(self, name: str, backend: Backend) -> None:
        """Follow the service's ``location`` when it has one.

        A device that is not reachable yet (a proxy still connecting) is
        asked again, less and less often, until it answers or leaves.
        """

        def on_change(change: Change) -> None:
            self._store_location(name, "" if change.removed else change.value)

        pause = 0.05
        while True:
            try:
                async with asyncio.timeout(self.timeout):
                    sub = await backend.listen("location", on_change)
                break
            except TimeoutError:
                pass
            except PropertyError as e:
                if e.code not in (Code.UNAVAILABLE, Code.DEADLINE_EXCEEDED):
                    self._learn_type(name, backend)
                    return  # no location (NOT_FOUND) or not listenable: nothing to follow
            await asyncio.sleep(pause)
            pause = min(pause * 2, max(1.0, self.period))
        self._learn_type(name, backend)
        if name not in self.services.children():
            await close_quietly(sub)
            return
        self._location_subs[name] = sub
        try:
            async with asyncio.timeout(self.timeout):
                value = await backend.get("location")
        except (PropertyError, TimeoutError):
            return
        self._store_location(name, value)

    def _learn_type(self, name: str, backend: Backend) -> None:
        """Take the type a device told in its greeting, unless the registration declared one.

        A proxy is served before its device greets, so the entry starts with
        the placeholder type; the device has greeted once it has answered.
        """
        entry = self.services.children().get(name)
        if not isinstance(entry, ServiceEntry) or self._dynamic.get(name, ("", {}))[1].get("type"):
            return
        kind = backend.info.type
        if kind and kind not in (entry.type, _PLACEHOLDER_TYPE):
            entry.type = kind
            self._index.set_type(name, kind)
            self.revision += 1

    def _store_location(self, name: str, text: str) -> None:
        entry = self.services.children().get(name)
        if not isinstance(entry, ServiceEntry):
            return
        try:
            vector = parse_vector(text) if text else np.zeros(0)
        except ValueFormatError:
            vector = np.zeros(0)
        entry.location = vector
        self._index.set_location(name, vector if vector.size >= 2 else None)

    # -- registration by Set -------------------------------------------------

    async def register(self, name: str, url: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        """Create the backend for ``url`` and serve it as ``name`` (what a Set on ``services.<name>`` does).

        Raises InvalidArgument (bad name, URL or parameter), AlreadyExists
        (name taken by another URL), Unavailable or DeadlineExceeded (the
        device does not answer; nothing stays registered).
        """
        validate_service_name(name)
        url = check_url(url.strip())
        for key in params:
            if key not in _REGISTER_PARAMS:
                raise InvalidArgument(
                    f"registering {name!r}: unknown parameter {key[:64]!r} "
                    f"(known: {', '.join(_REGISTER_PARAMS)})"
                )
        lease = _parse_lease(params["lease"]) if "lease" in params else None
        directory = self._require_directory()
        existing = self.services.children().get(name)
        if name in self._busy:
            raise AlreadyExists(f"{name!r} is being registered or unregistered right now")
        if isinstance(existing, ServiceEntry) or name in directory.names():
            if isinstance(existing, ServiceEntry) and existing.url == url:
                self.set_state(name, "up")  # the same registration again: a sign of life
                if lease is not None:
                    self.renew(name, lease)
                return url
            taken_by = existing.url if isinstance(existing, ServiceEntry) else "another service"
            raise AlreadyExists(f"the name {name!r} is taken (by {taken_by}); unregister it first")
        declared = params.get("type", "").strip()
        self._busy.add(name)
        try:
            await self._open(directory, name, url)
        except asyncio.CancelledError:
            # The caller gave up first (the gateway's call timeout is shorter than
            # register_timeout): a half-made registration must not stay behind.
            undo = self._spawn(self._close_quietly_registered(directory, name), f"registry: undo {name}")
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.shield(undo)
            raise
        finally:
            self._busy.discard(name)
        entry = self._entry(name)
        # The proxy learns the type from the device's greeting; a declared type wins.
        kind = declared or directory.backend(name).info.type
        if kind != entry.type:
            entry.type = kind
            self._index.set_type(name, kind)
            self.revision += 1
        if lease is not None:
            self.renew(name, lease)
        options = {"type": declared} if declared else {}
        self._dynamic[name] = (url, options)
        self._schedule_save()
        return url

    async def _open(self, directory: Directory, name: str, url: str) -> None:
        timeout = self._register_timeout
        # One deadline for creating the backend and for the device's first answer together:
        # the gateway's call timeout is set longer than register_timeout, so the caller gets
        # this method's clear answer rather than a bare DEADLINE_EXCEEDED.
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        try:
            async with asyncio.timeout_at(deadline):
                await directory.register(name, url)
        except TimeoutError:
            raise DeadlineExceeded(
                f"registering {name!r}: {url} did not answer within {timeout:g} s; nothing was registered"
            ) from None
        except PropertyError as e:
            if e.code in (Code.INVALID_ARGUMENT, Code.ALREADY_EXISTS):
                raise
            raise type(e)(f"registering {name!r}: {e.message}; nothing was registered", e.code) from None
        # A device that is not reachable, or accepts a connection but never
        # answers, is not registered either. A proxy connects in the
        # background, so "not connected yet" is asked again until the deadline.
        last: PropertyError | None = None
        try:
            backend = directory.backend(name)
            # A line-protocol proxy says when the device greeted, and why not (cannot connect)
            # when the deadline comes: outside the timeout scope, so that reason is not lost.
            await backend.wait_connected(max(0.0, deadline - loop.time()))
            async with asyncio.timeout_at(deadline):
                pause = 0.02
                while True:
                    try:
                        await backend.get("properties")
                        break
                    except PropertyError as e:
                        if e.code is not Code.UNAVAILABLE:
                            raise
                        last = e
                    await asyncio.sleep(pause)
                    pause = min(pause * 2, 0.5)
        except (TimeoutError, PropertyError) as e:
            await self._close_quietly_registered(directory, name)
            if isinstance(e, PropertyError):
                last = e
            if last is None:
                raise DeadlineExceeded(
                    f"registering {name!r}: {url} did not answer within {timeout:g} s; nothing was registered"
                ) from None
            raise type(last)(
                f"registering {name!r}: {url} does not answer ({last.message}); nothing was registered",
                last.code,
            ) from None
        if name not in self.services.children():  # the directory does not tell its watchers before returning
            self._on_directory(name, directory.backend(name))

    async def _close_quietly_registered(self, directory: Directory, name: str) -> None:
        with contextlib.suppress(PropertyError):
            await directory.unregister(name)
        self._forget(name)

    async def unregister(self, name: str) -> None:
        """Remove service ``name`` (what a Set of ``services.<name>`` to the empty value does)."""
        validate_service_name(name)
        entry = self._entry(name)
        if entry.url == "local" or name in self._busy:
            raise PropertyError(
                f"{name!r} runs inside the gateway and cannot be unregistered", Code.FAILED_PRECONDITION
            )
        directory = self._require_directory()
        self._busy.add(name)
        try:
            await directory.unregister(name)
        except NotFound:
            pass
        finally:
            self._busy.discard(name)
        self._forget(name)

    def renew(self, name: str, seconds: float) -> None:
        """Give ``name`` a lease of ``seconds`` from now (0 ends the lease: it is polled again)."""
        seconds = _check_lease(seconds)
        entry = self._entry(name)
        if seconds == 0:
            entry._lease_until = None
        else:
            entry._lease_until = _now() + seconds
            entry.last_seen = round(time.time(), 3)
            entry.misses = 0
            self._set_state(name, entry, "up")
        entry.changed("lease")

    def _require_directory(self) -> Directory:
        if self._directory is None:
            raise Unavailable("this registry cannot change the services: it was started without a directory")
        return self._directory

    # -- liveness ------------------------------------------------------------

    async def _liveness_loop(self) -> None:
        while True:
            await asyncio.sleep(self.period if self.period > 0 else 1.0)
            if self.period > 0:
                await self.check_all()

    async def check_all(self) -> None:
        """One round of liveness checks (the loop runs it every ``period``; tests call it directly)."""
        directory = self._directory
        if directory is None:
            return
        now = _now()
        polled: list[str] = []
        for name, entry in list(self.services.children().items()):
            if not isinstance(entry, ServiceEntry) or entry.url == "local" or name in self._busy:
                continue
            if entry._lease_until is not None:
                if now > entry._lease_until:
                    self._miss(name, entry, lapsed=True)
            else:
                polled.append(name)

        async def check(name: str) -> None:
            entry = self.services.children().get(name)
            if isinstance(entry, ServiceEntry):
                await self._check(directory, name, entry)

        await run_bounded(polled, check, MAX_CONCURRENT_CHECKS)
        for name, entry in list(self.services.children().items()):
            if not isinstance(entry, ServiceEntry) or entry.state != "down" or entry._down_since is None:
                continue
            if name in self._static or entry.url == "local" or name in self._busy:
                continue
            if _now() - entry._down_since >= self.grace:
                log.info("service %s was down for %g s: removing it", name, self.grace)
                try:
                    await self.unregister(name)
                except PropertyError as e:
                    log.warning("removing %s failed: %s", name, e.message)

    async def _check(self, directory: Directory, name: str, entry: ServiceEntry) -> None:
        try:
            backend = directory.backend(name)
            async with asyncio.timeout(self.timeout):
                await backend.check()
        except (PropertyError, TimeoutError):
            self._miss(name, entry)
            return
        self._learn_type(name, backend)
        entry.misses = 0
        entry.last_seen = round(time.time(), 3)
        self._set_state(name, entry, "up")

    def _miss(self, name: str, entry: ServiceEntry, *, lapsed: bool = False) -> None:
        if lapsed:
            entry.misses = max(entry.misses, self.misses)
        else:
            entry.misses += 1
        if entry.misses >= self.misses:
            self._set_state(name, entry, "down")

    # -- search --------------------------------------------------------------

    @functional(doc="names of the services matching type, location, state and property values")
    async def find(
        self,
        *,
        type: str = "",
        near: str = "",
        radius: str = "",
        state: str = "",
        limit: str = "",
        where: str = "",
    ) -> list[str]:
        """Find services: ``type`` (a type or a list of types), ``near`` (x y [z]) with ``radius`` metres,
        ``state`` (up or down), ``where`` (property=value pairs joined by &), at most ``limit`` names.

        Sorted nearest first when ``near`` is given, else by name.
        """
        given = {"type": type, "near": near, "radius": radius, "state": state, "limit": limit, "where": where}
        query = Query.parse({k: v for k, v in given.items() if v != ""})
        if query.near is not None:
            pending = [t for t in self._locating.values() if not t.done()]
            if pending:  # services that joined a moment ago: their locations are on the way
                await asyncio.wait(pending, timeout=self.timeout)
        names = self._index.select(query)
        if query.props:
            names = await self._where(names, query.props)
        if query.limit is not None:
            names = names[: query.limit]
        return names

    async def _where(self, names: list[str], props: Mapping[str, str]) -> list[str]:
        directory = self._directory
        if directory is None:
            raise Unavailable("this registry cannot ask services for their properties: it has no directory")
        timeout = self.timeout
        matching: set[str] = set()

        async def match(name: str) -> None:
            try:
                backend = directory.backend(name)
                async with asyncio.timeout(timeout):
                    for path, expected in props.items():
                        if not values_equal(expected, await backend.get(path)):
                            return
            except (PropertyError, TimeoutError):
                return
            matching.add(name)

        await run_bounded(names, match, MAX_CONCURRENT_PROPERTY_GETS)
        return [n for n in names if n in matching]

    # -- persistence ---------------------------------------------------------

    def _schedule_save(self) -> None:
        if self._persist is None or self._save_handle is not None:
            return
        self._save_handle = asyncio.get_running_loop().call_later(_SAVE_DELAY, self._save)

    def _save(self) -> None:
        self._save_handle = None
        path = self._persist
        if path is None:
            return
        data = {"services": {n: {"url": u, "options": o} for n, (u, o) in sorted(self._dynamic.items())}}
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile("w", dir=path.parent, prefix=path.name, delete=False) as f:
                json.dump(data, f, indent=1)
            os.replace(f.name, path)
        except OSError as e:
            log.error("cannot save the registrations to %s: %s", path, e)

    async def _restore(self) -> None:
        path = self._persist
        assert path is not None
        try:
            text = path.read_text()
        except FileNotFoundError:
            return
        except OSError as e:
            log.error("cannot read the registrations in %s: %s", path, e)
            return
        try:
            saved = json.loads(text)["services"]
            items = [
                (str(n), str(v["url"]), {str(k): str(x) for k, x in v.get("options", {}).items()})
                for n, v in saved.items()
            ]
        except (ValueError, KeyError, TypeError, AttributeError) as e:
            log.error("ignoring %s: not a registrations file (%s)", path, e)
            return

        async def one(name: str, url: str, options: dict[str, str]) -> None:
            try:
                await self.register(name, url, options)
            except PropertyError as e:
                log.warning("cannot restore the registration of %s at %s: %s", name, url, e.message)
                self._dynamic[name] = (url, options)  # kept for the next start

        await asyncio.gather(*(one(*item) for item in items))


def _now() -> float:
    return time.monotonic()


def _parse_lease(text: str) -> float:
    try:
        return _check_lease(parse_number(text))
    except InvalidArgument as e:
        raise InvalidArgument(f"bad parameter lease: {e.message}") from None


def _check_lease(seconds: float) -> float:
    if not (math.isfinite(seconds) and 0 <= seconds <= MAX_LEASE):
        raise InvalidArgument(f"a lease is 0 to {format_number(MAX_LEASE)} seconds, got {seconds}")
    return float(seconds)


class RegistryService(LocalService):
    """Serves a :class:`Registry`, and turns Sets on ``services.<name>`` into (un)registrations.

    ``services.<name>`` is a namespace with its own value (the URL), which
    the class wrapper treats as read-only; this is the one place it is written.
    """

    def __init__(self, registry: Registry, url: str = "local") -> None:
        super().__init__(registry, url)
        self.registry = registry

    async def set(self, path: str, value: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        head, dot, name = path.partition(".")
        if head == "services" and dot and "." not in name:
            if value.strip() == "":
                if params:
                    raise InvalidArgument(f"unregistering {name!r} takes no parameters")
                await self.registry.unregister(name)
                return ""
            return await self.registry.register(name, value, params)
        return await super().set(path, value, params)
