"""What one gateway knows of the cluster: every registration, owner, state and gateway, kept from the store.

:class:`ClusterView` is plain data: the shared store's watch (or a full read) is applied to it
change by change, and it answers which names a change concerns, so that the gateway looks again
at those services only. It never touches the network.
"""

from __future__ import annotations

import logging
from collections import Counter
from typing import TypeVar

from gateway.cluster.records import (
    DrainOrder,
    GatewayRecord,
    Registration,
    read_drain,
    read_gateway,
    read_registration,
    read_state,
)
from services.apps.registry.store import Change, Kind

__all__ = ["ClusterView"]

log = logging.getLogger(__name__)

V = TypeVar("V")


class ClusterView:
    """The registrations, owners, states and live gateways of the cluster, as last heard."""

    def __init__(self) -> None:
        self.registrations: dict[str, Registration] = {}
        #: Service name → the id of the gateway that owns it.
        self.owners: dict[str, str] = {}
        #: Service name → its state as its owner reported it.
        self.states: dict[str, str] = {}
        #: Gateway id → where it is reached.
        self.gateways: dict[str, GatewayRecord] = {}
        #: Gateway id → the admin's order that drained it (it may not be live now).
        self.drains: dict[str, DrainOrder] = {}

    def apply(self, change: Change) -> list[str]:
        """Take one change of the store; the service names whose serving it may change."""
        kind, name, value = change.kind, change.name, change.value
        if kind is Kind.SERVICE:
            registration = read_registration(value) if value is not None else None
            if value is not None and registration is None:
                log.warning("cluster: ignoring services/%s: not a registration: %.200r", name, value)
            return self._put(self.registrations, name, registration)
        if kind is Kind.OWNER:
            return self._put(self.owners, name, value or None)
        if kind is Kind.STATE:
            state = read_state(value) if value is not None else None
            return self._put(self.states, name, state)
        if kind is Kind.GATEWAY:
            record = read_gateway(value) if value is not None else None
            if value is not None and record is None:
                log.warning("cluster: ignoring gateways/%s: not a gateway: %.200r", name, value)
            old = self.gateways.get(name)
            if record is None:
                self.gateways.pop(name, None)
            else:
                self.gateways[name] = record
            if old is not None and record is not None and old.address == record.address:
                return []  # only its count of owned services changed
            return self.owned_by(name)
        if kind is Kind.DRAIN:
            if value is None:
                self.drains.pop(name, None)
            else:
                self.drains[name] = read_drain(value)
        return []

    @staticmethod
    def _put(table: dict[str, V], name: str, value: V | None) -> list[str]:
        if value is None:
            if table.pop(name, None) is None:
                return []
        elif table.get(name) == value:
            return []
        else:
            table[name] = value
        return [name]

    def replace(self, folders: dict[Kind, dict[str, str]]) -> list[str]:
        """Take a full read of the given folders (after a start or a reconnect); the names it concerns."""
        names: set[str] = set()
        for kind, keys in folders.items():
            held = self._names_in(kind)
            for name in held - keys.keys():
                names.update(self.apply(Change(kind, name, None)))
            for name, value in keys.items():
                names.update(self.apply(Change(kind, name, value)))
        return sorted(names)

    def _names_in(self, kind: Kind) -> set[str]:
        if kind is Kind.SERVICE:
            return set(self.registrations)
        if kind is Kind.OWNER:
            return set(self.owners)
        if kind is Kind.STATE:
            return set(self.states)
        if kind is Kind.GATEWAY:
            return set(self.gateways)
        if kind is Kind.DRAIN:
            return set(self.drains)
        return set()

    def owned_by(self, gateway_id: str) -> list[str]:
        """The services ``gateway_id`` owns, sorted."""
        return sorted(name for name, owner in self.owners.items() if owner == gateway_id)

    def loads(self) -> dict[str, int]:
        """Every live gateway's count of owned services (0 for one that owns none)."""
        counts = Counter(self.owners.values())
        return {gateway: counts.get(gateway, 0) for gateway in self.gateways}

    def orphans(self) -> list[str]:
        """Registrations nobody owns that a gateway may take over (not devices that dialled in), sorted."""
        return sorted(
            name for name, reg in self.registrations.items() if name not in self.owners and not reg.dialled_in
        )
