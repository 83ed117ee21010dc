"""The Foxglove endpoint the HTTP front hands a WebSocket upgrade, with the caller's subject."""

from __future__ import annotations

from aiohttp import web

from gateway.engine.calls import Calls
from gateway.engine.listen import ListenHub
from gateway.engine.rules import Subject
from gateway.fronts.foxglove.connection import Connection
from gateway.fronts.foxglove.protocol import SUBPROTOCOLS
from services.kernel.errors import InvalidArgument
from services.kernel.values.binary import MAX_BINARY_SIZE

#: The largest message a client may send: a binary property's largest value in base64, with room
#: for its JSON. aiohttp refuses a bigger one (close code 1009) before it is buffered whole.
MAX_FRAME_BYTES = MAX_BINARY_SIZE * 4 // 3 + 64 * 1024


class FoxgloveEndpoint:
    """Serves Foxglove clients through the engine's calls and listen hub."""

    def __init__(
        self,
        calls: Calls,
        hub: ListenHub,
        *,
        write_timeout: float,
        heartbeat: float = 0.0,
        name: str = "psgateway",
    ) -> None:
        self.calls = calls
        self.hub = hub
        self.write_timeout = write_timeout
        #: Seconds between pings (``http.heartbeat``); 0: none.
        self.heartbeat = heartbeat
        self.name = name

    async def serve(self, request: web.Request, subject: Subject) -> web.StreamResponse:
        """Upgrade ``request`` (it must offer a Foxglove subprotocol) and serve the client until it leaves."""
        offered = [
            p.strip() for p in request.headers.get("Sec-WebSocket-Protocol", "").split(",") if p.strip()
        ]
        if not any(p in SUBPROTOCOLS for p in offered):
            raise InvalidArgument(
                f"a Foxglove client must offer the WebSocket subprotocol {' or '.join(SUBPROTOCOLS)}"
                f" (offered: {', '.join(offered)[:200] or 'none'})"
            )
        # A ping every ``heartbeat`` seconds, and the socket closed when no pong follows within half
        # of it: a client that vanished without a FIN gives its place back, as an event stream's
        # heartbeat does.
        ws = web.WebSocketResponse(
            protocols=SUBPROTOCOLS,
            max_msg_size=MAX_FRAME_BYTES,
            autoping=True,
            heartbeat=self.heartbeat or None,
        )
        await ws.prepare(request)
        connection = Connection(
            ws,
            request,
            calls=self.calls,
            hub=self.hub,
            subject=subject,
            write_timeout=self.write_timeout,
            name=self.name,
        )
        try:
            await connection.run()
        finally:
            await ws.close()
        return ws
