"""The registry's table: one :class:`ServiceEntry` per service, and the search index beside it."""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from services.apps.query import ServiceIndex
from services.apps.registry.entry import STATES, ServiceEntry, ServiceList, check_lease, wall_clock
from services.kernel.backend import UNKNOWN_TYPE, BackendInfo
from services.kernel.errors import InvalidArgument, NotFound
from services.kernel.paths import validate_service_name
from services.kernel.values import Vector

__all__ = ["GONE", "PLACEHOLDER_TYPE", "ServiceTable"]

log = logging.getLogger(__name__)

#: The type a backend has before its device says what it is (a proxy before the greeting).
PLACEHOLDER_TYPE = UNKNOWN_TYPE

#: The "state" a member watcher hears when a service leaves the table.
GONE = "gone"


class ServiceTable:
    """The known services (the ``services`` namespace), their search index and who watches their states.

    ``bump()`` is called on every join, leave and change of type or state
    (the registry counts them in ``revision``).
    """

    def __init__(self, services: ServiceList, bump: Callable[[], None]) -> None:
        self.services = services
        #: The entries of ``services`` by name, in the order they joined: the table is the only
        #: writer of ``services``, and its ``children()`` is a copy of every entry, which made
        #: each lookup (several a registration, one a liveness check) grow with the registry.
        self._entries: dict[str, ServiceEntry] = {}
        self.index = ServiceIndex()
        self._bump = bump
        self._state_watchers: list[Callable[[str, str], None]] = []
        #: Watchers that also hear joins (with their first state) and leaves (as state "gone").
        self._member_watchers: list[Callable[[str, str], None]] = []
        #: Called with a service's name when its location is asked for (the registry follows it then).
        self.want_location: Callable[[str], None] | None = None

    # -- reading -------------------------------------------------------------

    def names(self) -> list[str]:
        """The known service names, in the order they joined."""
        return list(self._entries)

    def get(self, name: str) -> ServiceEntry | None:
        """The entry of ``name``, None when it is not known."""
        return self._entries.get(name)

    def entry(self, name: str) -> ServiceEntry:
        """The entry of ``name``; NotFound when it is not known."""
        entry = self.get(name)
        if entry is None:
            raise NotFound(f"no service named {name!r} in the registry")
        return entry

    def entries(self) -> list[tuple[str, ServiceEntry]]:
        """(name, entry) of every known service, a snapshot."""
        return list(self._entries.items())

    # -- changing --------------------------------------------------------------

    def add(self, name: str, info: BackendInfo, renew: Callable[[str, float], None]) -> None:
        """Record ``name``, or refresh it: new type and URL, ``last_seen`` now.

        Its state is up, or "connecting" while its type is still unknown (a proxy not yet reached).
        """
        validate_service_name(name)
        state = "connecting" if info.type == PLACEHOLDER_TYPE else "up"
        existing = self.get(name)
        if existing is not None:
            url_changed = existing.url != info.url
            existing.type = info.type
            existing.url = info.url
            existing.last_seen = wall_clock()
            self._mark(name, existing, state)
            self.index.set_type(name, info.type)
            if url_changed:
                existing.changed()
            self._bump()
            return
        entry = ServiceEntry(name, info, state, renew=renew, want_location=self._wanted)
        self.services.attach(name, entry)
        self._entries[name] = entry
        self.index.put(name, info.type, state == "up")
        self._bump()
        self._tell(self._member_watchers, name, state)

    def forget(self, name: str) -> bool:
        """Drop ``name``; False when it was not known."""
        if self._entries.pop(name, None) is None:
            return False
        self.services.detach(name)
        self.index.remove(name)
        self._bump()
        self._tell(self._member_watchers, name, GONE)
        return True

    def set_state(self, name: str, state: str) -> None:
        """Mark ``name`` up or down; going (or staying) up also refreshes ``last_seen``."""
        if state not in STATES:
            raise InvalidArgument(f"bad state {state!r}: use one of {', '.join(STATES)}")
        entry = self.entry(name)
        if state == "up":
            entry.seen()
        self._mark(name, entry, state)

    def answered(self, name: str, entry: ServiceEntry) -> None:
        """``name`` answered a check: no misses, seen now, up."""
        entry.seen()
        self._mark(name, entry, "up")

    def missed(self, name: str, entry: ServiceEntry, *, allowed: int, lapsed: bool = False) -> None:
        """``name`` missed a check (or its lease lapsed); down after ``allowed`` misses in a row."""
        entry.misses = max(entry.misses, allowed) if lapsed else entry.misses + 1
        if entry.misses >= allowed:
            self._mark(name, entry, "down")

    def renew(self, name: str, seconds: float) -> None:
        """Give ``name`` a lease of ``seconds`` from now (0 ends the lease: it is polled again)."""
        seconds = check_lease(seconds)
        entry = self.entry(name)
        entry.set_lease(seconds)
        if seconds != 0:
            self.answered(name, entry)
        entry.changed("lease")

    def set_type(self, name: str, kind: str) -> None:
        """Change the type of ``name`` (known) when it differs."""
        entry = self.entry(name)
        if kind != entry.type:
            entry.type = kind
            self.index.set_type(name, kind)
            self._bump()

    def learn_type(self, name: str, kind: str) -> None:
        """Take the type a device told, unless it is empty or the placeholder; nothing for an unknown name.

        A service that answered has been reached: "connecting" becomes "up".
        """
        if self.get(name) is None:
            return
        if kind and kind != PLACEHOLDER_TYPE:
            self.set_type(name, kind)
        self.reached(name)

    def reached(self, name: str) -> None:
        """``name`` answered for the first time: "connecting" becomes "up" (other states stay)."""
        entry = self.entry(name)
        if entry.state == "connecting":
            entry.seen()
            self._mark(name, entry, "up")

    def _wanted(self, name: str) -> None:
        if self.want_location is not None:
            self.want_location(name)

    def set_location(self, name: str, location: Vector | None) -> None:
        """The service's own location (None: it has none); nothing for an unknown name."""
        entry = self.get(name)
        if entry is None:
            return
        entry.store_location(location if location is not None else np.zeros(0))
        self.index.set_location(name, location if location is not None and location.size >= 2 else None)

    # -- watching states -------------------------------------------------------

    def watch_states(
        self, listener: Callable[[str, str], None], *, members: bool = False
    ) -> Callable[[], None]:
        """Call ``listener(name, state)`` on every change of state; returns a function that stops it.

        With ``members``, also on every join (its first state) and leave (state :data:`GONE`).
        """
        watchers = self._member_watchers if members else self._state_watchers
        watchers.append(listener)

        def unwatch() -> None:
            if listener in watchers:
                watchers.remove(listener)

        return unwatch

    def _mark(self, name: str, entry: ServiceEntry, state: str) -> None:
        if not entry.mark(state):
            return
        self.index.set_up(name, state == "up")
        self._bump()
        self._tell(self._state_watchers, name, state)
        self._tell(self._member_watchers, name, state)

    @staticmethod
    def _tell(watchers: list[Callable[[str, str], None]], name: str, state: str) -> None:
        for listener in list(watchers):
            try:
                listener(name, state)
            except Exception:
                log.exception("a watcher of service states failed on %s -> %s", name, state)
