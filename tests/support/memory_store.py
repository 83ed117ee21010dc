"""A shared registry store held in memory: a test double of etcd for fast tests of the cluster's logic.

It keeps what :class:`services.apps.registry.store.SharedStore` promises, and nothing of etcd's wire:
keys in folders, keys bound to a gateway's lease (gone when the lease is ended, as when a gateway
dies), compare-and-set, a watch that reports every change on the event loop a moment later (as a
watch stream would), a server that can be stopped (every store is read-only) and started again,
empty or not. The cluster's integration tests run real etcd (``tests/support/etcd.py``); this
double only lets unit tests drive the cluster's decisions in milliseconds::

    server = MemoryServer()
    store_a, store_b = server.store("gw-a"), server.store("gw-b")
    ...
    server.end_lease("gw-a")   # gw-a's leased keys go, as when its lease expires
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable, Mapping
from typing import TypeVar

from services.apps.registry.store import Change, Kind, StoreListener
from services.kernel.errors import Unavailable

__all__ = ["MemoryServer", "MemoryStore"]

T = TypeVar("T")


class MemoryServer:
    """The keys every :class:`MemoryStore` of one test shares, and which lease each is bound to."""

    def __init__(self) -> None:
        #: (kind, name) → (value, the gateway id whose lease holds it, or None).
        self.keys: dict[tuple[Kind, str], tuple[str, str | None]] = {}
        self.stores: list[MemoryStore] = []
        #: Why the server cannot be reached; empty while it runs.
        self.down = ""

    def store(self, gateway_id: str) -> MemoryStore:
        """A store for gateway ``gateway_id``, on this server."""
        store = MemoryStore(self, gateway_id)
        self.stores.append(store)
        return store

    def value(self, kind: Kind, name: str) -> str | None:
        """A key's value now; None when absent."""
        held = self.keys.get((kind, name))
        return held[0] if held is not None else None

    def folder(self, kind: Kind) -> dict[str, str]:
        """Every key of one folder now."""
        return {name: value for (k, name), (value, _) in self.keys.items() if k is kind}

    def write(self, kind: Kind, name: str, value: str | None, lease: str | None = None) -> None:
        """Write (or delete, with None) a key and tell every watcher."""
        if value is None:
            if self.keys.pop((kind, name), None) is None:
                return
        else:
            self.keys[(kind, name)] = (value, lease)
        self._tell(Change(kind, name, value))

    def end_lease(self, gateway_id: str) -> None:
        """The lease of ``gateway_id`` expired: every key bound to it goes."""
        for (kind, name), (_, lease) in list(self.keys.items()):
            if lease == gateway_id:
                self.write(kind, name, None)

    def kill(self, gateway_id: str) -> None:
        """Gateway ``gateway_id`` died: its store hears and writes nothing more, and its lease ends."""
        for store in self.stores:
            if store.gateway_id == gateway_id:
                store.dead = True
        self.end_lease(gateway_id)

    def stop(self, reason: str = "connection refused") -> None:
        """The server cannot be reached from now on: every store is read-only."""
        self.down = reason
        for store in self.stores:
            store.read_only_changed()

    def start(self, *, empty: bool = False) -> None:
        """The server runs again (``empty``: restarted without its data); every store reconnects."""
        self.down = ""
        if empty:
            for kind, name in list(self.keys):
                self.write(kind, name, None)
        for store in self.stores:
            store.read_only_changed()
            if store.started:
                store.reconnected()

    def _tell(self, change: Change) -> None:
        for store in self.stores:
            store.deliver(change)


class MemoryStore:
    """One gateway's view of a :class:`MemoryServer`: a :class:`~services.apps.registry.store.SharedStore`."""

    def __init__(self, server: MemoryServer, gateway_id: str) -> None:
        self.server = server
        self._gateway_id = gateway_id
        self._listeners: list[StoreListener] = []
        self._reconnect_listeners: list[Callable[[], None]] = []
        self._read_only_listeners: list[Callable[[], None]] = []
        self.started = False
        #: The gateway died (:meth:`MemoryServer.kill`): nothing reaches it, nothing it writes lands.
        self.dead = False
        #: Writes made through this store (kind, name), in order: tests read what a gateway wrote.
        self.writes: list[tuple[str, Kind, str]] = []
        #: Calls of the bulk writes (what, kind, keys asked for), in order: one round trip each.
        self.bulk_calls: list[tuple[str, Kind, int]] = []
        #: The keys the watchers have been told of (as etcd's store keeps its mirror): a reconnection
        #: reports those gone meanwhile as deleted.
        self._known: set[tuple[Kind, str]] = set()

    # -- RegistryStore -------------------------------------------------------

    @property
    def shared(self) -> bool:
        return True

    @property
    def location(self) -> str:
        return "memory://test"

    @property
    def read_only(self) -> str:
        if self.dead:
            return "this gateway is dead"
        down = self.server.down
        return f"the memory store cannot be reached ({down})" if down else ""

    @property
    def gateway_id(self) -> str:
        return self._gateway_id

    @property
    def lease_expires(self) -> float:
        return 0.0  # the memory server's leases never lapse by time: only a kill ends one

    async def start(self) -> None:
        self.started = True
        self._known = set(self.server.keys)

    async def aclose(self) -> None:
        self.started = False
        self.server.end_lease(self._gateway_id)
        if self in self.server.stores:
            self.server.stores.remove(self)

    async def load(self) -> list[tuple[str, str, dict[str, str]]]:
        loaded = []
        for name, value in (await self.read(Kind.SERVICE)).items():
            record = json.loads(value)
            loaded.append((name, str(record["url"]), dict(record.get("options", {}))))
        return loaded

    async def save(self, name: str, url: str, options: dict[str, str]) -> None:
        await self.put(Kind.SERVICE, name, json.dumps({"url": url, "options": options}))

    async def drop(self, name: str) -> None:
        await self.delete(Kind.SERVICE, name)

    # -- SharedStore -----------------------------------------------------------

    def _reachable(self) -> None:
        if self.server.down or self.dead:
            raise Unavailable(f"the registry is read-only: {self.read_only}")

    async def read(self, kind: Kind) -> dict[str, str]:
        await asyncio.sleep(0)
        self._reachable()
        return self.server.folder(kind)

    async def put(self, kind: Kind, name: str, value: str, *, leased: bool = False) -> None:
        await asyncio.sleep(0)
        self._reachable()
        self.writes.append(("put", kind, name))
        self.server.write(kind, name, value, self._gateway_id if leased else None)

    async def create(self, kind: Kind, name: str, value: str, *, leased: bool = False) -> bool:
        await asyncio.sleep(0)
        self._reachable()
        if self.server.value(kind, name) is not None:
            return False
        self.writes.append(("create", kind, name))
        self.server.write(kind, name, value, self._gateway_id if leased else None)
        return True

    async def create_many(self, kind: Kind, values: Mapping[str, str], *, leased: bool = False) -> set[str]:
        await asyncio.sleep(0)
        self._reachable()
        self.bulk_calls.append(("create_many", kind, len(values)))
        created = set()
        for name, value in values.items():
            if self.server.value(kind, name) is None:
                self.writes.append(("create", kind, name))
                self.server.write(kind, name, value, self._gateway_id if leased else None)
                created.add(name)
        return created

    async def put_many(self, kind: Kind, values: Mapping[str, str], *, leased: bool = False) -> None:
        await asyncio.sleep(0)
        self._reachable()
        self.bulk_calls.append(("put_many", kind, len(values)))
        for name, value in values.items():
            self.writes.append(("put", kind, name))
            self.server.write(kind, name, value, self._gateway_id if leased else None)

    async def replace(
        self, kind: Kind, name: str, expected: str, value: str | None, *, leased: bool = False
    ) -> bool:
        await asyncio.sleep(0)
        self._reachable()
        held = self.server.keys.get((kind, name))
        if held is None or held[0] != expected:
            return False
        self.writes.append(("replace", kind, name))
        self.server.write(kind, name, value, self._gateway_id if leased else None)
        return True

    async def delete(self, kind: Kind, name: str) -> None:
        await asyncio.sleep(0)
        self._reachable()
        self.writes.append(("delete", kind, name))
        self.server.write(kind, name, None)

    def watch(self, listener: StoreListener) -> Callable[[], None]:
        return _listen(self._listeners, listener)

    def watch_read_only(self, listener: Callable[[], None]) -> Callable[[], None]:
        return _listen(self._read_only_listeners, listener)

    def read_only_changed(self) -> None:
        """The server stopped or started: tell who follows :attr:`read_only`."""
        for listener in list(self._read_only_listeners):
            listener()

    def on_reconnect(self, listener: Callable[[], None]) -> Callable[[], None]:
        return _listen(self._reconnect_listeners, listener)

    # -- what the server calls ---------------------------------------------------

    def deliver(self, change: Change) -> None:
        """Report ``change`` to the watchers a moment later, on the loop (as a watch stream does)."""
        if not self._listeners or self.dead or self.server.down:
            return
        where = (change.kind, change.name)
        if change.value is None:
            self._known.discard(where)
        else:
            self._known.add(where)
        loop = asyncio.get_running_loop()
        for listener in list(self._listeners):
            loop.call_soon(listener, change)

    def reconnected(self) -> None:
        """The server is back: every key is reported again (those gone as deleted, as etcd's store
        does), then the reconnect listeners write their leased keys again."""
        if self.dead:
            return
        for kind, name in sorted(self._known - set(self.server.keys), key=lambda key: (key[0].value, key[1])):
            self.deliver(Change(kind, name, None))
        for kind in Kind:
            for name, value in self.server.folder(kind).items():
                self.deliver(Change(kind, name, value))
        loop = asyncio.get_running_loop()
        for listener in list(self._reconnect_listeners):
            loop.call_soon(listener)


def _listen(listeners: list[T], listener: T) -> Callable[[], None]:
    """Add ``listener`` to ``listeners``; the function that takes it out again."""
    listeners.append(listener)

    def forget() -> None:
        if listener in listeners:
            listeners.remove(listener)

    return forget
