"""The asyncio client: :class:`AsyncClient` and its multiplexed :class:`Session`.

Unary calls (Get, Set) go over ``grpc.aio``; a :class:`Session` multiplexes many
calls over the bidirectional ``Session`` RPC, which is the fast path for programs
making many small calls. A client's listens share one Session of the client
(``separate_listens=True``: a server-streamed Listen call each).

* :mod:`~clients.aio.client`: :class:`AsyncClient`
* :mod:`~clients.aio.session`: :class:`Session`
* :mod:`~clients.aio.gateways`: several gateway addresses, and when to move to the next
* :mod:`~clients.aio.listen`: the one ``listen`` method of clients and sessions
* :mod:`~clients.aio.listen_buffer`: the conflating buffer of a session listen
* :mod:`~clients.aio.events`: :class:`Event`, :class:`Mark`
* :mod:`~clients.aio.requests`: calls to protobuf requests, :data:`Selector`
"""

from clients.aio.client import DEFAULT_MAX_IN_FLIGHT, DEFAULT_TARGET, DEFAULT_TIMEOUT, AsyncClient
from clients.aio.events import HEARTBEAT, SYNC, Event, History, Mark, Reading
from clients.aio.gateways import DEFAULT_FAILOVER_LIMIT, DEFAULT_KEEPALIVE
from clients.aio.listen import ListenCalls
from clients.aio.requests import ListenOptions, Selector, TimeArg
from clients.aio.session import DEFAULT_SESSION_QUEUE, MAX_SESSION_BATCH, Session

__all__ = [
    "DEFAULT_FAILOVER_LIMIT",
    "DEFAULT_KEEPALIVE",
    "DEFAULT_MAX_IN_FLIGHT",
    "DEFAULT_SESSION_QUEUE",
    "DEFAULT_TARGET",
    "DEFAULT_TIMEOUT",
    "HEARTBEAT",
    "MAX_SESSION_BATCH",
    "SYNC",
    "AsyncClient",
    "Event",
    "History",
    "ListenCalls",
    "ListenOptions",
    "Mark",
    "Reading",
    "Selector",
    "Session",
    "TimeArg",
]
