"""In-process pieces for registry and group tests: a Directory over real backends.

``MemoryDirectory`` does what the gateway's router does for system services,
with ``devices`` standing in for the network: registering ``tcp://...`` finds
the backend listening "at" that URL, or is refused like a closed port.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Mapping
from typing import Any

from services.apps.simulators import SimRobot
from services.kernel.backend import NO_PARAMS, Backend, BackendInfo, Change, Notify, Subscription
from services.kernel.core import LocalService
from services.kernel.directory import DirectoryListener
from services.kernel.errors import AlreadyExists, NotFound, Unavailable
from support.fake_backend import DictBackend


class MemoryDirectory:
    """A Directory over in-process backends; ``devices`` maps a URL to the backend "at" it."""

    def __init__(self) -> None:
        self.backends: dict[str, Backend] = {}
        self.devices: dict[str, Callable[[], Backend]] = {}
        self._watchers: list[DirectoryListener] = []

    def names(self) -> list[str]:
        return sorted(self.backends)

    def __contains__(self, name: object) -> bool:
        return name in self.backends

    def backend(self, name: str) -> Backend:
        try:
            return self.backends[name]
        except KeyError:
            raise NotFound(f"unknown service {name!r}") from None

    def watch(self, listener: DirectoryListener) -> Callable[[], None]:
        self._watchers.append(listener)
        return lambda: self._watchers.remove(listener) if listener in self._watchers else None

    async def add(self, name: str, backend: Backend) -> Backend:
        if name in self.backends:
            raise AlreadyExists(f"a service named {name!r} already exists")
        await backend.start()
        self.backends[name] = backend
        for w in list(self._watchers):
            w(name, backend)
        return backend

    async def serve(self, name: str, backend: Backend) -> None:
        await self.add(name, backend)

    async def register(self, name: str, url: str, options: Mapping[str, Any] | None = None) -> BackendInfo:
        if name in self.backends:
            raise AlreadyExists(f"a service named {name!r} already exists")
        make = self.devices.get(url)
        if make is None:
            raise Unavailable(f"cannot connect to {url}: connection refused")
        backend = make()
        backend.info = BackendInfo(type=backend.info.type, url=url)
        await self.add(name, backend)
        return backend.info

    async def unregister(self, name: str) -> None:
        backend = self.backends.pop(name, None)
        if backend is None:
            raise NotFound(f"unknown service {name!r}")
        for w in list(self._watchers):
            w(name, None)
        await backend.aclose()

    async def aclose(self) -> None:
        for name in self.names():
            await self.unregister(name)


def unreachable_robot(url: str = "tcp://127.0.0.1:9") -> DictBackend:
    """A device that cannot be reached any more: every call is UNAVAILABLE."""
    return DictBackend(type="mobile_robot", url=url, unreachable=True)


def mute_robot(url: str = "tcp://127.0.0.1:9") -> DictBackend:
    """A device that is connected but never answers."""
    return DictBackend(type="mobile_robot", url=url, silent=True)


class Switchable(Backend):
    """A real simulated robot whose link can be cut and restored, like a device on a flaky cable."""

    def __init__(self, inner: Backend) -> None:
        self.inner = inner
        self.info = inner.info
        self.alive = True

    def _check(self) -> None:
        if not self.alive:
            raise Unavailable(f"cannot reach {self.info.url}: connection reset")

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        self._check()
        return await self.inner.get(path, params)

    async def set(self, path: str, value: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        self._check()
        return await self.inner.set(path, value, params)

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        self._check()
        return await self.inner.listen(path, notify, params)

    async def start(self) -> None:
        await self.inner.start()

    async def aclose(self) -> None:
        await self.inner.aclose()


def sim_robot(x: float = 0.0, y: float = 0.0, speed: float = 200.0) -> LocalService:
    """A real simulated robot, fast so that tests finish quickly."""
    return LocalService(SimRobot(start=(x, y), speed=speed, tick_hz=200.0))


async def wait_for(
    service: Backend, path: str, predicate: Callable[[str], bool], within: float = 10.0
) -> str:
    """Listen to ``path`` until ``predicate(value)`` holds (at most ``within`` s); return that value."""
    done = asyncio.Event()
    seen: list[str] = []

    def notify(change: Change) -> None:
        seen.append(change.value)
        if predicate(change.value):
            done.set()

    sub = await service.listen(path, notify)
    try:
        try:
            current = await service.get(path)
        except Exception:  # not there yet: wait for the change
            current = None
        if current is not None and predicate(current):
            return current
        async with asyncio.timeout(within):
            await done.wait()
        return seen[-1]
    finally:
        await sub.close()
