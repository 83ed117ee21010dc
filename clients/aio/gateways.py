"""The gateways a client may use: several addresses, the one in use now, and when to move on.

A client given several addresses (gateways of one cluster, or gateways that reach the same
devices) uses one at a time. It moves to the next when the one in use stops answering: a call
that could not connect, a stream the gateway's connection dropped (UNAVAILABLE), or a keep-alive
ping left unanswered (a frozen gateway holds its connections open but answers nothing, so only
the ping finds it). An UNAVAILABLE the gateway itself answered (its device is away, say) is the
answer, not a reason to move.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import grpc

from clients.errors import GatewayUnreachable, tls_hint

__all__ = [
    "DEFAULT_FAILOVER_LIMIT",
    "DEFAULT_KEEPALIVE",
    "GatewayList",
    "answered_by_gateway",
    "channel_options",
    "no_gateway_answered",
    "parse_targets",
]

#: Seconds between keep-alive pings on a connection with calls open, and the time a ping may go
#: unanswered before the connection counts as dead: a SIGSTOPped gateway is found within twice this.
DEFAULT_KEEPALIVE = 1.0
#: Seconds a resumed Listen may go without reaching any gateway before it raises, naming each
#: address it tried. A gateway restart (seconds) and a cluster failover (the lease) fit well inside.
DEFAULT_FAILOVER_LIMIT = 30.0
#: The header a gateway gives every call it answered (see docs/logging.md): an error that carries
#: it came from the gateway, not from a connection that failed on the way.
_REQUEST_ID_HEADER = "x-request-id"
#: gRPC target schemes whose one name may stand for several addresses (``dns:///``,
#: ``ipv4:A,B``): such a string is one target, never split at its commas.
_SCHEMES = ("dns:", "ipv4:", "ipv6:", "unix:", "unix-abstract:", "vsock:", "xds:")


def parse_targets(targets: str | Sequence[str]) -> tuple[str, ...]:
    """The gateway addresses of ``targets``: a sequence, or one string of comma-separated
    ``HOST:PORT`` (a string with a gRPC scheme, ``dns:///name:port`` or ``ipv4:a:1,b:2``, is one
    target whose addresses gRPC resolves and tries itself)."""
    if isinstance(targets, str):
        text = targets.strip()
        parts = [text] if text.lower().startswith(_SCHEMES) else text.split(",")
    else:
        parts = list(targets)
    addresses = tuple(part.strip() for part in parts if part.strip())
    if not addresses:
        raise ValueError(f"no gateway address in {targets!r}")
    for address in addresses:
        if not isinstance(address, str) or any(c.isspace() for c in address):
            raise ValueError(f"not a gateway address: {address!r}")
    return addresses


def channel_options(keepalive: float | None) -> list[tuple[str, Any]]:
    """gRPC channel options that let a client see a dead or frozen gateway within about
    ``2 * keepalive`` seconds (None: grpc's own defaults, which wait minutes)."""
    if keepalive is None:
        return []
    ms = max(1, round(keepalive * 1000))
    return [
        # Pings only while calls are open: an idle channel costs the gateway nothing.
        ("grpc.keepalive_time_ms", ms),
        ("grpc.keepalive_timeout_ms", ms),
        ("grpc.http2.ping_timeout_ms", ms),
        # grpc stops pinging after two pings in which the client sent nothing: a Listen sends
        # nothing after its request, so without this a frozen gateway would go unnoticed.
        ("grpc.http2.max_pings_without_data", 0),
        # Also the connect timeout: a frozen gateway's kernel accepts the TCP connection but the
        # HTTP/2 handshake never completes; grpc's default would wait 20 s.
        ("grpc.min_reconnect_backoff_ms", 2 * ms),
        ("grpc.initial_reconnect_backoff_ms", min(ms, 1000)),
        ("grpc.max_reconnect_backoff_ms", 2 * ms),
    ]


def answered_by_gateway(err: grpc.RpcError) -> bool:
    """True when ``err`` is the gateway's own answer (it carries the gateway's request id), not
    a connection that failed."""
    trailing = getattr(err, "trailing_metadata", None)
    try:
        metadata = trailing() if callable(trailing) else None
    except Exception:  # an error built without a call behind it
        return False
    return any(key == _REQUEST_ID_HEADER for key, _ in metadata or ())


def no_gateway_answered(
    tried: dict[str, str], within: float | None, service: str = "", prop: str = ""
) -> GatewayUnreachable:
    """The error for a call or stream that reached no gateway: every address tried, with why."""
    how = f" within {within:g} s" if within is not None else ""
    reasons = "; ".join(f"{address}: {why}" for address, why in tried.items())
    error = GatewayUnreachable(None, f"no gateway answered{how} (tried {reasons})", service, prop)
    error.tried = tuple(tried)
    error.hint = next(filter(None, (tls_hint(why) for why in tried.values())), "")
    return error


class GatewayList:
    """The addresses a client may use, in order, and the one it uses now.

    :meth:`move_on` goes to the next address after the one in use failed; a failure reported
    late, by a call that began on an address already left, moves nothing (several streams that
    break together move the client once).
    """

    def __init__(self, targets: str | Sequence[str]) -> None:
        self.addresses = parse_targets(targets)
        self._index = 0

    @property
    def current(self) -> str:
        """The address in use."""
        return self.addresses[self._index]

    def __len__(self) -> int:
        return len(self.addresses)

    def move_on(self, failed: str) -> bool:
        """Use the address after ``failed`` when ``failed`` is the one in use; True when it moved."""
        if failed != self.current or len(self.addresses) == 1:
            return False
        self._index = (self._index + 1) % len(self.addresses)
        return True
