"""WebSocket endpoints on the HTTP front end: the HTTP half of a protocol spoken over a WebSocket.

A WebSocket protocol (rosbridge, :mod:`gateway.fronts.rosbridge`) is a front of its own; the
gateway's assembly hands its endpoint to :attr:`HttpFront.websockets` under a path, and this
module serves it there. The HTTP front end does what it does for every request (Origin and Host
checks, the request id) and, for the upgrade, what it does for an event stream: the caller's
identity (bearer header, ``ps_token`` cookie or client certificate; a bad token is 401 before
any upgrade), and one place of the stream count (``http.max_streams`` in all, 503 beyond;
``http.max_streams_per_client`` from one address, 429 beyond) for as long as the socket is
open. Pings every ``http.heartbeat`` seconds find a client that vanished; a message larger than
``http.max_body`` closes the socket (1009).
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Protocol

from aiohttp import web

from gateway.config import HttpSection
from gateway.engine.guard import Guard
from gateway.engine.rules import Subject
from gateway.fronts.http.places import StreamPlaces
from gateway.fronts.http.safety import identify
from services.kernel.errors import InvalidArgument


class WebSocketEndpoint(Protocol):
    """What a WebSocket protocol's front hands the HTTP front end."""

    #: The subprotocols it speaks (the first one a client offers is chosen); () for none.
    protocols: tuple[str, ...]

    async def serve(self, socket: web.WebSocketResponse, request: web.Request, subject: Subject) -> None:
        """Serve the prepared ``socket`` of ``request`` for ``subject`` until it closes."""


class WebSockets:
    """The upgrade of each WebSocket endpoint's requests; see the module docstring."""

    def __init__(self, guard: Guard, settings: HttpSection, places: StreamPlaces) -> None:
        self.guard = guard
        self.settings = settings
        self.places = places

    def handler(self, endpoint: WebSocketEndpoint) -> Callable[[web.Request], Awaitable[web.StreamResponse]]:
        """The route handler that upgrades a request and hands the socket to ``endpoint``."""

        async def upgrade(request: web.Request) -> web.StreamResponse:
            socket = web.WebSocketResponse(
                protocols=endpoint.protocols,
                heartbeat=self.settings.heartbeat or None,
                max_msg_size=self.settings.max_body,
            )
            if not socket.can_prepare(request).ok:
                raise InvalidArgument(f"{request.path[:200]} speaks WebSocket only: send an Upgrade request")
            subject = identify(request, self.guard, always=True)
            peer = request.remote or "?"
            refused = self.places.refusal(peer)
            if refused is not None:
                return refused
            with self.places.held(peer):
                await socket.prepare(request)
                await endpoint.serve(socket, request, subject)
            return socket

        return upgrade
