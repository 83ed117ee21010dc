"""Writing to a WebSocket client that may stop reading: the one writer the WebSocket fronts share.

The rosbridge and Foxglove endpoints write each message through :func:`send_within`: a client
that takes nothing for ``http.write_timeout`` seconds is dropped (its transport aborted: a close
frame would wait behind the same full buffer), and a client that went away ends its connection.
Either way the caller sees :class:`ConnectionResetError` and ends the connection quietly.
"""

from __future__ import annotations

import asyncio
import logging

from aiohttp import WSMsgType, web

log = logging.getLogger(__name__)


async def send_within(
    socket: web.WebSocketResponse,
    request: web.Request,
    data: bytes,
    kind: WSMsgType,
    *,
    within: float,
    front: str,
) -> None:
    """Send ``data`` as one frame of ``kind`` (TEXT holds UTF-8) to the client within ``within`` s.

    ConnectionResetError when the client took nothing for that long (it is dropped, and ``front``
    names it in the log line) or is gone.
    """
    try:
        async with asyncio.timeout(within):
            await socket.send_frame(data, kind)
    except TimeoutError:
        log.info(
            "%s client %s dropped: it read nothing for %g s (http.write_timeout)",
            front,
            request.remote or "?",
            within,
        )
        if request.transport is not None:
            request.transport.abort()
        raise ConnectionResetError("the client reads nothing") from None
    except ConnectionError as exc:
        # aiohttp keeps this error in the future its writer waited on, whose frame is in the
        # error's traceback: a cycle that would hold our frames (and the message being written)
        # until a full collection. Without its traceback nothing holds them.
        exc.__traceback__ = None
        raise ConnectionResetError("the client went away") from None
