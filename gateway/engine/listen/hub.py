"""The listen hub: fan-out of backend changes to Listen streams, with bounded memory.

It owns the :class:`~gateway.engine.listen.topics.Topics` (one backend subscription
per (service, path, parameters), shared by every stream) and the open
:class:`~gateway.engine.listen.stream.ListenStream`\\ s, follows the router's services
coming and going, and ends everything at shutdown.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

from gateway.config import Limits
from gateway.engine.events import ListenRequest, Selector, StreamOptions
from gateway.engine.guard import Guard
from gateway.engine.identity import ANONYMOUS
from gateway.engine.listen.budget import PayloadBudget
from gateway.engine.listen.requests import check_listen
from gateway.engine.listen.stream import ListenStream
from gateway.engine.listen.topics import Topics
from gateway.engine.router import Router
from gateway.engine.rules import Operation, Subject
from services.kernel.backend import Backend
from services.kernel.errors import ResourceExhausted, Unavailable
from services.kernel.paths import WILDCARD, is_pattern

log = logging.getLogger(__name__)

#: The message every stream ends with when the gateway stops: UNAVAILABLE, so a client knows
#: to reconnect (to this gateway once it is back, or another), never a clean end of the stream.
SHUTTING_DOWN = "gateway shutting down"


class ListenHub:
    """Shares backend subscriptions among Listen streams; see the module docstring."""

    def __init__(
        self, router: Router, limits: Limits, call_timeout: float, guard: Guard | None = None
    ) -> None:
        self.router = router
        self.guard = guard or Guard()
        self.limits = limits
        self.topics = Topics(call_timeout, self.guard)
        #: What every reader of every front end holds of large values, together (limits.max_pending_binary).
        self.budget = PayloadBudget(limits.max_pending_binary)
        self._streams: set[ListenStream] = set()
        #: Events sent and values conflated by the streams already closed (the open ones keep their own).
        self.closed_events_sent = 0
        self.closed_conflated = 0
        self._closing = False
        self._unwatch = router.watch(self._service_changed)

    @property
    def topic_count(self) -> int:
        """Backend subscriptions open right now."""
        return len(self.topics)

    @property
    def stream_count(self) -> int:
        """Listen streams open right now."""
        return len(self._streams)

    def listen(
        self, request: ListenRequest, on_ready: Callable[[], None], subject: Subject = ANONYMOUS
    ) -> ListenStream:
        """:meth:`open` a stream for ``request``, checked against the limits first (InvalidArgument,
        ResourceExhausted); what the gRPC front calls (the HTTP front checks a request itself
        first: a bad one is refused before it takes a place)."""
        return self.open(*check_listen(request, self.limits), on_ready, subject)

    def open(
        self,
        selectors: Sequence[Selector],
        options: StreamOptions,
        on_ready: Callable[[], None],
        subject: Subject = ANONYMOUS,
        *,
        own_work: bool = False,
    ) -> ListenStream:
        """A new stream of checked ``selectors`` and ``options`` (then ``start`` it, and ``close`` it
        when done) for ``subject``; ``on_ready`` is called when the stream has something to take.

        Raises RESOURCE_EXHAUSTED beyond the limits, and UNAUTHENTICATED or PERMISSION_DENIED
        for an exact selector the subject may not read (wildcards skip what it may not read).
        ``own_work``: a service's own stream (a configuration's follow,
        :mod:`gateway.engine.listen.follow`), which no rule checks.
        """
        if self._closing:
            raise Unavailable(SHUTTING_DOWN)
        guard = self.guard
        checks = guard.checks and not own_work
        if checks:
            for sel in selectors:
                if sel.service != WILDCARD and not is_pattern(sel.path):
                    guard.require(subject, sel.service, sel.path, Operation.READ)
        if len(self._streams) >= self.limits.max_streams:
            raise ResourceExhausted(
                f"too many Listen streams open ({self.limits.max_streams}, limits.max_streams)"
            )
        stream = ListenStream(
            self.router,
            self.topics,
            self.limits,
            selectors=selectors,
            options=options,
            on_ready=on_ready,
            on_close=self._closed,
            may_read=guard.reader(subject) if checks else None,
            caller=subject if checks else None,
        )
        self._streams.add(stream)
        return stream

    @property
    def closing(self) -> bool:
        """The gateway is shutting down: no stream opens any more."""
        return self._closing

    def _closed(self, stream: ListenStream) -> None:
        self._streams.discard(stream)
        self.closed_events_sent += stream.events_sent
        self.closed_conflated += stream.conflated

    def counts(self) -> tuple[int, int, list[int]]:
        """Events sent and values conflated by every stream so far, and what each open stream has queued."""
        sent, conflated = self.closed_events_sent, self.closed_conflated
        queued = []
        for stream in self._streams:
            sent += stream.events_sent
            conflated += stream.conflated
            queued.append(stream.queued)
        return sent, conflated, queued

    def _service_changed(self, name: str, backend: Backend | None) -> None:
        if backend is not None:
            for stream in list(self._streams):
                stream.service_added(name, backend)
            return
        self.topics.service_removed(name)
        for stream in list(self._streams):
            stream.service_removed(name)

    def end_all(self) -> None:
        """End every stream with UNAVAILABLE "gateway shutting down"; refuse new ones."""
        self._closing = True
        for stream in list(self._streams):
            stream.fail(Unavailable(SHUTTING_DOWN))

    async def aclose(self) -> None:
        """End every stream and close every backend subscription."""
        self.end_all()
        self._unwatch()
        for stream in list(self._streams):
            stream.close()
        await self.topics.aclose()
