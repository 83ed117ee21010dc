"""The places for long-lived HTTP streams: Server-Sent Events and live images share one bound.

An open stream holds a connection, a listen-hub stream and a buffer for as long as the client
stays, so the front end bounds how many are open: ``http.max_streams`` in all (503 beyond) and
``http.max_streams_per_client`` from one client address (429 beyond), so that one client cannot
take every place. An event stream and an image stream each take one place of the same count:
a page that shows a camera holds its event stream and one place per image it shows.
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager

from aiohttp import web

from gateway.config import HttpSection, Limits
from gateway.engine.calls import Calls
from gateway.engine.events import Selector, StreamOptions
from gateway.engine.guard import Guard
from gateway.engine.listen import ListenHub, ListenStream
from gateway.engine.listen.drain import Wake
from gateway.engine.rules import Subject
from gateway.fronts.http.errors import TOO_MANY_REQUESTS, TOO_MANY_STREAMS, error_response
from services.kernel.errors import ResourceExhausted

log = logging.getLogger(__name__)


class StreamPlaces:
    """Counts of open streams, in all and by client address (an address leaves with its last one)."""

    def __init__(self, settings: HttpSection) -> None:
        self.max_streams = settings.max_streams
        self.max_per_client = settings.max_streams_per_client
        self.open = 0
        self.per_client: Counter[str] = Counter()

    def refusal(self, peer: str) -> web.Response | None:
        """The answer to a stream ``peer`` may not open now (429 or 503), or None when it may."""
        if self.per_client[peer] >= self.max_per_client:
            return too_many(
                f"too many streams open from {peer[:100]} ({self.max_per_client},"
                " http.max_streams_per_client; event and image streams together)",
                TOO_MANY_REQUESTS,
            )
        if self.open >= self.max_streams:
            return too_many(f"too many streams open ({self.max_streams}, http.max_streams)")
        return None

    @contextmanager
    def held(self, peer: str) -> Iterator[None]:
        """One place taken by ``peer`` while the block runs (check :meth:`refusal` first)."""
        self.open += 1
        self.per_client[peer] += 1
        try:
            yield
        finally:
            self.open -= 1
            self.per_client[peer] -= 1
            if self.per_client[peer] <= 0:
                del self.per_client[peer]


class StreamHandler:
    """What a handler of long-lived streams holds: the hub, the calls, the guard, the limits, the
    shared places and the write deadline, and the listen-hub streams it has open."""

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
        self.hub = hub
        self.calls = calls
        self.guard = guard
        self.limits = limits
        self.places = places
        self.write_timeout = settings.write_timeout
        self.open: set[ListenStream] = set()

    async def serve_stream(
        self,
        peer: str,
        subject: Subject,
        listen: tuple[list[Selector], StreamOptions],
        serve: Callable[[ListenStream, Wake], Awaitable[web.StreamResponse]],
    ) -> web.StreamResponse:
        """Open a hub stream of the checked ``listen`` for ``peer`` and answer with
        ``serve(stream, wake)``; the stream and the peer's place are given back however it ends."""
        selectors, options = listen
        wake = Wake()
        try:
            stream = self.hub.open(selectors, options, wake.set, subject)
        except ResourceExhausted as exc:
            return too_many(exc.message)
        self.open.add(stream)
        try:
            with self.places.held(peer):
                return await serve(stream, wake)
        finally:
            stream.close()
            self.open.discard(stream)


def too_many(message: str, status: int = TOO_MANY_STREAMS) -> web.Response:
    """RESOURCE_EXHAUSTED as JSON with ``status`` (503: come back later; 429: this client asks too much)."""
    return error_response(ResourceExhausted(message), status=status)


#: Bytes handed to a connection at a time. The transport copies what the socket does not take at
#: once into its own buffer, so a large value written whole would be copied once per slow reader
#: (Python 3.11's asyncio); in slices of its high-water mark (64 KiB) the transport holds at most
#: about two, and the value itself stays the one copy every reader shares.
WRITE_SLICE = 64 * 1024


async def write_or_drop(
    request: web.Request,
    response: web.StreamResponse,
    *pieces: bytes,
    within_s: float,
    what: str,
    peer: str,
) -> bool:
    """Write ``pieces`` one after the other to a stream within ``within_s`` seconds; False when
    the reader did not take them.

    A piece larger than :data:`WRITE_SLICE` is written a slice at a time, each once the
    connection has taken the last (no copy of it piles up in the transport). A reader that reads
    nothing for that long is dropped (its connection aborted), not finished: finishing would wait
    on the same full buffer. ``what`` names the stream in the log line.
    """
    try:
        async with asyncio.timeout(within_s):
            for piece in pieces:
                if len(piece) <= WRITE_SLICE:
                    await response.write(piece)
                    continue
                view = memoryview(piece)
                for start in range(0, len(view), WRITE_SLICE):
                    await response.write(view[start : start + WRITE_SLICE])
    except TimeoutError:
        log.info("%s to %s ended: it read nothing for %g s (http.write_timeout)", what, peer, within_s)
        if request.transport is not None:
            request.transport.abort()
        return False
    return True
