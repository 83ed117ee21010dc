"""What the cluster's keys hold: the JSON of a registration and of a gateway, read and written.

Key layout (``PREFIX`` is ``[registry] store_prefix``)::

    PREFIX/services/NAME   {"url": URL, "options": {"type": ..., "features": ...}}
    PREFIX/owners/NAME     the owning gateway's id                                   (leased)
    PREFIX/states/NAME     up | down | connecting, as the owner sees it              (leased)
    PREFIX/gateways/ID     {"address": HOST:PORT, "http": ..., "line": ..., "owned": N,
                            "protocols": [1, 2], ...}                                 (leased)
    PREFIX/licences/NAME   [{"id": ..., "subtree": ..., "holder": ..., ...}, ...]   (see licences)
    PREFIX/drains/ID       {"by": ..., "at": unix seconds}: an admin drained gateway ID

A gateway's record carries, besides where it is reached, what the cluster view shows of it (its
version, load, lease expiry, read-only reason, whether it is draining) and its count of rebalance
requests: each field is written only when it is not its default, and a reader takes a missing
field for its default, so gateways that know fewer fields read the records of those that know more.

The cluster protocol versions a gateway speaks (:mod:`gateway.peer_protocol`) are in its
``gateways`` key; a key without them was written by a gateway of version 1. The other keys hold
what the versions those gateways share say they hold.

A value another program wrote badly is not trusted: :func:`read_registration` and
:func:`read_gateway` answer None for it, and the cluster logs and skips the key.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from gateway.peer_protocol import SPOKEN, read_protocols
from services.apps.registry import STATES
from services.apps.registry.store import decode_registration, encode_registration
from services.kernel.release import package_version

__all__ = [
    "DIAL_IN_PREFIX",
    "DrainOrder",
    "GatewayRecord",
    "Ownership",
    "Registration",
    "gateway_version",
    "read_drain",
    "read_gateway",
    "read_registration",
    "read_state",
]

#: A registration whose URL starts so is a device that dialled in to a gateway's line listener:
#: its key is bound to that gateway's lease, and nobody else can dial it (it dials again elsewhere).
DIAL_IN_PREFIX = "tcp-in://"


def gateway_version() -> str:
    """This gateway's release, as ``--version`` tells it (:func:`services.kernel.release.package_version`)."""
    return package_version()


@dataclass(frozen=True, slots=True)
class Registration:
    """One ``services/NAME`` key: where the service is, and what its registration declared."""

    url: str
    options: dict[str, str] = field(default_factory=dict)

    @property
    def dialled_in(self) -> bool:
        """A device that dialled in: it leaves with its gateway and is never taken over."""
        return self.url.startswith(DIAL_IN_PREFIX)

    @property
    def declared_type(self) -> str:
        """The type the registration declared; empty when none."""
        return self.options.get("type", "")

    def to_json(self) -> str:
        """The key's value (written as the registry's store writes it)."""
        return encode_registration(self.url, self.options)


def read_registration(text: str) -> Registration | None:
    """The registration a ``services/NAME`` value holds; None when it is not one."""
    try:
        url, options = decode_registration(text)
    except ValueError:
        return None
    return Registration(url, options) if url else None


#: Fields of a gateway's record beyond where it is reached: name → (type, default). A field at its
#: default is not written; one of another type is read as its default (a record is never refused for them).
_EXTRA_FIELDS: dict[str, tuple[type, object]] = {
    "tls": (bool, False),
    "via": (str, ""),
    "version": (str, ""),
    "draining": (bool, False),
    "read_only": (str, ""),
    "calls_per_s": (float, 0.0),
    "listens": (int, 0),
    "lease_expires": (float, 0.0),
    "rebalance": (int, 0),
}


@dataclass(frozen=True, slots=True)
class GatewayRecord:
    """One ``gateways/ID`` key: where a live gateway of the cluster is reached, and how it is doing."""

    #: host:port of its gRPC port, as the other gateways dial it (``[registry] advertise``).
    address: str
    #: host:port of its HTTP front end ("" when off).
    http: str = ""
    #: host:port of its line-protocol listener ("" when off): devices dial it.
    line: str = ""
    #: Services it owns (``owners`` keys naming it), as it last counted them.
    owned: int = 0
    #: Whether its gRPC port serves TLS (the others forward to it over ``grpcs://``).
    tls: bool = False
    #: Its id in the ``ps-via`` chain of the calls it forwards (gateway.federation): the owner
    #: knows a call another gateway of the cluster forwarded by it.
    via: str = ""
    #: The cluster protocol versions it speaks (gateway.peer_protocol); a key without them: {1}.
    protocols: frozenset[int] = SPOKEN
    #: The gateway's release (the package version).
    version: str = ""
    #: It hands what it owns over to the others and takes nothing new (an admin drained it).
    draining: bool = False
    #: Why its registry was read-only when it last wrote this record ("" when it was not).
    read_only: str = ""
    #: Calls (Get, Set, Describe; gRPC and HTTP) a second it answered lately.
    calls_per_s: float = 0.0
    #: Listen streams open on it.
    listens: int = 0
    #: Wall-clock time its lease lapses unless renewed, as of its last renewal.
    lease_expires: float = 0.0
    #: How many rebalances an admin asked for through it: every gateway runs one when it grows.
    rebalance: int = 0

    def to_json(self) -> str:
        """The key's value."""
        fields: dict[str, object] = {
            "address": self.address,
            "http": self.http,
            "line": self.line,
            "owned": self.owned,
            "protocols": sorted(self.protocols),
        }
        for name, (_, default) in _EXTRA_FIELDS.items():
            value = getattr(self, name)
            if value != default:
                fields[name] = value
        return json.dumps(fields, sort_keys=True)


def read_gateway(text: str) -> GatewayRecord | None:
    """The gateway a ``gateways/ID`` value holds; None when it is not one."""
    try:
        data = json.loads(text)
        address = data["address"]
        http = data.get("http", "")
        line = data.get("line", "")
        owned = data.get("owned", 0)
        tls = data.get("tls", False)
        protocols = read_protocols(data.get("protocols"))
    except (ValueError, KeyError, TypeError, AttributeError):
        return None
    if (
        not isinstance(address, str)
        or not address
        or not isinstance(owned, int)
        or not isinstance(tls, bool)
        or protocols is None
    ):
        return None
    extra: dict[str, Any] = {}
    for name, (kind, default) in _EXTRA_FIELDS.items():
        value = data.get(name, default)
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        finite = not isinstance(value, float) or math.isfinite(value)
        extra[name] = value if type(value) is kind and finite else default
    extra["via"] = str(data.get("via", "") or "")
    return GatewayRecord(address, str(http or ""), str(line or ""), owned, protocols=protocols, **extra)


@dataclass(frozen=True, slots=True)
class DrainOrder:
    """One ``drains/ID`` key: an admin drained gateway ID (it stays drained until undrained)."""

    #: Who asked (the caller's identity, as the rules know it).
    by: str = ""
    #: When, unix seconds.
    at: float = 0.0

    def to_json(self) -> str:
        """The key's value."""
        return json.dumps({"by": self.by, "at": self.at}, sort_keys=True)


def read_drain(text: str) -> DrainOrder:
    """The order a ``drains/ID`` value holds; any value drains (a bad one is read as an order by nobody)."""
    try:
        data = json.loads(text)
        return DrainOrder(str(data.get("by", "")), float(data.get("at", 0.0)))
    except (ValueError, TypeError, AttributeError):
        return DrainOrder()


def read_state(text: str) -> str | None:
    """A ``states/NAME`` value when it is a state the registry knows; None otherwise."""
    return text if text in STATES else None


@dataclass(frozen=True, slots=True)
class Ownership:
    """Who owns what in a cluster at one moment, for people (the cluster command's table, its picture)."""

    #: The shared store's URL.
    store: str
    gateways: Mapping[str, GatewayRecord]
    #: Service name → the id of the gateway that owns it.
    owners: Mapping[str, str]
    registrations: Mapping[str, Registration]

    def owned_by(self, gateway: str) -> list[str]:
        """The services ``gateway`` owns, sorted."""
        return sorted(name for name, owner in self.owners.items() if owner == gateway)

    def orphans(self) -> list[str]:
        """The registrations no live gateway owns, sorted."""
        return sorted(name for name in self.registrations if self.owners.get(name) not in self.gateways)
