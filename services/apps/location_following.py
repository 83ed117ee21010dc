"""Following the ``location`` of many services at once, by name.

The registry keeps each service's location for ``find near=...``; a group keeps
its members' locations for its centroid. Both Listen on every service's
``location`` (the Listen brings the current value: a device's LISTEN answers
with it, so no Get follows; :meth:`Backend.listen_current`), and hand each
parsed vector on. :class:`LocationFollower` is that piece; what the holder does
with a location is its callback.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable, Coroutine
from typing import Any

from services.kernel.backend import Backend, Change, Subscription, close_quietly
from services.kernel.directory import own_context
from services.kernel.errors import Code, PropertyError
from services.kernel.values import Value, ValueFormatError, Vector, as_text, parse_vector

__all__ = ["LocationFollower"]

log = logging.getLogger(__name__)

#: The first pause before a service that did not answer is asked again (it doubles each time).
_FIRST_RETRY = 0.05
#: Codes that mean "not now" rather than "no location": the service may answer later.
_TRANSIENT = (Code.UNAVAILABLE, Code.DEADLINE_EXCEEDED)


class LocationFollower:
    """Listens on ``location`` of each followed service and calls ``on_location(name, vector)``.

    ``vector`` is None when the service has no location (the property was
    removed, is empty, malformed or an empty vector). The value a Get returns
    after the Listen is in place is handed on only when no change was heard
    meanwhile (a change heard is newer).

    ``timeout()`` bounds each Listen and Get. With ``retry_max`` a service
    that does not answer yet (a proxy still connecting) is asked again, less
    and less often, up to every ``retry_max`` seconds, until it answers or is
    forgotten; without it, it is not asked again. ``on_answer(name, backend)``
    is called once the service has answered the Listen, with a subscription
    or with a refusal.
    """

    def __init__(
        self,
        on_location: Callable[[str, Vector | None], None],
        *,
        timeout: Callable[[], float],
        retry_max: float | None = None,
        on_answer: Callable[[str, Backend], None] | None = None,
        what: str = "location",
    ) -> None:
        self._on_location = on_location
        self._timeout = timeout
        self._retry_max = retry_max
        self._on_answer = on_answer
        self._what = what
        self._tasks: dict[str, asyncio.Task[None]] = {}
        self._subscriptions: dict[str, Subscription] = {}
        self._heard: set[str] = set()
        self._running: set[asyncio.Task[None]] = set()

    def follow(self, name: str, backend: Backend) -> None:
        """Start following ``name``'s location; nothing when it is followed already."""
        if name in self._tasks:
            return
        self._tasks[name] = self._spawn(self._follow(name, backend), f"{self._what}: follow {name}")

    def forget(self, name: str) -> None:
        """Stop following ``name`` (its Listen is closed in the background)."""
        task = self._tasks.pop(name, None)
        if task is not None:
            task.cancel()
        self._heard.discard(name)
        sub = self._subscriptions.pop(name, None)
        if sub is not None:
            self._spawn(close_quietly(sub), f"{self._what}: unlisten {name}")

    async def settled(self, within: float) -> None:
        """Wait, at most ``within`` seconds, until every followed service has answered or given up."""
        pending = [t for t in self._tasks.values() if not t.done()]
        if pending:
            await asyncio.wait(pending, timeout=within)

    async def aclose(self) -> None:
        """Forget every service and close every Listen; the follower may be used again afterwards."""
        tasks = list(self._tasks.values())
        self._tasks.clear()
        self._heard.clear()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        subscriptions = list(self._subscriptions.values())
        self._subscriptions.clear()
        for sub in subscriptions:
            await close_quietly(sub)
        if self._running:
            await asyncio.gather(*self._running, return_exceptions=True)

    # -- one service -------------------------------------------------------

    async def _follow(self, name: str, backend: Backend) -> None:
        mine = asyncio.current_task()

        def on_change(change: Change) -> None:
            if self._tasks.get(name) is mine:
                self._heard.add(name)
                self._hand_on(name, "" if change.removed else change.value)

        opened = await self._listen(name, backend, on_change)
        if opened is None:
            return
        sub, value = opened
        if self._tasks.get(name) is not mine:  # forgotten while the Listen was on its way
            await close_quietly(sub)
            return
        self._subscriptions[name] = sub
        if name not in self._heard:
            self._hand_on(name, value)

    async def _listen(
        self, name: str, backend: Backend, on_change: Callable[[Change], None]
    ) -> tuple[Subscription, Value] | None:
        pause = _FIRST_RETRY
        while True:
            try:
                async with asyncio.timeout(self._timeout()):
                    opened = await backend.listen_current("location", on_change)
                break
            except TimeoutError:
                if self._retry_max is None:
                    return None
            except PropertyError as e:
                if e.code not in _TRANSIENT:
                    self._answered(name, backend)
                    return None  # no location (NOT_FOUND) or not listenable: nothing to follow
                if self._retry_max is None:
                    return None  # not reachable now: it does not count until followed again
            await asyncio.sleep(pause)
            pause = min(pause * 2, self._retry_max)
        self._answered(name, backend)
        return opened

    def _answered(self, name: str, backend: Backend) -> None:
        if self._on_answer is not None:
            self._on_answer(name, backend)

    def _hand_on(self, name: str, text: Value) -> None:
        try:
            vector: Vector | None = parse_vector(as_text(text, "location")) if text else None
        except ValueFormatError:
            vector = None
        if vector is not None and vector.size == 0:
            vector = None
        self._on_location(name, vector)

    def _spawn(self, coro: Coroutine[Any, Any, None], what: str) -> asyncio.Task[None]:
        # Following is the follower's own work, whichever client's call made it start.
        task = asyncio.get_running_loop().create_task(coro, name=what, context=own_context())
        self._running.add(task)
        task.add_done_callback(self._done)
        return task

    def _done(self, task: asyncio.Task[None]) -> None:
        self._running.discard(task)
        if not task.cancelled() and task.exception() is not None:
            log.error("%s failed", task.get_name(), exc_info=task.exception())
