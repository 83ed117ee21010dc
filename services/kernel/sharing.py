"""One upstream listen per (path, parameters), shared by every local listener of it.

A proxy (a device on a line, another gateway) pays for each listen it opens
upstream: a LISTEN line, a remote stream. :class:`SharedListens` opens one
per key and hands every further local listener of the same key to it,
counting them; when the last one leaves, the upstream listen is closed.

The key is the path **and** the request parameters (:func:`listen_key`):
two listens of ``location`` in different frames are two upstream listens,
never one that answers both with the first one's values.

The table knows nothing of what an upstream listen is: the owner says how to
make an entry (its own :class:`SharedListen` subclass, which holds the
upstream state), how to open it and how to close it.
"""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Awaitable, Callable, Iterator, Mapping
from typing import Generic, TypeVar

from services.kernel.backend import Change, Notify, OnRaise, Subscription, tell_each
from services.kernel.errors import Unavailable

__all__ = ["ListenKey", "SharedListen", "SharedListens", "listen_key"]

#: (path, the parameters as sorted (name, value) pairs).
ListenKey = tuple[str, tuple[tuple[str, str], ...]]


def listen_key(path: str, params: Mapping[str, str]) -> ListenKey:
    """The key that tells shared listens apart: the path and the parameters, in a fixed order."""
    return (path, tuple(sorted(params.items())) if params else ())


class SharedListen:
    """One upstream listen of (``path``, ``params``) and the local listeners that share it.

    Subclass it to keep the upstream state (a call, a poller, the last value).
    """

    def __init__(self, path: str, params: Mapping[str, str]) -> None:
        self.path = path
        self.params: dict[str, str] = dict(params)
        self.key = listen_key(path, params)
        self.listeners: dict[int, Notify] = {}
        #: Resolved once the upstream listen is open (failed when it could not be opened).
        self.ready: asyncio.Future[None] | None = None

    def deliver(self, change: Change) -> None:
        """Hand ``change`` to every listener; one that raises is logged and keeps its place (its
        share's close takes it out, and the last one's closes the upstream listen)."""
        tell_each(self.listeners, change, what=self.path, on_raise=OnRaise.KEEP)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.path!r}, {self.params!r}, {len(self.listeners)} listeners)"


E = TypeVar("E", bound=SharedListen)


class _Share(Subscription, Generic[E]):
    """One local listener's place in a shared listen."""

    def __init__(self, table: SharedListens[E], entry: E, token: int) -> None:
        self._table = table
        self._entry = entry
        self._token = token

    @property
    def entry(self) -> E:
        """The shared listen this listener holds a place in."""
        return self._entry

    async def close(self) -> None:
        await self._table.leave(self._entry, self._token)


class SharedListens(Generic[E]):
    """The shared listens of one backend, by (path, parameters); see the module docstring.

    ``make(path, params)`` builds an entry; ``open_upstream(entry)`` opens
    its upstream listen (raise to refuse: the error reaches every listener
    that waited for it); ``close_upstream(entry)`` closes it once its last
    listener left, also when the entry was already :meth:`drop`-ped from the
    table.
    """

    def __init__(
        self,
        make: Callable[[str, Mapping[str, str]], E],
        open_upstream: Callable[[E], Awaitable[None]],
        close_upstream: Callable[[E], Awaitable[None]],
    ) -> None:
        self._make = make
        self._open = open_upstream
        self._close = close_upstream
        self._entries: dict[ListenKey, E] = {}
        #: path → the entries on it (a device's events and GONE lines name only the path).
        self._by_path: dict[str, dict[ListenKey, E]] = {}
        self._tokens = itertools.count()

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str]) -> _Share[E]:
        """Add ``notify`` to the shared listen of (``path``, ``params``), opening it if it is the first."""
        key = listen_key(path, params)
        entry = self._entries.get(key)
        if entry is None:
            entry = self._make(path, params)
            ready = entry.ready = asyncio.get_running_loop().create_future()
            self._put(entry)
            try:
                await self._open(entry)
            except BaseException as exc:
                self.drop(entry)
                ready.set_exception(exc if isinstance(exc, Exception) else Unavailable("listen cancelled"))
                ready.exception()  # retrieved: the waiters re-raise it themselves
                raise
            ready.set_result(None)
        elif entry.ready is not None and not entry.ready.done():
            await asyncio.shield(entry.ready)
        token = next(self._tokens)
        entry.listeners[token] = notify
        return _Share(self, entry, token)

    async def leave(self, entry: E, token: int) -> None:
        """Take one listener away; close the upstream listen when it was the last."""
        if entry.listeners.pop(token, None) is None or entry.listeners:
            return
        self.drop(entry)
        await self._close(entry)

    def _put(self, entry: E) -> None:
        self._entries[entry.key] = entry
        self._by_path.setdefault(entry.path, {})[entry.key] = entry

    def drop(self, entry: E) -> bool:
        """Take ``entry`` out of the table (its upstream ended); False when it was not in it.

        Its listeners stay attached to it; leaving it still closes it.
        """
        if self._entries.get(entry.key) is not entry:
            return False
        del self._entries[entry.key]
        on_path = self._by_path[entry.path]
        del on_path[entry.key]
        if not on_path:
            del self._by_path[entry.path]
        return True

    def holds(self, entry: E) -> bool:
        """True while ``entry`` is the table's shared listen of its key."""
        return self._entries.get(entry.key) is entry

    def on_path(self, path: str) -> list[E]:
        """The shared listens of ``path``, whatever their parameters."""
        on_path = self._by_path.get(path)
        return list(on_path.values()) if on_path else []

    def paths(self) -> list[str]:
        """The paths listened to, one per shared listen, oldest first."""
        return [entry.path for entry in self._entries.values()]

    def clear(self) -> list[E]:
        """Empty the table (the owner closes); return what was in it."""
        entries = list(self._entries.values())
        self._entries.clear()
        self._by_path.clear()
        return entries

    def __iter__(self) -> Iterator[E]:
        return iter(list(self._entries.values()))

    def __len__(self) -> int:
        return len(self._entries)
