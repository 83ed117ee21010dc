"""What a front end hands the engine for a Get, Set or Describe, and what it gets back.

Plain named tuples (immutable values), built by each front from its own wire form (the gRPC front from the
contract's messages, the HTTP front from a URL and a JSON body) and read by the call layer
(:class:`gateway.calls.Calls`), the guard and the licences; no protobuf message passes the door.

* A call names the **service** (its registry name) and the **path** inside it, the request
  **parameters** (name → text), and for a Set the **value**: text (``str``) or bytes. How long
  the engine may take is the time limit handed beside the call (the front knows the client's
  deadline).
* The **caller** is a :class:`~gateway.rules.Subject` (:data:`ANONYMOUS` when nothing proved a
  name); each front identifies it its own way (a certificate, a token, a secret on a line).
* A failure is a :class:`~services.errors.PropertyError` carrying its
  :class:`~services.errors.Code`; each front turns it into its own status (a gRPC status, an
  HTTP status, an ``ERR`` line).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import NamedTuple

from gateway.identity import ANONYMOUS
from gateway.rules import Subject
from services.backend import NO_PARAMS
from services.errors import Code, PropertyError
from services.paths import is_pattern
from services.values import Value

__all__ = [
    "ANONYMOUS",
    "Code",
    "DescribeCall",
    "GetCall",
    "GetReply",
    "PropertyError",
    "PropertyRef",
    "PropertyValue",
    "SetCall",
    "Subject",
    "is_snapshot",
]


class PropertyRef(NamedTuple):
    """One more path a Get reads; an empty ``service`` is the Get's own."""

    service: str
    path: str
    parameters: Mapping[str, str] = NO_PARAMS


class GetCall(NamedTuple):
    """A Get of ``path`` of ``service`` and of the ``more`` paths with it (all or nothing).

    A path with ``*`` segments makes the Get a snapshot (:func:`is_snapshot`).
    """

    service: str
    path: str
    parameters: Mapping[str, str] = NO_PARAMS
    more: Sequence[PropertyRef] = ()


class SetCall(NamedTuple):
    """A Set of ``path`` of ``service`` to ``value`` (text, or bytes for a binary property)."""

    service: str
    path: str
    value: Value
    parameters: Mapping[str, str] = NO_PARAMS


class DescribeCall(NamedTuple):
    """The whole model of ``service``."""

    service: str


class PropertyValue(NamedTuple):
    """One value a Get read, with the concrete path it was read at."""

    service: str
    path: str
    value: Value


class GetReply(NamedTuple):
    """What a Get read: the value of its path, and the values of its ``more`` paths in order.

    A snapshot (:func:`is_snapshot`) lists every match in ``more`` and leaves ``value`` empty.
    """

    value: Value = ""
    more: Sequence[PropertyValue] = ()


def is_snapshot(call: GetCall) -> bool:
    """True when a path of the Get has a ``*`` segment: its answer lists every match in ``more``."""
    return is_pattern(call.path) or any(is_pattern(ref.path) for ref in call.more)
