"""``/metrics``: the Prometheus text exposition, on the HTTP front end and on a port of its own.

:class:`MetricsEndpoint` holds a registry of its own (never prometheus_client's
global one, so several gateways in one process each report their own) with the
gateway's collector. On the HTTP front end ``GET /metrics`` passes the front
end's checks (Host header, and with ``[[rules]]`` or tokens: a caller that may
read ``registry``/``services``); the listener of ``[metrics] listen`` serves
only ``/metrics``, in plaintext, for a scraper beside the gateway. It checks
the Host and Origin headers as the HTTP front end does (on loopback, a page of
another site pointed at it by DNS rebinding is refused), and holds at most
:data:`~gateway.config.METRICS_MAX_CONNECTIONS` connections.
"""

from __future__ import annotations

import logging

from aiohttp import web
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest

from gateway.config import (
    METRICS_MAX_CONNECTIONS,
    METRICS_MAX_CONNECTIONS_PER_ADDRESS,
    REGISTRY_NAME,
    is_loopback,
)
from gateway.connections import BoundedListener, ConnectionCaps
from gateway.engine.rules import Operation
from gateway.fronts.http.errors import connection_refusal, error_response
from gateway.fronts.http.safety import check_request, identify
from gateway.metrics.collector import GatewayCollector, Measured
from gateway.ports import start_bounded
from services.kernel.errors import PropertyError

log = logging.getLogger(__name__)

#: The property a caller must be allowed to read to scrape the HTTP front end's ``/metrics`` when
#: rules apply: the registry's listing, which tells as much about what the gateway serves.
GUARDED_BY = (REGISTRY_NAME, "services")
#: Seconds a connection to the port of its own may stay open with no request running (a
#: scraper asks every 15 to 60 s, and opens a new connection when this one is gone).
_IDLE_TIMEOUT = 120.0


class MetricsEndpoint:
    """The exposition of one gateway's metrics; see the module docstring."""

    def __init__(self, gateway: Measured) -> None:
        self.gateway = gateway
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(GatewayCollector(gateway))
        self._runner: web.AppRunner | None = None
        self._listener: BoundedListener | None = None
        #: Whether Host headers must be loopback names on the port of its own (it listens on loopback).
        self._loopback_only = True
        #: "host:port" of the listener of its own (the real port when 0 was asked); "" when none.
        self.address = ""

    def render(self) -> bytes:
        """Every metric now, in the text exposition format."""
        return generate_latest(self.registry)

    def _response(self) -> web.Response:
        response = web.Response(body=self.render())
        response.headers["Content-Type"] = CONTENT_TYPE_LATEST
        return response

    async def guarded(self, request: web.Request) -> web.Response:
        """``GET /metrics`` on the HTTP front end: with rules, only for who may read the registry's list."""
        guard = self.gateway.guard
        if guard.checks:
            guard.require(identify(request, guard), *GUARDED_BY, Operation.READ)
        return self._response()

    async def _plain(self, request: web.Request) -> web.Response:
        try:
            check_request(request, self._loopback_only)
        except PropertyError as exc:
            return error_response(exc, f"GET {request.path[:200]}")
        return self._response()

    async def start(
        self, listen: str, shutdown_grace: float, max_connections: int = METRICS_MAX_CONNECTIONS
    ) -> None:
        """Serve ``/metrics`` alone on ``listen`` (host:port), holding at most ``max_connections``;
        PortInUse naming the holder when taken."""
        app = web.Application()
        app.router.add_route("GET", "/metrics", self._plain)
        runner = web.AppRunner(
            app, access_log=None, shutdown_timeout=shutdown_grace, keepalive_timeout=_IDLE_TIMEOUT
        )
        await runner.setup()
        host, _, port_text = listen.rpartition(":")
        port = int(port_text)
        self._loopback_only = is_loopback(listen)
        caps = ConnectionCaps(
            max_connections,
            METRICS_MAX_CONNECTIONS_PER_ADDRESS,
            "the metrics port's connections",
            "the metrics port's connections from one address",
        )
        server = runner.server
        assert server is not None  # set up just before
        self._listener = BoundedListener(server, caps, "metrics.listen", refusal=connection_refusal)
        self.address = await start_bounded(self._listener, runner, host.strip("[]"), port, "metrics.listen")
        self._runner = runner

    async def stop(self) -> None:
        """Stop the listener of its own (if any). Idempotent."""
        listener, self._listener = self._listener, None
        if listener is not None:
            await listener.aclose()
        runner, self._runner = self._runner, None
        if runner is not None:
            await runner.cleanup()
