"""Where the registry keeps what must outlive one gateway: the store interface.

Two kinds of store sit behind one interface:

* **embedded** (the default): the registrations made by Set, kept in this gateway's memory and,
  with ``[registry] persist``, in a JSON file (:mod:`services.apps.registry.persistence`). One gateway,
  no server to run.
* **shared** (``[registry] store = "etcd://…"``): many gateways share one view. Every key is
  written under a prefix, in one of the :class:`Kind` folders; a key written ``leased`` is bound to
  the writing gateway's lease, which it keeps alive while it runs, so a gateway that dies takes its
  leased keys (its ownership of devices, the states it reported) with it within the lease time.
  A watch tells every gateway of every change.

The registry and the gateway's cluster code speak only to these protocols; the etcd adapter lives in
the gateway (``gateway.stores``), so that ``services`` needs no etcd client.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from typing import Protocol, runtime_checkable

__all__ = [
    "EMBEDDED",
    "Change",
    "Kind",
    "RegistryStore",
    "SharedStore",
    "StoreListener",
    "decode_registration",
    "encode_registration",
]

#: The ``location`` of the embedded store.
EMBEDDED = "embedded"


class Kind(StrEnum):
    """The folders of a shared store (each key is ``PREFIX/KIND/NAME``)."""

    #: A registration: JSON ``{"url": ..., "options": {...}}``; not leased when made by Set (it
    #: outlives the gateway that took it), leased when a device dialled in (it leaves with it).
    SERVICE = "services"
    #: Which gateway owns a service's connection: the owner's gateway id, leased.
    OWNER = "owners"
    #: A service's state as its owner sees it (``up``, ``down``, ``connecting``), leased.
    STATE = "states"
    #: A gateway of the cluster: JSON ``{"address": host:port of its gRPC port, ...}``, leased.
    GATEWAY = "gateways"
    #: A licence granted on a service: JSON of the licence, created only when absent.
    LICENCE = "licences"
    #: A gateway an admin drained (named by its id): JSON ``{"by": ..., "at": ...}``, not leased (a
    #: drained gateway that restarts stays drained until an admin undrains it).
    DRAIN = "drains"


@dataclass(frozen=True, slots=True)
class Change:
    """One key of a shared store changed: ``value`` is its new value, None when it was deleted
    (or its lease expired)."""

    kind: Kind
    name: str
    value: str | None


#: Called for every change a shared store's watch reports, on the event loop.
StoreListener = Callable[[Change], None]


@runtime_checkable
class RegistryStore(Protocol):
    """Where the registrations made by Set are kept (name → url and options)."""

    @property
    def shared(self) -> bool:
        """True when other gateways see what this store holds (a :class:`SharedStore`)."""
        ...

    @property
    def location(self) -> str:
        """Where the registrations are kept, for people: ``embedded``, or the shared store's URL
        (``etcd://127.0.0.1:2379``)."""
        ...

    @property
    def read_only(self) -> str:
        """Why registrations cannot be changed now (the store's server is unreachable); empty
        when they can. A registry whose store is read-only refuses registrations with UNAVAILABLE
        and this reason, and keeps serving what it has."""
        ...

    def watch_read_only(self, listener: Callable[[], None]) -> Callable[[], None]:
        """Call ``listener`` each time :attr:`read_only` changes; returns the unwatch."""
        ...

    async def start(self) -> None:
        """Connect (a shared store) or nothing (the embedded one)."""
        ...

    async def aclose(self) -> None:
        """Write what is waiting and let go of every connection."""
        ...

    async def load(self) -> list[tuple[str, str, dict[str, str]]]:
        """(name, url, options) of every registration kept."""
        ...

    async def save(self, name: str, url: str, options: dict[str, str]) -> None:
        """Keep the registration of ``name``; raises Unavailable when read-only."""
        ...

    async def drop(self, name: str) -> None:
        """Forget the registration of ``name`` (no error when it was not kept)."""
        ...


@runtime_checkable
class SharedStore(RegistryStore, Protocol):
    """A store many gateways share: keys in :class:`Kind` folders, leases, compare-and-set, a watch."""

    @property
    def gateway_id(self) -> str:
        """This gateway's id in the cluster (the value of the ``owners`` keys it writes)."""
        ...

    @property
    def lease_expires(self) -> float:
        """Wall-clock time (``time.time()``) at which this gateway's lease lapses unless renewed, as
        of its last renewal; 0 while it holds none."""
        ...

    async def read(self, kind: Kind) -> dict[str, str]:
        """Every key of one folder right now: name → value."""
        ...

    async def put(self, kind: Kind, name: str, value: str, *, leased: bool = False) -> None:
        """Write a key; ``leased`` binds it to this gateway's lease. Raises Unavailable when the
        store cannot be reached."""
        ...

    async def create(self, kind: Kind, name: str, value: str, *, leased: bool = False) -> bool:
        """Write a key only when it is absent (one transaction); False when it exists."""
        ...

    async def create_many(self, kind: Kind, values: Mapping[str, str], *, leased: bool = False) -> set[str]:
        """Write each key of ``values`` (name → value) that is absent, many in one transaction; the
        names written. A key that exists (another gateway wrote it first) is left as it is and does
        not keep the others from being written. Raises Unavailable when the store cannot be reached
        (the keys written by then stay written: the watch reports them)."""
        ...

    async def put_many(self, kind: Kind, values: Mapping[str, str], *, leased: bool = False) -> None:
        """Write every key of ``values`` (name → value), many in one transaction; ``leased`` as for
        :meth:`put`. Raises Unavailable when the store cannot be reached."""
        ...

    async def replace(
        self, kind: Kind, name: str, expected: str, value: str | None, *, leased: bool = False
    ) -> bool:
        """Compare-and-set: write ``value`` (delete when None) only when the key holds ``expected``;
        ``leased`` binds the new value to this gateway's lease (as for :meth:`put`)."""
        ...

    async def delete(self, kind: Kind, name: str) -> None:
        """Remove a key (no error when absent)."""
        ...

    def watch(self, listener: StoreListener) -> Callable[[], None]:
        """Call ``listener`` for every change of every folder from now on; returns the unwatch.
        After the store reconnected (its server restarted), every key is reported again."""
        ...

    def on_reconnect(self, listener: Callable[[], None]) -> Callable[[], None]:
        """Call ``listener`` after the store reconnected, so that the gateway writes again what it
        lost. Before the listener is called, the watch has reported every key as the store holds
        it now. The store keeps its lease when it can, and with it every key bound to it; it takes a
        new lease only once the old one is gone, and every key bound to the old one with it."""
        ...


def encode_registration(url: str, options: dict[str, str]) -> str:
    """The value of a ``services`` key: JSON ``{"url": ..., "options": {...}}``."""
    return json.dumps({"url": url, "options": options}, sort_keys=True, separators=(",", ":"))


def decode_registration(value: str) -> tuple[str, dict[str, str]]:
    """(url, options) of a ``services`` key's value; raises ValueError when it is not one."""
    try:
        data = json.loads(value)
        url = data["url"]
        options = data.get("options", {})
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise ValueError(f"not a registration: {value[:80]!r} ({e})") from None
    if not isinstance(url, str) or not isinstance(options, dict):
        raise ValueError(f"not a registration: {value[:80]!r}")
    return url, {str(k): str(v) for k, v in options.items()}
