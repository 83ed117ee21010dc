"""rosbridge v2 over one aiohttp WebSocket: text frames in, :class:`Connection`'s messages out.

The HTTP front end upgrades the request at ``/rosbridge`` (its Origin and Host checks, the
caller's identity from the bearer header, the ``ps_token`` cookie or a client certificate, and
one of its stream places: ``http.max_streams`` and ``http.max_streams_per_client``) and hands
the socket here. A write that the client does not take within ``http.write_timeout`` drops the
connection: a client that reads nothing for that long is gone.
"""

from __future__ import annotations

import asyncio
import logging

from aiohttp import WSCloseCode, WSMsgType, web

from gateway.engine.calls import Calls
from gateway.engine.guard import Guard
from gateway.engine.listen import ListenHub
from gateway.engine.rules import Subject
from gateway.fronts.rosbridge.connection import Connection

log = logging.getLogger(__name__)

#: Where the HTTP front end serves rosbridge (what roslibjs's ``new ROSLIB.Ros({url})`` names).
ROSBRIDGE_PATH = "/rosbridge"
#: A WebSocket close reason has at most 123 bytes (RFC 6455 5.5: a control frame's 125, less the code).
MAX_REASON_BYTES = 123


class RosbridgeEndpoint:
    """The rosbridge WebSocket endpoint: one :class:`Connection` a socket."""

    #: rosbridge clients ask for no subprotocol.
    protocols: tuple[str, ...] = ()

    def __init__(self, calls: Calls, hub: ListenHub, guard: Guard, *, write_timeout: float) -> None:
        self.calls = calls
        self.hub = hub
        self.guard = guard
        self.write_timeout = write_timeout
        #: The connections open now (read by the tests and the metrics).
        self.connections: set[Connection] = set()

    async def serve(self, socket: web.WebSocketResponse, request: web.Request, subject: Subject) -> None:
        """Serve one prepared socket of ``request`` until either side closes it."""
        within = self.write_timeout
        peer = request.remote or "?"

        async def send(text: str) -> None:
            try:
                async with asyncio.timeout(within):
                    await socket.send_str(text)
            except TimeoutError:
                log.info(
                    "rosbridge client %s dropped: it read nothing for %g s (http.write_timeout)", peer, within
                )
                # Dropped, not closed: a close frame would wait behind the same full buffer.
                if request.transport is not None:
                    request.transport.abort()
                raise ConnectionResetError("the client reads nothing") from None

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
