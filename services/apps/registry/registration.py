"""Registering and unregistering services by Set: ``services.<name>`` set to a URL, or to nothing."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable, Mapping

from services.apps.registry.allow import AllowList
from services.apps.registry.entry import parse_lease
from services.apps.registry.persistence import Registration
from services.apps.registry.scheduling import parse_capabilities
from services.apps.registry.store import RegistryStore
from services.apps.registry.table import ServiceTable
from services.apps.registry.urls import check_url
from services.kernel.backend import NO_PARAMS, Backend
from services.kernel.core import RESERVED_NAMES
from services.kernel.directory import Directory, own_work
from services.kernel.errors import (
    AlreadyExists,
    Code,
    DeadlineExceeded,
    InvalidArgument,
    NotFound,
    PermissionDenied,
    PropertyError,
    ResourceExhausted,
    Unavailable,
)
from services.kernel.paths import validate_service_name

__all__ = ["DEFAULT_MAX_REGISTRATIONS", "DEFAULT_REGISTER_TIMEOUT", "RESERVED_SERVICE_NAMES", "Registrations"]

log = logging.getLogger(__name__)

#: Registrations by Set the registry holds at once (``[registry] max_registrations``): each one
#: is a proxy with a connection and tasks, so an unbounded number is a way to exhaust the gateway.
DEFAULT_MAX_REGISTRATIONS = 256

#: Names no registration may take: those every service reserves for itself (``services.properties``
#: is the list of names, ``services.gui`` metadata). ``registry`` is always served, hence taken.
RESERVED_SERVICE_NAMES = RESERVED_NAMES

#: Answers "may this caller administer service NAME?"; the default: nobody may.
AdminCheck = Callable[[str], bool]


def _nobody_is_admin(name: str) -> bool:
    return False


#: Seconds a Set on ``services.<name>`` waits for the device by default (the gateway passes less
#: when its call timeout is shorter, so that the caller hears why nothing was registered).
DEFAULT_REGISTER_TIMEOUT = 10.0

_REGISTER_PARAMS = ("type", "lease", "features")
#: Codes with which a device's greeting is refused (docs/line-protocol.md §3).
_REFUSALS = (Code.FAILED_PRECONDITION, Code.INVALID_ARGUMENT)
#: Codes that say only that nothing answered as a device, for whatever reason (see :meth:`_open`).
_NOT_REACHED = (Code.UNAVAILABLE, Code.DEADLINE_EXCEEDED)


def parse_features(text: str) -> frozenset[str]:
    """The ``features`` parameter of a registration: ``(video ptz mobile)``, the capabilities it offers."""
    return parse_capabilities(text, "bad parameter features")


class Registrations:
    """Turns registrations into backends through a :class:`Directory`, and remembers them.

    ``records`` holds the registrations made by Set (name → (url, options)); ``store`` keeps
    them (:mod:`services.apps.registry.store`: this gateway's memory and file, or etcd). While the
    store is read-only, registrations and unregistrations answer UNAVAILABLE with its reason.
    ``forget(name)`` drops a service from the registry; ``joined(name,
    backend)`` records one that the directory now serves.
    """

    def __init__(
        self,
        table: ServiceTable,
        directory: Directory | None,
        *,
        timeout: float,
        forget: Callable[[str], None],
        joined: Callable[[str, Backend], None],
        store: RegistryStore,
        allow: AllowList | None = None,
        configured: frozenset[str] = frozenset(),
        max_registrations: int = DEFAULT_MAX_REGISTRATIONS,
    ) -> None:
        self.table = table
        self.allow = allow if allow is not None else AllowList()
        #: Names from the gateway's config: never unregistered or replaced from outside.
        self.configured = configured
        self.max_registrations = max_registrations
        #: The admin check (see :meth:`services.apps.registry.Registry.set_admin_check`).
        self.may_administer: AdminCheck = _nobody_is_admin
        self.directory = directory
        self.timeout = timeout
        self.records: dict[str, Registration] = {}
        self._forget = forget
        self._joined = joined
        self.store = store
        self._busy: set[str] = set()  # names being registered or unregistered right now
        self._undoing: set[asyncio.Task[None]] = set()
        #: Registrations being dropped from the store (a service that left), each one task.
        self._dropping: set[asyncio.Task[None]] = set()

    def busy(self, name: str) -> bool:
        """``name`` is being registered or unregistered right now."""
        return name in self._busy

    def declared_type(self, name: str) -> str:
        """The type the registration of ``name`` declared; empty when none (or not registered by Set)."""
        record = self.records.get(name)
        return record[1].get("type", "") if record else ""

    def declared_features(self, name: str) -> frozenset[str]:
        """The capabilities the registration of ``name`` declared (``features``); empty when none."""
        record = self.records.get(name)
        text = record[1].get("features", "") if record else ""
        return parse_features(text) if text else frozenset()

    def drop(self, name: str) -> None:
        """Forget the registration record of ``name`` (it left), here and in the store."""
        if self.records.pop(name, None) is not None:
            task = asyncio.get_running_loop().create_task(
                self._drop_kept(name), name=f"registry: drop {name}"
            )
            self._dropping.add(task)
            task.add_done_callback(self._dropping.discard)

    async def _drop_kept(self, name: str) -> None:
        try:
            await self.store.drop(name)
        except PropertyError as e:
            log.warning("the registry store still keeps %s: %s", name, e.message)

    async def settle(self) -> None:
        """Wait until every registration that left is dropped from the store (the registry stops)."""
        while self._dropping:
            await asyncio.gather(*self._dropping, return_exceptions=True)

    def check_writable(self, doing: str) -> None:
        """Raise UNAVAILABLE, saying why, while the store cannot keep a change."""
        reason = self.store.read_only
        if reason:
            raise Unavailable(f"{doing}: the registry is read-only: {reason}")

    def keep(self, name: str, url: str, options: dict[str, str]) -> None:
        """Keep a registration that could not be restored, for the next start."""
        self.records[name] = (url, options)

    def require_directory(self) -> Directory:
        """The directory, or Unavailable when the registry has none."""
        if self.directory is None:
            raise Unavailable("this registry cannot change the services: it was started without a directory")
        return self.directory

    async def register(self, name: str, url: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        """Create the backend for ``url`` and serve it as ``name``; see :meth:`Registry.register`."""
        self._check_name(name, "registered")
        url = check_url(url.strip())
        for key in params:
            if key not in _REGISTER_PARAMS:
                raise InvalidArgument(
                    f"registering {name!r}: unknown parameter {key[:64]!r} "
                    f"(known: {', '.join(_REGISTER_PARAMS)})"
                )
        lease = parse_lease(params["lease"]) if "lease" in params else None
        features = params.get("features", "").strip()
        if features:
            parse_features(features)  # checked before anything is made
        directory = self.require_directory()
        existing = self.table.get(name)
        if name in self._busy:
            raise AlreadyExists(f"{name!r} is being registered or unregistered right now")
        if existing is not None or name in directory:
            if existing is not None and existing.url == url:
                self.table.set_state(name, "up")  # the same registration again: a sign of life
                if lease is not None:
                    self.table.renew(name, lease)
                return url
            taken_by = existing.url if existing is not None else "another service"
            raise AlreadyExists(f"the name {name!r} is taken (by {taken_by}); unregister it first")
        self.check_writable(f"registering {name!r}")
        declared = params.get("type", "").strip()
        if len(self.records) + len(self._busy) >= self.max_registrations:
            raise ResourceExhausted(
                f"registering {name!r}: the registry holds {self.max_registrations} registrations "
                "already ([registry] max_registrations); unregister one first"
            )
        self._busy.add(name)
        try:
            # Before any connection: neither a port scanner nor a relay, nor a loop into itself.
            try:
                async with asyncio.timeout(self.timeout):
                    await self.allow.check(name, url)
            except TimeoutError:
                raise DeadlineExceeded(f"registering {name!r}: resolving {url[:120]} took too long") from None
            await self._open(directory, name, url)
        except asyncio.CancelledError:
            # The caller gave up first (the gateway's call timeout is shorter than
            # register_timeout): a half-made registration must not stay behind.
            undo = asyncio.get_running_loop().create_task(
                self._undo(directory, name), name=f"registry: undo {name}"
            )
            self._undoing.add(undo)
            undo.add_done_callback(self._undoing.discard)
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.shield(undo)
            raise
        finally:
            self._busy.discard(name)
        self.table.entry(name)
        # The proxy learns the type from the device's greeting; a declared type wins.
        self.table.set_type(name, declared or directory.backend(name).info.type)
        self.table.reached(name)  # _open waited for its first answer
        if lease is not None:
            self.table.renew(name, lease)
        options = {"type": declared} if declared else {}
        if features:
            options["features"] = features
        try:
            await self.store.save(name, url, options)
        except PropertyError as e:
            # The store went read-only while the device was opened: a registration it does not
            # keep would vanish at the next start, or from the other gateways' view.
            await self._undo(directory, name)
            raise Unavailable(
                f"registering {name!r}: the registry is read-only: {e.message}; nothing was registered"
            ) from None
        self.records[name] = (url, options)
        return url

    def _check_name(self, name: str, what: str) -> None:
        """A name a registration may take; nothing is changed when it is not."""
        validate_service_name(name)
        if name in RESERVED_SERVICE_NAMES:
            raise InvalidArgument(
                f"{name!r} is reserved (a name every service keeps for itself: "
                f"{', '.join(sorted(RESERVED_SERVICE_NAMES))}); it cannot be {what}"
            )

    async def _open(self, directory: Directory, name: str, url: str) -> None:
        timeout = self.timeout
        # One deadline for creating the backend and for the device's first answer together:
        # the gateway's call timeout is set longer than register_timeout, so the caller gets
        # this method's clear answer rather than a bare DEADLINE_EXCEEDED.
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        try:
            async with asyncio.timeout_at(deadline):
                await directory.register(name, url)
        except TimeoutError:
            raise self._not_reached(name, url, "no answer") from None
        except PropertyError as e:
            if e.code in (Code.INVALID_ARGUMENT, Code.ALREADY_EXISTS):
                raise
            if e.code in _NOT_REACHED:
                raise self._not_reached(name, url, e.message) from None
            raise type(e)(f"registering {name!r}: {e.message}; nothing was registered", e.code) from None
        # A device that is not reachable, or accepts a connection but never
        # answers, is not registered either. A proxy connects in the
        # background, so "not connected yet" is asked again until the deadline.
        last: PropertyError | None = None
        # The registry's own probe of what it opened, not a read for the caller who registers.
        with own_work():
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
                await self._undo(directory, name)
                if isinstance(e, PropertyError):
                    last = e
                if last is None or last.code in _NOT_REACHED:
                    raise self._not_reached(name, url, last.message if last else "no answer") from None
                # A device that answered with a greeting the gateway refused (another protocol
                # version, a bad field) did answer: say it was refused, and why.
                verb = "was refused" if last.code in _REFUSALS else "does not answer"
                raise type(last)(
                    f"registering {name!r}: {url} {verb} ({last.message}); nothing was registered",
                    last.code,
                ) from None
        if self.table.get(name) is None:  # the directory does not tell its watchers before returning
            self._joined(name, directory.backend(name))

    def _not_reached(self, name: str, url: str, reason: str) -> Unavailable:
        """The one answer for a device not reached, whatever the reason: the reason (refused,
        silent, not a device) would tell an open port from a closed one, so that the registry
        would scan ports for its caller. The gateway's log keeps the reason."""
        log.info("registering %r: %s not reached: %s", name, url, reason)
        return Unavailable(
            f"registering {name!r}: no device answered at {url} within {self.timeout:g} s; "
            "nothing was registered"
        )

    async def _undo(self, directory: Directory, name: str) -> None:
        with contextlib.suppress(PropertyError):
            await directory.unregister(name)
        self._forget(name)

    async def unregister(self, name: str) -> None:
        """Remove service ``name`` (what a Set of ``services.<name>`` to the empty value does)."""
        self._check_name(name, "unregistered")
        entry = self.table.entry(name)
        if name in self.configured and not entry.is_local() and not self.may_administer(name):
            raise PermissionDenied(
                f"{name!r} comes from the gateway's config and cannot be unregistered "
                "(only an admin may; no admin is configured)"
            )
        if entry.is_local() or name in self._busy:
            raise PropertyError(
                f"{name!r} runs inside the gateway and cannot be unregistered", Code.FAILED_PRECONDITION
            )
        directory = self.require_directory()
        self.check_writable(f"unregistering {name!r}")
        self._busy.add(name)
        try:
            await directory.unregister(name)
        except NotFound:
            pass
        finally:
            self._busy.discard(name)
        self._forget(name)
