"""One service of the cluster as this gateway serves it: a stable router entry whose target can change.

A service registered on a shared store has one owner, the gateway that holds its connection. Every
gateway serves it under one router entry, a :class:`SwitchingBackend`, whose *target* is what
reaches the service now:

* on the owner, the service's own proxy (``tcp://``, ``serial://``, ``grpc://``);
* on every other gateway, a gRPC proxy to the owner (``grpc://OWNER/NAME``): calls are forwarded;
* while no gateway owns it (its owner died and nobody has taken it over yet), nothing: calls get
  UNAVAILABLE saying why.

When the owner changes, :meth:`SwitchingBackend.switch` moves every Listen to the new target and
hands each listener the current value as a ``Change(gap=True)``: values may have been missed in
between, and the listener hears that it may have. The router entry, and so the listen hub's topics
and every client stream on them, stay as they are.

A planned move (a drain, a rebalance: :mod:`gateway.cluster.moves`) is cleaner than a failure: the
old target is closed only once the Gets and Sets on it have ended (at most :data:`CALLS_END_WAIT`),
and while the service has no target for such a move (``switch(None, hold=...)``) a call waits for
the next target, up to the hold, instead of being refused: a client's Set is answered by the new
owner, never lost in between.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import logging
import random
from collections.abc import Mapping

from services.kernel.backend import (
    NO_PARAMS,
    UNKNOWN_TYPE,
    Backend,
    BackendInfo,
    Change,
    LinkCounts,
    Notify,
    Subscription,
    close_quietly,
)
from services.kernel.errors import Code, PropertyError, Unavailable
from services.kernel.model import PropertyModel, ServiceModel
from services.kernel.values import Value

__all__ = [
    "CALLS_END_WAIT",
    "RESUME_BACKOFF_INITIAL",
    "RESUME_BACKOFF_MAX",
    "RESUME_NOT_FOUND_WAIT",
    "SwitchingBackend",
]

log = logging.getLogger(__name__)

#: First and longest pause between attempts to listen again on a new target that cannot be
#: listened to yet (the new owner is still connecting to the device); doubled per failure, jittered.
RESUME_BACKOFF_INITIAL = 0.1
RESUME_BACKOFF_MAX = 2.0
#: Seconds a Listen being opened again on a new target takes NOT_FOUND for "not there yet" (the new
#: owner, or the gateway it forwards to, has not caught up with the move) before it reports the
#: property removed: a service that only moves between owners is never reported removed.
RESUME_NOT_FOUND_WAIT = 5.0
#: Seconds a switch waits for the Gets and Sets on the old target to end before closing it: a
#: device's own timeout (2 s by default) ends them sooner.
CALLS_END_WAIT = 5.0


class _CallsOn:
    """The Gets and Sets under way on one target: a switch waits for them to end before closing it."""

    __slots__ = ("ended", "running")

    def __init__(self) -> None:
        self.running = 0
        self.ended: asyncio.Event | None = None

    def end(self) -> None:
        self.running -= 1
        if self.running == 0 and self.ended is not None:
            self.ended.set()

    async def wait_ended(self, wait_s: float) -> None:
        if self.running == 0:
            return
        self.ended = asyncio.Event()
        try:
            async with asyncio.timeout(wait_s):
                await self.ended.wait()
        except TimeoutError:
            log.info("%d calls still under way on a target being closed", self.running)


class _SwitchedListen(Subscription):
    """One listener of a :class:`SwitchingBackend`: its place on the current target, moved on a switch."""

    def __init__(self, owner: SwitchingBackend, path: str, notify: Notify, params: Mapping[str, str]) -> None:
        self.owner = owner
        self.path = path
        self.notify = notify
        self.params = dict(params)
        #: The subscription on the target it was opened on; None while it is being moved.
        self.sub: Subscription | None = None
        #: Counts the targets this listen was opened on: a change from an older one is dropped.
        self.generation = 0
        #: The task that opens it on a new target (one at a time).
        self.resuming: asyncio.Task[None] | None = None
        self.closed = False
        #: Its key in the owner's table of listens.
        self.key = -1
        #: While it is opened again on a new target, and until the first ordinary change after:
        #: whether the gap of this move has been told (None: not moving).
        self.gap_told: bool | None = None
        #: The value the gap of this move carried.
        self.gap_value: Value = ""

    def forward_for(self, generation: int) -> Notify:
        """The notify handed to the target of ``generation``: it passes changes on while that is current."""

        def forward(change: Change) -> None:
            if self.generation == generation and not self.closed:
                if self.gap_told is None:
                    self.notify(change)
                else:
                    self.tell_moved(change)

        return forward

    def tell_moved(self, change: Change) -> None:
        """A change while the listen moves to a new target, or just after: one gap for the move.

        The new target may report a gap of its own for the same interruption (a gateway it forwards
        to that was still connecting to the device, a device proxy that had to listen again): the
        listener hears of the move once, marked gap, and the value it did not have yet unmarked.
        """
        if change.removed or not change.gap:
            if not change.gap and self.gap_told:
                self.gap_told = None  # an ordinary change: the move is over
            self.notify(change)
        elif not self.gap_told:
            self.gap_told = True
            self.gap_value = change.value
            self.notify(change)
        elif change.value != self.gap_value:
            self.gap_value = change.value
            self.notify(dataclasses.replace(change, gap=False))

    async def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        self.owner.forget(self)
        resuming, self.resuming = self.resuming, None
        if resuming is not None and resuming is not asyncio.current_task():
            resuming.cancel()
            await asyncio.gather(resuming, return_exceptions=True)
        sub, self.sub = self.sub, None
        if sub is not None:
            await close_quietly(sub)


class SwitchingBackend(Backend):
    """A cluster service's router entry on one gateway; its target follows the owner (module docstring)."""

    def __init__(
        self,
        name: str,
        url: str,
        *,
        declared_type: str = "",
        reason: str = "",
        not_found_wait: float = RESUME_NOT_FOUND_WAIT,
    ) -> None:
        """``url`` is the registration's URL (what every gateway's registry shows); ``declared_type``
        the type the registration declared; ``reason`` why there is no target yet;
        ``not_found_wait``: see :data:`RESUME_NOT_FOUND_WAIT`."""
        self.not_found_wait = not_found_wait
        self.name = name
        self.info = BackendInfo(type=declared_type or UNKNOWN_TYPE, url=url)
        self._declared_type = declared_type
        self._target: Backend | None = None
        #: What the target is, for messages ("owned here", "forwarded to gateway gw2 at ...").
        self.target_label = ""
        self._reason = reason or f"service {name!r} has no owner in the cluster yet"
        self._listens: dict[int, _SwitchedListen] = {}
        self._ids = itertools.count()
        self._has_target = asyncio.Event()
        #: The Gets and Sets under way on the current target.
        self._calls = _CallsOn()
        #: Until this loop time a call finding no target waits for one (a planned move: ``hold``).
        self._hold_until = 0.0
        #: Subscriptions being closed because they were opened on a target that is gone.
        self._dropping: set[asyncio.Task[None]] = set()
        self._closed = False

    def __repr__(self) -> str:
        return f"SwitchingBackend({self.name!r}, {self.target_label or self._reason!r})"

    @property
    def target(self) -> Backend | None:
        """What reaches the service now; None while nobody owns it."""
        return self._target

    # -- switching ---------------------------------------------------------

    async def switch(
        self, target: Backend | None, label: str = "", reason: str = "", hold: float = 0.0
    ) -> None:
        """Reach the service through ``target`` (started) from now on; None: through nothing, because of
        ``reason``. The old target is closed once the calls on it have ended; every Listen moves to
        the new one with a gap. ``hold`` (with None, for a planned move): seconds a call waits for
        the next target before it is refused."""
        old = self._target
        if target is None and hold > 0:
            self._hold_until = asyncio.get_running_loop().time() + hold
        if target is old:
            return
        if self._closed:
            if target is not None:
                await target.aclose()
            return
        old_calls, self._calls = self._calls, _CallsOn()
        self._target = target
        self.target_label = label if target is not None else ""
        if reason:
            self._reason = reason
        if target is None:
            self._has_target.clear()
        else:
            self._has_target.set()
            self._learn_type(target)
        listens = list(self._listens.values())
        for listen in listens:
            listen.generation += 1
        # The old subscriptions go first (their proxy is about to close); then each Listen opens
        # again on the new target in its own task, which retries while the new owner connects.
        await asyncio.gather(*(self._detach(listen) for listen in listens))
        for listen in listens:
            self._resume(listen)
        if old is not None:
            await old_calls.wait_ended(CALLS_END_WAIT)
            await old.aclose()

    async def _detach(self, listen: _SwitchedListen) -> None:
        resuming, listen.resuming = listen.resuming, None
        if resuming is not None:
            resuming.cancel()
            await asyncio.gather(resuming, return_exceptions=True)
        sub, listen.sub = listen.sub, None
        if sub is not None:
            await close_quietly(sub)

    def _resume(self, listen: _SwitchedListen) -> None:
        if self._target is None or listen.closed:
            return  # resumed by the switch that brings a target
        listen.resuming = asyncio.get_running_loop().create_task(
            self._listen_again(listen, self._target, listen.generation),
            name=f"cluster {self.name}: listen again to {listen.path}",
        )

    async def _listen_again(self, listen: _SwitchedListen, target: Backend, generation: int) -> None:
        """Open ``listen`` on ``target`` (retrying while it cannot be reached yet), then report a gap."""
        failures = 0
        loop = asyncio.get_running_loop()
        began = loop.time()
        if listen.gap_told is None:
            listen.gap_told = False  # one gap for the move, however many targets it passes through
        while listen.generation == generation and not listen.closed:
            try:
                sub, value = await target.listen_current(
                    listen.path, listen.forward_for(generation), listen.params
                )
            except PropertyError as exc:
                if exc.code is Code.NOT_FOUND and loop.time() - began >= self.not_found_wait:
                    listen.gap_told = None
                    listen.notify(Change(listen.path, "", removed=True))
                    return
                failures += 1
                level = logging.INFO if failures == 1 else logging.DEBUG
                log.log(level, "%s: cannot listen to %s again yet: %s", self.name, listen.path, exc.message)
                delay = min(RESUME_BACKOFF_MAX, RESUME_BACKOFF_INITIAL * 2 ** min(failures - 1, 30))
                await asyncio.sleep(delay * random.uniform(0.5, 1.0))
                continue
            if listen.generation != generation or listen.closed:
                await close_quietly(sub)
                return
            listen.sub = sub
            listen.resuming = None
            listen.tell_moved(Change(listen.path, value, gap=True))
            return

    # -- calls -------------------------------------------------------------

    def _require(self) -> Backend:
        target = self._target
        if target is None:
            raise Unavailable(self._reason)
        return target

    async def _held(self) -> Backend:
        """The target, once there is one again when a planned move holds the calls; else as _require."""
        loop = asyncio.get_running_loop()
        if self._target is None and loop.time() < self._hold_until:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout_at(self._hold_until):
                    await self._has_target.wait()
        return self._require()

    def _learn_type(self, target: Backend) -> None:
        if not self._declared_type and target.info.type != UNKNOWN_TYPE:
            self.info.type = target.info.type

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
        target = self._target
        if target is None:
            target = await self._held()
        calls = self._calls
        calls.running += 1
        try:
            return await target.get(path, params)
        finally:
            calls.end()

    async def set(self, path: str, value: Value, params: Mapping[str, str] = NO_PARAMS) -> Value:
        target = self._target
        if target is None:
            target = await self._held()
        calls = self._calls
        calls.running += 1
        try:
            return await target.set(path, value, params)
        finally:
            calls.end()

    async def describe(self) -> ServiceModel:
        target = self._target
        return await (target if target is not None else await self._held()).describe()

    async def properties(self) -> list[str]:
        return await self._require().properties()

    async def match_properties(self, pattern: str, under: str = "") -> list[PropertyModel]:
        return await self._require().match_properties(pattern, under)

    async def check(self) -> None:
        target = self._require()
        await target.check()
        self._learn_type(target)

    def link_counts(self) -> LinkCounts | None:
        target = self._target
        return target.link_counts() if target is not None else None

    async def wait_connected(self, wait_s: float) -> None:
        """Wait for a target, then for it to be connected; Unavailable, saying why, after ``wait_s``."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + wait_s
        try:
            async with asyncio.timeout_at(deadline):
                await self._has_target.wait()
        except TimeoutError:
            raise Unavailable(self._reason) from None
        target = self._require()
        await target.wait_connected(max(0.0, deadline - loop.time()))
        self._learn_type(target)

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        if self._target is None:
            await self._held()
        listen, target, generation = self._place(path, notify, params)
        try:
            sub = await target.listen(path, listen.forward_for(generation), params)
        except BaseException:
            await listen.close()
            raise
        self._settle(listen, sub, generation)
        return listen

    async def listen_current(
        self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS
    ) -> tuple[Subscription, Value]:
        if self._target is None:
            await self._held()
        listen, target, generation = self._place(path, notify, params)
        try:
            sub, value = await target.listen_current(path, listen.forward_for(generation), params)
        except BaseException:
            await listen.close()
            raise
        self._settle(listen, sub, generation)
        return listen, value

    def _place(
        self, path: str, notify: Notify, params: Mapping[str, str]
    ) -> tuple[_SwitchedListen, Backend, int]:
        target = self._require()
        listen = _SwitchedListen(self, path, notify, params)
        listen.key = next(self._ids)
        self._listens[listen.key] = listen
        return listen, target, listen.generation

    def _settle(self, listen: _SwitchedListen, sub: Subscription, generation: int) -> None:
        if listen.generation == generation and not listen.closed:
            listen.sub = sub
            return
        # The target changed while the Listen was being opened: the switch found no subscription to
        # move and has already set it to open again on the new target; this one is dropped.
        task = asyncio.get_running_loop().create_task(
            close_quietly(sub), name=f"cluster {self.name}: drop a listen"
        )
        self._dropping.add(task)
        task.add_done_callback(self._dropping.discard)

    def forget(self, listen: _SwitchedListen) -> None:
        """A Listen ended (its :meth:`_SwitchedListen.close`)."""
        self._listens.pop(listen.key, None)

    @property
    def listens(self) -> int:
        """Listens held now (for tests and metrics)."""
        return len(self._listens)

    # -- lifecycle ---------------------------------------------------------

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        await asyncio.gather(*(listen.close() for listen in list(self._listens.values())))
        await asyncio.gather(*self._dropping, return_exceptions=True)
        target, self._target = self._target, None
        self._has_target.clear()
        if target is not None:
            await target.aclose()
