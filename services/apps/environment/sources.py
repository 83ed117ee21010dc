"""Following properties of other services through the gateway's directory, come what may.

A :class:`Follow` keeps Listens on every property of one service whose path matches a
pattern (``*`` stands for one segment, as in a Listen selector): it Listens to the service's
``properties`` and joins and leaves the matching paths as the list changes, so robots that
join a swarm are followed as they come. The listen hub does the same for clients; a service
cannot reach the hub (services never import the gateway), so this is its own small version.

Nothing here ever gives up while the service runs: a service that is not in the directory yet
is waited for (its arrival ends the pause at once), one that does not answer is tried again
after pauses of :func:`services.kernel.backoff.pauses` (through
:func:`~services.kernel.backoff.wait_to_retry`, so a proxy that connects again ends the pause), and one
path that fails is tried again on its own while the others carry on. Every call has a time
limit; every set of paths has a bound.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable

from services.kernel.backend import Backend, Change, Subscription, close_quietly
from services.kernel.backoff import pauses, wait_to_retry
from services.kernel.errors import Code, DeadlineExceeded, NotFound, PropertyError
from services.kernel.paths import compile_pattern
from services.kernel.values import Value, parse_names

__all__ = ["CALL_TIMEOUT_S", "MAX_PATHS", "RETRY_FIRST_S", "RETRY_MAX_S", "Follow"]

log = logging.getLogger(__name__)

#: Pauses before a service or a path is tried again: doubled from the first to the longest,
#: as the gateway's wildcard Listens do (gateway.engine.listen.stream).
RETRY_FIRST_S = 0.5
RETRY_MAX_S = 10.0
#: Seconds one Listen (with its first value) may take.
CALL_TIMEOUT_S = 5.0
#: Paths one follow keeps at most: a swarm of 10,000 robots, one property each.
MAX_PATHS = 10_000
#: Codes that mean "not now": the path may answer later.
_TRANSIENT = (Code.UNAVAILABLE, Code.DEADLINE_EXCEEDED, Code.RESOURCE_EXHAUSTED)

#: Called with (path, value) for the current value and each change of a followed path.
OnValue = Callable[[str, str], None]
#: Called with a path that is gone (removed from the service, or the service left).
OnGone = Callable[[str], None]
#: Picks the pattern to follow from the service's property list; None: nothing to follow yet.
Chooser = Callable[[list[str]], str | None]


def fixed(pattern: str) -> Chooser:
    """A chooser that always follows ``pattern``."""
    compile_pattern(pattern)  # InvalidArgument for a bad one, now
    return lambda names: pattern


class Follow:
    """Listens on the paths of ``service`` that match the chosen pattern, for as long as it runs."""

    def __init__(
        self,
        service: str,
        choose: Chooser,
        on_value: OnValue,
        on_gone: OnGone,
        *,
        role: str,
        timeout_s: float = CALL_TIMEOUT_S,
        max_paths: int = MAX_PATHS,
    ) -> None:
        self.service = service
        #: What the paths are to the follower (one word: markers, robots, readings, locations).
        self.role = role
        self._choose = choose
        self._on_value = on_value
        self._on_gone = on_gone
        self._timeout = timeout_s
        self._max_paths = max_paths
        self._paths: dict[str, asyncio.Task[None]] = {}
        self._pattern: str | None = None
        self._changed = asyncio.Event()
        self._joined = asyncio.Event()
        self._left = asyncio.Event()
        #: One word: starting, absent (not in the directory), retrying, idle (nothing matches), following.
        self.state = "starting"
        #: Why the last try failed ("" when it did not).
        self.reason = ""
        #: Paths the service lists that match, beyond ``max_paths``: not followed.
        self.dropped = 0

    @property
    def pattern(self) -> str | None:
        """The pattern followed now (None until the service's list chose one)."""
        return self._pattern

    @property
    def following(self) -> int:
        return len(self._paths)

    def service_joined(self) -> None:
        """The directory has the service (again): stop waiting for it."""
        self._joined.set()

    def service_left(self) -> None:
        """The service left the directory: its paths are gone until it is back."""
        self._left.set()

    async def run(self, backend_of: Callable[[str], Backend]) -> None:
        """Follow until cancelled. ``backend_of`` is the directory's ``backend`` (NotFound when absent)."""
        delays = pauses(RETRY_FIRST_S, RETRY_MAX_S)
        while True:
            backend: Backend | None = None
            self._joined.clear()
            try:
                backend = backend_of(self.service)
            except NotFound:
                self.state = "absent"
            if backend is not None:
                self._left.clear()
                try:
                    self.reason = ""
                    await self._follow(backend)
                    delays = pauses(RETRY_FIRST_S, RETRY_MAX_S)  # it answered: start the pauses anew
                except PropertyError as e:
                    self.state = "retrying"
                    self.reason = e.message
                    log.debug("%s: %s/properties: %s", self.role, self.service, e.message)
                finally:
                    await self._drop_all()
            pause = next(delays)
            if backend is None:
                try:
                    async with asyncio.timeout(pause):
                        await self._joined.wait()
                except TimeoutError:
                    pass
            else:
                await wait_to_retry(backend, pause)

    async def _follow(self, backend: Backend) -> None:
        """Follow the property list of ``backend``; returns when the service left or its list is gone."""
        listing: list[str] = []
        heard = False
        lost = asyncio.Event()

        def on_list(change: Change) -> None:
            nonlocal heard
            if change.removed:
                lost.set()
                return
            heard = True
            listing[:] = _names(change.value)
            self._changed.set()

        sub: Subscription | None = None
        try:
            async with asyncio.timeout(self._timeout):
                sub, first = await backend.listen_current("properties", on_list)
        except TimeoutError:
            why = f"Listen to {self.service}/properties: no answer within {self._timeout:g} s"
            raise DeadlineExceeded(why) from None
        try:
            if not heard:
                listing[:] = _names(first)
            while not lost.is_set() and not self._left.is_set():
                self._changed.clear()
                self._reconcile(backend, listing)
                waiters = [
                    asyncio.ensure_future(self._changed.wait()),
                    asyncio.ensure_future(lost.wait()),
                    asyncio.ensure_future(self._left.wait()),
                ]
                try:
                    await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
                finally:
                    for waiter in waiters:
                        waiter.cancel()
        finally:
            if sub is not None:
                await close_quietly(sub)

    def _reconcile(self, backend: Backend, listing: list[str]) -> None:
        pattern = self._choose(listing)
        if pattern != self._pattern:
            self._pattern = pattern
            for path in list(self._paths):
                self._drop(path)
        if pattern is None:
            self.state = "idle"
            return
        matches = compile_pattern(pattern)
        wanted = [n for n in listing if matches(n)]
        if len(wanted) > self._max_paths:
            self.dropped = len(wanted) - self._max_paths
            log.warning(
                "%s: %s lists %d paths matching %s; following the first %d",
                self.role,
                self.service,
                len(wanted),
                pattern,
                self._max_paths,
            )
            wanted = wanted[: self._max_paths]
        else:
            self.dropped = 0
        keep = set(wanted)
        for path in [p for p in self._paths if p not in keep]:
            self._drop(path)
        for path in wanted:
            if path not in self._paths:
                self._paths[path] = asyncio.get_running_loop().create_task(
                    self._follow_path(backend, path), name=f"{self.role}: {self.service}/{path}"
                )
        self.state = "following"

    async def _follow_path(self, backend: Backend, path: str) -> None:
        """Listen to one path, trying again after transient failures, until cancelled or refused."""
        delays = pauses(RETRY_FIRST_S, RETRY_MAX_S)
        while True:
            heard = False

            def on_change(change: Change) -> None:
                nonlocal heard
                if change.removed:
                    self._on_gone(path)
                    return
                heard = True
                self._hand_on(path, change.value)

            try:
                async with asyncio.timeout(self._timeout):
                    sub, value = await backend.listen_current(path, on_change)
            except TimeoutError:
                log.debug("%s: Listen to %s/%s: no answer", self.role, self.service, path)
            except PropertyError as e:
                if e.code not in _TRANSIENT:
                    log.debug("%s: %s/%s refused: %s", self.role, self.service, path, e.message)
                    return
                log.debug("%s: %s/%s: %s", self.role, self.service, path, e.message)
            else:
                try:
                    if not heard:
                        self._hand_on(path, value)
                    await asyncio.Event().wait()  # held until cancelled
                finally:
                    await close_quietly(sub)
            await wait_to_retry(backend, next(delays))

    def _hand_on(self, path: str, value: Value) -> None:
        if isinstance(value, bytes):  # every source here is text: a binary value says nothing
            log.debug("%s: %s/%s is binary; not read", self.role, self.service, path)
            return
        try:
            self._on_value(path, value)
        except Exception:  # a listener's callback must not raise into the backend
            log.exception("%s: %s/%s: the value could not be taken in", self.role, self.service, path)

    def _drop(self, path: str) -> None:
        task = self._paths.pop(path, None)
        if task is not None:
            task.cancel()
        self._on_gone(path)

    async def _drop_all(self) -> None:
        tasks = list(self._paths.values())
        for path in list(self._paths):
            self._drop(path)
        self._pattern = None
        if tasks:
            await asyncio.gather(*tasks, return_exceptions=True)


def _names(text: Value) -> list[str]:
    try:
        return parse_names(text) if isinstance(text, str) and text else []
    except PropertyError:
        return []
