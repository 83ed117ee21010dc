"""Server-Sent Events: a Listen as ``text/event-stream``, drained like a gRPC Listen stream.

``GET /api/v1/events?sel=SERVICE/PATH&sel=...`` opens one
:class:`~gateway.engine.listen.stream.ListenStream` on the gateway's listen hub (the same
selectors, wildcards, rules, limits and conflating queue as a gRPC Listen) and writes
the events :func:`gateway.engine.listen.drain.taken` yields (:class:`gateway.engine.events.Event`):

* ``event: value`` with ``id: N`` (the stream's sequence) and ``data:`` a JSON object
  ``{"service", "path", "value", "gap", "removed", "conflated", "time"}``: first the current
  value of every matched property, then ``event: sync`` (``data: {}``), then changes; a binary
  value has ``data`` (base64) and ``media_type`` instead of ``value`` (:mod:`gateway.fronts.http.binary`);
* ``: heartbeat`` comment lines when the stream has been quiet for ``http.heartbeat`` seconds;
* ``event: error`` (``data: {"code", "message"}``) when the Listen fails; the stream then ends.

A request with ``Last-Event-ID`` (EventSource resuming) gets the snapshot with
``gap: true`` on each value: changes in between may be lost. A client that does not read
makes ``write`` wait (the message is written in slices: the transport buffers at most about
two); meanwhile the stream's queue keeps only the latest value of each property. A message
carrying a large value counts against the hub's budget while it is written
(:mod:`gateway.engine.listen.budget`); one that does not fit ends the stream with ``event: error``
(RESOURCE_EXHAUSTED). A write that waits longer than
``http.write_timeout`` ends the stream (the connection is dropped): a client that reads
nothing for that long is gone.

Bounds on open streams: ``http.max_streams`` in all (503 beyond) and
``http.max_streams_per_client`` from one client address (429 beyond), shared with the live
image streams (:mod:`gateway.fronts.http.places`).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from contextlib import aclosing, suppress

from aiohttp import hdrs, web

from gateway.config import HttpSection, Limits
from gateway.engine.calls import Calls
from gateway.engine.events import Event, ListenRequest, Mark, Selector
from gateway.engine.guard import Guard
from gateway.engine.listen import ListenHub, ListenStream
from gateway.engine.listen.drain import Wake, taken
from gateway.engine.listen.requests import check_listen
from gateway.engine.rules import Subject
from gateway.engine.status import to_property_error
from gateway.fronts.http.binary import OCTET_STREAM, MediaTypes, value_json
from gateway.fronts.http.errors import error_json
from gateway.fronts.http.places import StreamHandler, StreamPlaces, write_or_drop
from gateway.fronts.http.safety import identify
from services.kernel.errors import InvalidArgument, PropertyError

log = logging.getLogger(__name__)

SYNC = b"event: sync\ndata: {}\n\n"
HEARTBEAT = b": heartbeat\n\n"
#: The query key of a selector; every other key is refused (a typo must not pass unnoticed).
SELECTOR_KEY = "sel"


def listen_request(selectors: list[str], heartbeat: float = 0.0) -> ListenRequest:
    """``SERVICE/PATH`` selectors as a Listen (the first ``/`` splits service from path), with a
    heartbeat after ``heartbeat`` quiet seconds (0: none)."""
    if not selectors:
        raise InvalidArgument("give at least one selector: /api/v1/events?sel=SERVICE/PATH")
    parsed = []
    for text in selectors:
        service, slash, path = text.partition("/")
        if not slash or not service or not path:
            raise InvalidArgument(
                f"selector {text[:300]!r} must be SERVICE/PATH, like scout1/location or */location"
            )
        parsed.append(Selector(service, path))
    return ListenRequest(parsed, heartbeat_interval=heartbeat)


def event_json(event: Event, gap: bool, media_type: str) -> dict[str, object]:
    """One event as the JSON of its ``data:`` line: ``value``, or ``data`` and ``media_type`` when binary."""
    item: dict[str, object] = {"service": event.service, "path": event.path}
    value = event.value
    if isinstance(value, bytes):
        item.update(value_json("", value, media_type))
    else:
        item.update(value_json(value, None, media_type))
    item.update(
        gap=event.gap or gap,
        removed=event.removed,
        conflated=event.conflated,
        time=event.time_ns / 1e9,
    )
    return item


def binary_refs(item: list[Event] | Mark) -> list[tuple[str, str]]:
    """(service, path) of each binary value in ``item``."""
    if isinstance(item, Mark):
        return []
    return [(event.service, event.path) for event in item if isinstance(event.value, bytes)]


def encode(item: list[Event] | Mark, gap: bool, media_types: Mapping[tuple[str, str], str] = {}) -> bytes:
    """Events or a marker as SSE messages; ``gap`` marks every value (a resumed snapshot);
    ``media_types`` names the media type of each binary value by (service, path)."""
    if item is Mark.SYNC:
        return SYNC
    if item is Mark.HEARTBEAT:
        return HEARTBEAT
    assert not isinstance(item, Mark)
    parts = []
    for event in item:
        media_type = media_types.get((event.service, event.path), OCTET_STREAM)
        data = json.dumps(event_json(event, gap, media_type), ensure_ascii=False)
        parts.append(f"id: {event.sequence}\nevent: value\ndata: {data}\n\n")
    return "".join(parts).encode()


def error_event(err: PropertyError) -> bytes:
    return f"event: error\ndata: {json.dumps(error_json(err), ensure_ascii=False)}\n\n".encode()


class EventStreams(StreamHandler):
    """The ``/api/v1/events`` handler and its bound on open streams."""

    def __init__(
        self,
        hub: ListenHub,
        calls: Calls,
        *,
        guard: Guard,
        limits: Limits,
        settings: HttpSection,
        places: StreamPlaces,
    ) -> None:
        super().__init__(hub, calls, guard=guard, limits=limits, settings=settings, places=places)
        self.heartbeat = settings.heartbeat

    async def events(self, request: web.Request) -> web.StreamResponse:
        unknown = [key for key in request.query if key != SELECTOR_KEY]
        if unknown:
            raise InvalidArgument(f"unknown query key {unknown[0][:100]!r} (known: {SELECTOR_KEY})")
        listen = listen_request(request.query.getall(SELECTOR_KEY, []), self.heartbeat)
        # Checked before the stream takes a place: a bad Listen is refused whatever the load.
        checked = check_listen(listen, self.limits)
        subject = identify(request, self.guard)
        peer = request.remote or "?"
        refused = self.places.refusal(peer)
        if refused is not None:
            return refused
        return await self.serve_stream(
            peer,
            subject,
            checked,
            lambda stream, wake: self._serve(request, stream, wake, peer, subject),
        )

    async def _serve(
        self, request: web.Request, stream: ListenStream, wake: Wake, peer: str, subject: Subject
    ) -> web.StreamResponse:
        response = web.StreamResponse(
            headers={
                hdrs.CONTENT_TYPE: "text/event-stream; charset=utf-8",
                hdrs.CACHE_CONTROL: "no-cache",
                # Proxies such as nginx would otherwise hold events back to fill a buffer.
                "X-Accel-Buffering": "no",
            }
        )
        await response.prepare(request)
        resumed = hdrs.LAST_EVENT_ID in request.headers
        snapshot = True
        media_types = MediaTypes(self.calls)
        budget = self.hub.budget
        try:
            async with aclosing(taken(stream, wake)) as ready:
                async for item in ready:
                    for service, path in binary_refs(item):
                        await media_types.of(service, path)  # a model read the first time only
                    chunk = encode(item, resumed and snapshot, media_types.known)
                    if item is Mark.SYNC:
                        snapshot = False
                    # A chunk carrying a binary value is this reader's one copy of it (base64):
                    # counted against the hub's budget until the connection has taken it.
                    size = len(chunk)
                    if not budget.take(size):
                        del chunk  # not held while the error is written
                        return await self._end(request, response, budget.refusal(size, "event stream"), peer)
                    try:
                        written = await write_or_drop(
                            request,
                            response,
                            chunk,
                            within_s=self.write_timeout,
                            what="event stream",
                            peer=peer,
                        )
                    finally:
                        budget.give_back(size)
                    del chunk
                    if not written:
                        return response
        except ConnectionError:
            return response  # the client went away
        except Exception as exc:
            return await self._end(request, response, exc, peer)
        return response

    async def _end(
        self, request: web.Request, response: web.StreamResponse, exc: BaseException, peer: str
    ) -> web.StreamResponse:
        """End the stream with ``event: error`` for ``exc`` (a reader that does not take it within
        ``http.write_timeout`` is dropped)."""
        event = error_event(to_property_error(exc, "event stream"))
        with suppress(ConnectionError):
            await write_or_drop(
                request, response, event, within_s=self.write_timeout, what="event stream", peer=peer
            )
        return response
