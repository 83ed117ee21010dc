"""The one fake service of the tests: a Backend over a dict of strings that the test controls.

Properties are the dict's keys; ``properties`` lists them. A Set notifies
listeners; :meth:`DictBackend.put` changes a value "from the inside", as a
device would; :meth:`~DictBackend.add` and :meth:`~DictBackend.remove` change
the property list. Its link can fail the ways a real device's does:
``delay`` makes every get and set wait that long, ``unreachable`` makes every
call UNAVAILABLE (a closed port), ``silent`` makes gets and sets never answer
and listens fail (a device that is connected but mute).
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping

from services.kernel.backend import NO_PARAMS, Backend, BackendInfo, Change, Notify, Subscription
from services.kernel.errors import NotFound, ReadOnly, Unavailable
from services.kernel.values import format_names


class DictSubscription(Subscription):
    """One listener of one property of a :class:`DictBackend`."""

    def __init__(self, backend: DictBackend, path: str, notify: Notify) -> None:
        self.backend, self.path, self.notify = backend, path, notify

    async def close(self) -> None:
        if self in self.backend.subs:
            self.backend.subs.remove(self)


class DictBackend(Backend):
    """A service whose properties are a dict of strings."""

    def __init__(
        self,
        values: Mapping[str, str] | None = None,
        readonly: tuple[str, ...] = (),
        delay: float = 0.0,
        *,
        type: str = "dict",
        url: str = "local",
        unreachable: bool = False,
        silent: bool = False,
    ) -> None:
        self.values = dict(values or {})
        self.readonly = set(readonly)
        self.delay = delay
        #: Every call is UNAVAILABLE while this is true; a test may flip it to cut or mend the link.
        self.unreachable = unreachable
        self.silent = silent
        self.subs: list[DictSubscription] = []
        self.info = BackendInfo(type=type, url=url)
        self.closed = False

    async def _answer_after(self, path: str) -> None:
        """Wait and fail as the link is set to; then check that ``path`` exists."""
        if self.unreachable:
            raise Unavailable(f"cannot reach {self.info.url}: connection refused")
        if self.silent:
            await asyncio.Event().wait()
        if self.delay:
            await asyncio.sleep(self.delay)
        if path != "properties" and path not in self.values:
            raise NotFound(f"no property {path!r}")

    def _value(self, path: str) -> str:
        return format_names(self.values) if path == "properties" else self.values[path]

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        await self._answer_after(path)
        return self._value(path)

    async def set(self, path: str, value: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        await self._answer_after(path)
        if path in self.readonly or path == "properties":
            raise ReadOnly(f"{path} is read-only")
        self.put(path, value)
        return value

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        if self.unreachable or self.silent:
            raise Unavailable(f"cannot reach {self.info.url}: connection refused")
        await self._answer_after(path)
        sub = DictSubscription(self, path, notify)
        self.subs.append(sub)
        return sub

    def put(self, path: str, value: str) -> None:
        """Change a value from the inside, as a device would."""
        self.values[path] = value
        self._notify(Change(path, value))

    def add(self, path: str, value: str) -> None:
        """A new property appears."""
        self.values[path] = value
        self._notify(Change("properties", format_names(self.values)))

    def remove(self, path: str) -> None:
        """A property goes away."""
        del self.values[path]
        self._notify(Change(path, "", removed=True))
        self._notify(Change("properties", format_names(self.values)))

    def _notify(self, change: Change) -> None:
        for sub in list(self.subs):
            if sub.path == change.path:
                sub.notify(change)

    def listeners(self, path: str) -> int:
        """How many subscriptions are open on ``path``."""
        return sum(1 for s in self.subs if s.path == path)

    async def aclose(self) -> None:
        self.closed = True
