"""A small Backend over a dict, for tests that need a service they fully control.

Properties are the dict's keys; ``properties`` lists them. Sets notify
listeners; ``add``/``remove`` change the property list and notify listeners
of ``properties``; ``delay`` makes every get and set wait that long.
"""

from __future__ import annotations

import asyncio
from collections.abc import Mapping

from services.backend import NO_PARAMS, Backend, BackendInfo, Change, Notify, Subscription
from services.errors import NotFound, ReadOnly
from services.values import format_names


class _Sub(Subscription):
    def __init__(self, backend: DictBackend, path: str, notify: Notify) -> None:
        self.backend, self.path, self.notify = backend, path, notify

    async def close(self) -> None:
        self.backend.subs.discard(self)


class DictBackend(Backend):
    """A service whose properties are a dict of strings."""

    def __init__(self, values: Mapping[str, str], readonly: tuple[str, ...] = (), delay: float = 0.0) -> None:
        self.values = dict(values)
        self.readonly = set(readonly)
        self.delay = delay
        self.subs: set[_Sub] = set()
        self.info = BackendInfo(type="dict", url="local")
        self.closed = False

    def _check(self, path: str) -> None:
        if path != "properties" and path not in self.values:
            raise NotFound(f"no property {path!r}")

    def _value(self, path: str) -> str:
        return format_names(self.values) if path == "properties" else self.values[path]

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        if self.delay:
            await asyncio.sleep(self.delay)
        self._check(path)
        return self._value(path)

    async def set(self, path: str, value: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        if self.delay:
            await asyncio.sleep(self.delay)
        self._check(path)
        if path in self.readonly or path == "properties":
            raise ReadOnly(f"{path} is read-only")
        self.put(path, value)
        return value

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        self._check(path)
        sub = _Sub(self, path, notify)
        self.subs.add(sub)
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
