"""The typed model of a service: every property with its type, access, unit, range and docs.

One call returns the whole model of a service (``Backend.describe``, the
``Describe`` RPC), so that a user interface or a code generator never walks
the service property by property (OPC UA's browse with attributes, KUKSA's
``ListMetadata``, gNMI ``Capabilities``).

Access says what a client may do, and that reads never act:

* ``read`` — Get and Listen; a Set is FAILED_PRECONDITION.
* ``write`` — Set only (rare: a value that cannot be read back).
* ``read-write`` — Get, Listen and Set.
* ``action`` — Set only, and a Set *does* something (``behaviors.moveto``);
  a Get is FAILED_PRECONDITION naming how to invoke it, and a Listen
  selector with ``*`` skips it.
* ``query`` — Get only (with parameters), declared by its author as never
  changing state (``registry/find``).
* ``unknown`` — a device that does not describe itself.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass


class Access(enum.StrEnum):
    """What a client may do with a property; see the module docstring."""

    READ = "read"
    WRITE = "write"
    READ_WRITE = "read-write"
    ACTION = "action"
    QUERY = "query"
    UNKNOWN = "unknown"

    @property
    def readable(self) -> bool:
        """Get (and, but for a query, Listen) are allowed."""
        return self in (Access.READ, Access.READ_WRITE, Access.QUERY, Access.UNKNOWN)

    @property
    def listenable(self) -> bool:
        """A Listen may follow it: a readable value, not a query (which needs its parameters)."""
        return self in (Access.READ, Access.READ_WRITE, Access.UNKNOWN)

    @property
    def writable(self) -> bool:
        """A Set is allowed."""
        return self in (Access.WRITE, Access.READ_WRITE, Access.ACTION, Access.UNKNOWN)


#: Data type words, as ``NAME.parameters`` and the Describe RPC spell them. A ``bytes`` value is
#: binary: it travels as raw bytes (the contract's ``data`` field), never as text.
DATA_TYPES = frozenset(
    {"number", "integer", "boolean", "text", "vector", "list", "names", "vectors", "marker", "bytes", "none"}
    | {"namespace", "unknown"}
)


@dataclass(frozen=True, slots=True)
class ParameterModel:
    """One parameter of a functional property (or its value)."""

    name: str
    #: A word of :data:`DATA_TYPES`.
    type: str
    required: bool = True
    #: The default as value text; "" when there is none.
    default: str = ""
    doc: str = ""


@dataclass(frozen=True, slots=True)
class PropertyModel:
    """One property of a service, as a client sees it."""

    #: Dotted path (``location``, ``behaviors.moveto``, ``robots.scout1.location``).
    name: str
    #: A word of :data:`DATA_TYPES`; for an action or query, the type of its answer.
    type: str
    access: Access
    #: Elements of a vector when fixed (6 for a pose), else None.
    length: int | None = None
    #: Unit of the value (``m``, ``m/s``, ``degC``); "" when it has none or none is known.
    unit: str = ""
    #: Bounds a Set from outside must respect (numbers; for vectors each element).
    minimum: float | None = None
    maximum: float | None = None
    #: The values allowed, when they are a closed set (as value text).
    choices: tuple[str, ...] = ()
    doc: str = ""
    #: Preferred widget (``NAME.gui``).
    gui: str = ""
    #: Actions and queries: the value a Set (or a query's Get) takes; None when it takes none.
    value: ParameterModel | None = None
    #: Actions and queries (and a property read with a parameter, a storage service's
    #: ``file``): the request parameters they accept.
    parameters: tuple[ParameterModel, ...] = ()
    #: Type ``bytes``: what the bytes are (``image/jpeg``, ``application/x-npy``); "" when unknown.
    media_type: str = ""
    #: Type ``bytes``: the most bytes a Set may carry (0: the gateway's default, one message).
    max_size: int = 0
    #: Numbers and vectors: the smallest step the value is known to (0.01: to the hundredth), so a
    #: client shows as many decimals as that; None when the service gives none.
    resolution: float | None = None

    @property
    def needs_parameters(self) -> bool:
        """It takes a required parameter: a Get or Listen without one fails, so wildcards skip it."""
        return any(p.required for p in self.parameters)


@dataclass(frozen=True, slots=True)
class ServiceModel:
    """The whole model of one service."""

    #: Resource type (``mobile_robot``, ``sensor``, ...), as in ``BackendInfo.type``.
    type: str
    properties: tuple[PropertyModel, ...]
    doc: str = ""
