"""What a front end hands the engine for a Get, Set or Describe, and what it gets back.

Plain slotted classes, built by each front from its own wire form (the gRPC front from the
contract's messages, the HTTP front from a URL and a JSON body) and read by the call layer
(:class:`gateway.engine.calls.Calls`), the guard and the licences; no protobuf message passes the door.

* A call names the **service** (its registry name) and the **path** inside it, the request
  **parameters** (name → text), and for a Set the **value**: text (``str``) or bytes. How long
  the engine may take is the time limit handed beside the call (the front knows the client's
  deadline).
* The **caller** is a :class:`~gateway.engine.rules.Subject` (:data:`ANONYMOUS` when nothing proved a
  name); each front identifies it its own way (a certificate, a token, a secret on a line).
* A failure is a :class:`~services.kernel.errors.PropertyError` carrying its
  :class:`~services.kernel.errors.Code`; each front turns it into its own status (a gRPC status, an
  HTTP status, an ``ERR`` line).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from gateway.engine.identity import ANONYMOUS
from gateway.engine.rules import Subject
from services.kernel.backend import NO_PARAMS
from services.kernel.errors import Code, PropertyError
from services.kernel.paths import is_pattern
from services.kernel.values import Value

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


class _Plain:
    """Equal by value, shown with its fields: what a dataclass would give, but with an ``__init__``
    written out, so that the default parameters may be the shared read-only ``NO_PARAMS``."""

    __slots__: tuple[str, ...] = ()

    def _fields(self) -> tuple[object, ...]:
        return tuple(getattr(self, name) for name in self.__slots__)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, _Plain) and type(other) is type(self) and self._fields() == other._fields()

    #: Unhashable, as a dataclass that is not frozen: its parameters are a mapping.
    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        shown = ", ".join(f"{name}={getattr(self, name)!r}" for name in self.__slots__)
        return f"{type(self).__name__}({shown})"


class PropertyRef(_Plain):
    """One more path a Get reads; an empty ``service`` is the Get's own."""

    __slots__ = ("parameters", "path", "service")

    def __init__(self, service: str, path: str, parameters: Mapping[str, str] = NO_PARAMS) -> None:
        self.service = service
        self.path = path
        self.parameters = parameters


class GetCall(_Plain):
    """A Get of ``path`` of ``service`` and of the ``more`` paths with it (all or nothing).

    A path with ``*`` segments makes the Get a snapshot (:func:`is_snapshot`).
    """

    __slots__ = ("more", "parameters", "path", "service")

    def __init__(
        self,
        service: str,
        path: str,
        parameters: Mapping[str, str] = NO_PARAMS,
        more: Sequence[PropertyRef] = (),
    ) -> None:
        self.service = service
        self.path = path
        self.parameters = parameters
        self.more = more


class SetCall(_Plain):
    """A Set of ``path`` of ``service`` to ``value`` (text, or bytes for a binary property)."""

    __slots__ = ("parameters", "path", "service", "value")

    def __init__(
        self, service: str, path: str, value: Value, parameters: Mapping[str, str] = NO_PARAMS
    ) -> None:
        self.service = service
        self.path = path
        self.value = value
        self.parameters = parameters


class DescribeCall(_Plain):
    """The whole model of ``service``."""

    __slots__ = ("service",)

    def __init__(self, service: str) -> None:
        self.service = service


class PropertyValue(_Plain):
    """One value a Get read, with the concrete path it was read at and its source time."""

    __slots__ = ("path", "service", "time_ns", "value")

    def __init__(self, service: str, path: str, value: Value, time_ns: int = 0) -> None:
        self.service = service
        self.path = path
        self.value = value
        #: When the value became true, in nanoseconds since the epoch (0: not known).
        self.time_ns = time_ns


class GetReply(_Plain):
    """What a Get read: the value of its path, and the values of its ``more`` paths in order.

    A snapshot (:func:`is_snapshot`) lists every match in ``more`` and leaves ``value`` empty.
    ``time_ns`` is the source time of ``value`` (:meth:`gateway.engine.calls.Calls.value_time`):
    when the gateway heard it change, or when the answer arrived for a value nobody follows.
    """

    __slots__ = ("more", "time_ns", "value")

    def __init__(self, value: Value = "", more: Sequence[PropertyValue] = (), time_ns: int = 0) -> None:
        self.value = value
        self.more = more
        self.time_ns = time_ns


def is_snapshot(call: GetCall) -> bool:
    """True when a path of the Get has a ``*`` segment: its answer lists every match in ``more``."""
    return is_pattern(call.path) or any(is_pattern(ref.path) for ref in call.more)
