"""Where a device that dials in goes when its gateway is gone: the gateways it may dial, in turn.

A gateway of a cluster greets a device that dialled its line listener with one more field,
``alternates=HOST:PORT,HOST:PORT``: the line listeners of the other gateways of its cluster
(docs/line-protocol.md §5). Every gateway of the cluster serves every service, so a device whose
gateway died may register itself on any other. :class:`GatewayAddresses` keeps the list a device
dials in turn: the gateway it is connected to first, then the alternates it named, then the
address the device was started with.
"""

from __future__ import annotations

from collections.abc import Iterable

__all__ = ["ALTERNATES_FIELD", "MAX_ADDRESSES", "GatewayAddresses", "format_alternates", "parse_alternates"]

#: The greeting field that names the other gateways' line listeners.
ALTERNATES_FIELD = "alternates"
#: Addresses a device keeps: a cluster of more gateways than this names only this many.
MAX_ADDRESSES = 16

Address = tuple[str, int]


def format_alternates(addresses: Iterable[str]) -> str:
    """The field's value: ``HOST:PORT`` items joined by commas (no spaces: one word on the line)."""
    return ",".join(address for address in addresses if address and "," not in address)


def parse_alternates(text: str) -> list[Address]:
    """The (host, port) pairs a field names; items that are not ``HOST:PORT`` are skipped."""
    found: list[Address] = []
    for item in text.split(",")[:MAX_ADDRESSES]:
        host, sep, port = item.strip().rpartition(":")
        if sep and host and port.isdigit() and 0 < int(port) < 65536:
            found.append((host.strip("[]"), int(port)))
    return found


class GatewayAddresses:
    """The gateways a device dials, in turn (see the module docstring)."""

    def __init__(self, first: Address) -> None:
        self.given = first
        self.addresses: list[Address] = [first]
        self._next = 0
        # Dialled since the last pause, counted apart from the turn: a gateway that greets and then
        # refuses the name starts the turn again (connected), and must not start the count again.
        self._dialled = 0

    def take(self) -> tuple[Address, bool]:
        """The address to dial now, and True when it starts a new round (all were tried)."""
        if self._next >= len(self.addresses):
            self._next = 0
        new_round = self._next == 0
        address = self.addresses[self._next]
        self._next += 1
        self._dialled += 1
        return address, new_round

    def pause_due(self) -> bool:
        """Every address known was dialled since the last pause: wait before dialling again."""
        return self._dialled >= len(self.addresses)

    def rested(self) -> None:
        """The device paused, or its last connection lasted: the next round may dial at once."""
        self._dialled = 0

    def connected(self, address: Address, alternates: str) -> None:
        """Connected to ``address``, whose greeting named ``alternates``: the list from now on is that
        gateway, its alternates, then the address the device was given; the next to dial after it
        is the first alternate."""
        ordered = [address, *parse_alternates(alternates), self.given]
        unique = list(dict.fromkeys(ordered))[:MAX_ADDRESSES]
        self.addresses = unique
        self._next = 1 if len(unique) > 1 else 0
