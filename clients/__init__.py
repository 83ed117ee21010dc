"""Python client SDK (sync and asyncio) and the ``psctl`` command line.

``AsyncClient`` and ``Client`` call a Property Service gateway; ``Session``
multiplexes many calls over one stream; ``clients.values`` decodes value
texts; every failure is a ``PropertyServiceError`` subclass.
"""

from clients.aio import (
    DEFAULT_TARGET,
    DEFAULT_TIMEOUT,
    HEARTBEAT,
    SYNC,
    AsyncClient,
    Event,
    Mark,
    Selector,
    Session,
)
from clients.errors import (
    Aborted,
    AlreadyExists,
    Cancelled,
    DeadlineExceeded,
    FailedPrecondition,
    GatewayUnreachable,
    Internal,
    InvalidArgument,
    NotFound,
    PermissionDenied,
    PropertyServiceError,
    ResourceExhausted,
    Unauthenticated,
    Unavailable,
    Unimplemented,
    Unknown,
)
from clients.sync import Client, ListenIterator, SyncSession
from clients.values import (
    Marker,
    ValueFormatError,
    Vector,
    format_value,
    parse_marker,
    parse_names,
    parse_number,
    parse_vector,
    parse_vectors,
)

__all__ = [
    "DEFAULT_TARGET",
    "DEFAULT_TIMEOUT",
    "HEARTBEAT",
    "SYNC",
    "Aborted",
    "AlreadyExists",
    "AsyncClient",
    "Cancelled",
    "Client",
    "DeadlineExceeded",
    "Event",
    "FailedPrecondition",
    "GatewayUnreachable",
    "Internal",
    "InvalidArgument",
    "ListenIterator",
    "Mark",
    "Marker",
    "NotFound",
    "PermissionDenied",
    "PropertyServiceError",
    "ResourceExhausted",
    "Selector",
    "Session",
    "SyncSession",
    "Unauthenticated",
    "Unavailable",
    "Unimplemented",
    "Unknown",
    "ValueFormatError",
    "Vector",
    "format_value",
    "parse_marker",
    "parse_names",
    "parse_number",
    "parse_vector",
    "parse_vectors",
]
