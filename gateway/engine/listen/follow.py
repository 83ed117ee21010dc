"""The gateway's side of :data:`services.kernel.follow.Follow`: a Listen that an application drains.

A recorder (and a keeper of history) follows selectors as a Listen would, without importing the
gateway: the gateway hands it :class:`HubFollow`, which opens one
:class:`~gateway.engine.listen.stream.ListenStream` on the hub (the same selectors, wildcards,
limits, snapshot, conflation and ``gap`` as a client's Listen) and drains it on a task of its
own with :func:`gateway.engine.listen.drain.steps`, handing each batch to the follower as
:class:`~services.kernel.follow.FollowedEvent` values. An in-process front, like the HTTP event
stream, but with no wire: markers (``sync``, heartbeats) are not handed on.

**Whose rights.** The stream is opened for the caller of the call being served
(:data:`services.kernel.directory.CALLER`): a recording a client starts hears only what that
client may read, checked as its own Listen would be (an exact selector it may not read is
PERMISSION_DENIED, a wildcard skips what it may not read). With no caller (a service's own work,
a configuration's selectors) the stream is the service's own and no rule checks it.

The follower's callback runs on the event loop as each batch is taken, and must not block: a
follower that hands batches to a thread of its own keeps the stream drained, so conflation
happens only when the loop itself falls behind.
"""

from __future__ import annotations

import asyncio
import logging

from gateway.engine.events import ListenRequest, Mark, Selector, events
from gateway.engine.guard import subject_of
from gateway.engine.listen.drain import Wake, steps
from gateway.engine.listen.hub import ListenHub
from gateway.engine.listen.requests import check_listen
from gateway.engine.listen.stream import ListenStream
from services.kernel.backend import Subscription
from services.kernel.directory import CALLER, own_context
from services.kernel.errors import InvalidArgument, PropertyError
from services.kernel.follow import FollowedEvent, OnEvents

__all__ = ["HubFollow", "parse_selector"]

log = logging.getLogger(__name__)


def parse_selector(text: str) -> Selector:
    """``SERVICE/PATH`` (the first ``/`` splits service from path) as a Listen selector."""
    service, slash, path = text.partition("/")
    if not slash or not service or not path:
        raise InvalidArgument(
            f"selector {text[:300]!r} must be SERVICE/PATH, like scout1/location or */location"
        )
    return Selector(service, path)


class _Followed(Subscription):
    """One follow: its stream and the task that drains it; ``close`` ends both."""

    __slots__ = ("_stream", "_task")

    def __init__(self, stream: ListenStream, task: asyncio.Task[None]) -> None:
        self._stream = stream
        self._task = task

    async def close(self) -> None:
        self._stream.close()
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)


class HubFollow:
    """:data:`services.kernel.follow.Follow` on a listen hub; see the module docstring."""

    def __init__(self, hub: ListenHub) -> None:
        self.hub = hub

    async def __call__(self, selectors: list[str], on_events: OnEvents) -> Subscription:
        hub = self.hub
        request = ListenRequest([parse_selector(text) for text in selectors])
        checked, options = check_listen(request, hub.limits)
        caller = CALLER.get()
        wake = Wake()
        stream = hub.open(checked, options, wake.set, subject_of(caller), own_work=caller is None)
        try:
            await stream.start()
        except BaseException:
            stream.close()
            raise
        # The drain is the service's own: it outlives the call that started it.
        task = asyncio.get_running_loop().create_task(
            _drain(stream, wake, on_events, selectors), context=own_context()
        )
        return _Followed(stream, task)


async def _drain(stream: ListenStream, wake: Wake, on_events: OnEvents, selectors: list[str]) -> None:
    try:
        for step in steps(stream, wake):
            if isinstance(step, asyncio.Future):
                await step
                continue
            if isinstance(step, Mark):
                continue
            followed = events(step, FollowedEvent)
            del step
            try:
                on_events(followed)
            except Exception:
                log.exception("a follower of %s failed on %d events", " ".join(selectors), len(followed))
    except PropertyError as exc:
        log.info("the follow of %s ended: %s", " ".join(selectors), exc.message)
    finally:
        stream.close()
