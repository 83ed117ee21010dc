"""A live image: ``GET /api/v1/services/{service}/properties/{path}/stream``.

One binary property, followed on the listen hub (the same rules, limits and conflating queue
as a gRPC Listen), written as ``multipart/x-mixed-replace``: one part per value, each with its
``Content-Type`` (the property's media type), ``Content-Length``, ``X-Sequence`` (the stream's
sequence) and ``X-Conflated`` (values skipped for this reader since the last part). For
``image/jpeg`` this is MJPEG, which an ``<img>`` shows as it comes; any image type works the
same way. When the property goes away the body ends with the closing boundary.

A reader slower than the property's rate gets the latest value only: while ``write`` waits on
the client, the stream's queue keeps one value for the property, and a response holding several
events writes only its last. The part's bytes are the value every reader shares, written in
slices (the transport holds at most about two): a stalled reader holds no copy of its own. While
it is written a large part counts against the hub's budget (:mod:`gateway.engine.listen.budget`); one
that does not fit ends the stream. A write that waits longer than ``http.write_timeout`` drops
the connection. Such a stream takes one of the places event streams take
(:mod:`gateway.fronts.http.places`).

A request that cannot start (no such service or property, a text property, refused by the rules)
is a JSON error with its status, before any part.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncGenerator
from contextlib import aclosing

from aiohttp import hdrs, web

from gateway.engine.events import Event, ListenRequest, Mark, Selector
from gateway.engine.listen import ListenStream
from gateway.engine.listen.drain import Wake, taken
from gateway.engine.listen.requests import check_listen
from gateway.engine.rules import Operation
from gateway.engine.status import to_property_error
from gateway.fronts.http.binary import OCTET_STREAM, RAW_HEADERS, property_model, served_type
from gateway.fronts.http.bodies import query_parameters
from gateway.fronts.http.errors import error_response
from gateway.fronts.http.places import StreamHandler, write_or_drop
from gateway.fronts.http.safety import identify
from services.kernel.errors import InvalidArgument, PropertyError
from services.kernel.paths import WILDCARD, is_pattern, validate_path

log = logging.getLogger(__name__)

#: The boundary between parts; it never needs to be absent from a part: each has a Content-Length.
BOUNDARY = "psframe"
CONTENT_TYPE = f"multipart/x-mixed-replace; boundary={BOUNDARY}"
END = f"--{BOUNDARY}--\r\n".encode()


def part_head(media_type: str, size: int, sequence: int, conflated: int) -> bytes:
    """The boundary and headers of one part of ``size`` bytes (the part's bytes and CRLF follow)."""
    return (
        f"--{BOUNDARY}\r\nContent-Type: {media_type}\r\nContent-Length: {size}\r\n"
        f"X-Sequence: {sequence}\r\nX-Conflated: {conflated}\r\n\r\n"
    ).encode("ascii")


def latest(item: list[Event] | Mark) -> tuple[Event | None, int]:
    """The event of what a stream took to write (the last one), and how many values the others
    stood for (a marker: none, nothing)."""
    if isinstance(item, Mark):
        return None, 0
    ready = item
    if not ready:
        return None, 0
    skipped = len(ready) - 1 + sum(event.conflated for event in ready[:-1])
    return ready[-1], skipped


class ImageStreams(StreamHandler):
    """The ``/stream`` handler; streams take places of :class:`StreamPlaces` beside event streams."""

    async def stream(self, request: web.Request) -> web.StreamResponse:
        service = request.match_info["service"]
        path = request.match_info["path"]
        if service == WILDCARD or is_pattern(path):
            raise InvalidArgument("a live image follows one property: no '*' in its service or path")
        validate_path(path)
        parameters = query_parameters(request.query)
        subject = identify(request, self.guard)
        # The property first (a caller may read it without being allowed the whole service's model).
        self.guard.require(subject, service, path, Operation.READ)
        prop = await property_model(self.calls, service, path)
        if prop.type != "bytes":
            raise InvalidArgument(
                f"{service}/{path} is not a binary property (its type is {prop.type}): follow it with"
                f" /api/v1/events?sel={service}/{path}"
            )
        media_type = served_type(prop.media_type or OCTET_STREAM)
        peer = request.remote or "?"
        refused = self.places.refusal(peer)
        if refused is not None:
            return refused
        listen = ListenRequest([Selector(service, path, tuple(sorted(parameters.items())))])

        async def serve(stream: ListenStream, wake: Wake) -> web.StreamResponse:
            async with aclosing(taken(stream, wake)) as ready:
                return await self._serve(request, ready, media_type, peer)

        return await self.serve_stream(peer, subject, check_listen(listen, self.limits), serve)

    async def _serve(
        self,
        request: web.Request,
        ready: AsyncGenerator[list[Event] | Mark, None],
        media_type: str,
        peer: str,
    ) -> web.StreamResponse:
        # The first answer (the current value) before the response begins: a Listen that cannot
        # start is still a JSON error with its status.
        try:
            item: list[Event] | Mark | None = await anext(ready)
        except StopAsyncIteration:
            item = None
        except PropertyError as exc:
            return error_response(exc, f"stream {request.path[:200]}")
        response = web.StreamResponse(
            headers={
                **RAW_HEADERS,
                hdrs.CONTENT_TYPE: CONTENT_TYPE,
                # Proxies such as nginx would otherwise hold parts back to fill a buffer.
                "X-Accel-Buffering": "no",
            }
        )
        await response.prepare(request)
        what = f"image stream {request.path[:200]}"
        skipped = 0
        try:
            while item is not None:
                event, conflated = latest(item)
                item = None
                skipped += conflated
                if event is not None and event.removed:
                    break  # the property went away: the body ends
                data = event.value if event is not None else None
                if event is not None and isinstance(data, bytes):
                    head = part_head(media_type, len(data), event.sequence, skipped + event.conflated)
                    if not await self._write_part(
                        request, response, head=head, data=data, what=what, peer=peer
                    ):
                        return response
                    skipped = 0
                event = data = None  # waiting for the next value, the stream holds nothing of this one
                item = await anext(ready, None)
        except ConnectionError:
            return response  # the client went away
        except Exception as exc:
            err = to_property_error(exc, what)
            log.info("image stream to %s ended: %s %s", peer, err.code.name, err.message)
        try:
            async with asyncio.timeout(self.write_timeout):
                await response.write(END)
                await response.write_eof()
        except (ConnectionError, TimeoutError):
            if request.transport is not None:
                request.transport.abort()
        return response

    async def _write_part(
        self,
        request: web.Request,
        response: web.StreamResponse,
        *,
        head: bytes,
        data: bytes,
        what: str,
        peer: str,
    ) -> bool:
        """Write one part: ``head``, then the value itself (the one every reader shares, in
        slices: no copy of it piles up for a slow reader), counted against the hub's budget
        while it is written. False when the reader was dropped; RESOURCE_EXHAUSTED when the
        budget has no room for it."""
        budget = self.hub.budget
        if not budget.take(len(data)):
            raise budget.refusal(len(data), what)
        try:
            return await write_or_drop(
                request,
                response,
                head,
                data,
                b"\r\n",
                within_s=self.write_timeout,
                what="image stream",
                peer=peer,
            )
        finally:
            budget.give_back(len(data))
