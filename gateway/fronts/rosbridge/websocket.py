"""rosbridge v2 over one aiohttp WebSocket: text frames in, :class:`Connection`'s messages out.

The HTTP front end hands the request at ``/rosbridge`` here (a ``WebSocketRoute``) once it has
made its checks (Origin, Host), named the caller (the bearer header, the ``ps_token`` cookie or
a client certificate; a bad token is 401 before any upgrade) and given it one of its stream
places (``http.max_streams``, ``http.max_streams_per_client``). The endpoint upgrades it: pings
every ``http.heartbeat`` seconds find a client that vanished, a message larger than
``http.max_body`` closes the socket (1009), and a write the client does not take within
``http.write_timeout`` drops the connection: a client that reads nothing for that long is gone.
"""

from __future__ import annotations

from aiohttp import WSCloseCode, WSMsgType, web

from gateway.engine.calls import Calls
from gateway.engine.guard import Guard
from gateway.engine.listen import ListenHub
from gateway.engine.rules import Subject
from gateway.fronts.rosbridge.connection import Connection
from gateway.fronts.websocket import send_within
from services.kernel.errors import InvalidArgument

#: Where the HTTP front end serves rosbridge (what roslibjs's ``new ROSLIB.Ros({url})`` names).
ROSBRIDGE_PATH = "/rosbridge"
#: A WebSocket close reason has at most 123 bytes (RFC 6455 5.5: a control frame's 125, less the code).
MAX_REASON_BYTES = 123


class RosbridgeEndpoint:
    """The rosbridge WebSocket endpoint: one :class:`Connection` a socket."""

    #: rosbridge clients ask for no subprotocol.
    protocols: tuple[str, ...] = ()

    def __init__(
        self,
        calls: Calls,
        hub: ListenHub,
        guard: Guard,
        *,
        write_timeout: float,
        heartbeat: float = 0.0,
        max_message: int = 1024 * 1024,
    ) -> None:
        self.calls = calls
        self.hub = hub
        self.guard = guard
        self.write_timeout = write_timeout
        #: Seconds between pings (``http.heartbeat``; 0: none): no pong within half of it closes the socket.
        self.heartbeat = heartbeat
        #: The largest message a client may send (``http.max_body``).
        self.max_message = max_message
        #: The connections open now (read by the tests and the metrics).
        self.connections: set[Connection] = set()

    async def serve(self, request: web.Request, subject: Subject) -> web.StreamResponse:
        """Upgrade ``request`` and serve the client as ``subject`` until either side closes."""
        socket = web.WebSocketResponse(
            protocols=self.protocols, heartbeat=self.heartbeat or None, max_msg_size=self.max_message
        )
        if not socket.can_prepare(request).ok:
            raise InvalidArgument(f"{request.path[:200]} speaks WebSocket only: send an Upgrade request")
        await socket.prepare(request)
        await self._serve(socket, request, subject)
        return socket

    async def _serve(self, socket: web.WebSocketResponse, request: web.Request, subject: Subject) -> None:
        peer = request.remote or "?"

        async def send(data: bytes) -> None:
            await send_within(
                socket, request, data, WSMsgType.TEXT, within=self.write_timeout, front="rosbridge"
            )

        connection = Connection(
            calls=self.calls, hub=self.hub, guard=self.guard, subject=subject, send=send, peer=peer
        )
        self.connections.add(connection)
        try:
            async for frame in socket:
                if frame.type in (WSMsgType.TEXT, WSMsgType.BINARY):
                    await connection.received(frame.data)
                    if connection.refused is not None:
                        reason = connection.refused.encode()[:MAX_REASON_BYTES]
                        await socket.close(code=WSCloseCode.POLICY_VIOLATION, message=reason)
                        break
                elif frame.type == WSMsgType.ERROR:
                    break
        except ConnectionError:
            pass  # the client is gone, or was dropped for not reading
        finally:
            self.connections.discard(connection)
            await connection.aclose()
            if not socket.closed:
                await socket.close()
