"""The gateway speaking the line protocol on raw TCP (off by default; ``gateway.line_listen``).

A microcontroller that knows only lines of text can reach every service
behind the gateway: the first path segment names the service::

    GET scout1.location.x     →  router.backend("scout1").get("location.x")
    SET light1.switch on
    LISTEN scout1.location.x  →  EVENT scout1.location.x 0.52 ...
    GET properties            →  the names of the services, "(light1 registry scout1)"

The sessions themselves are :class:`services.device_server.DeviceSession`s: the
gateway is just one more device whose backend is the whole router.
"""

from __future__ import annotations

import contextlib
from collections.abc import Mapping
from typing import TYPE_CHECKING

from services.backend import NO_PARAMS, Backend, BackendInfo, Change, Notify, Subscription
from services.device_server import DeviceServer
from services.errors import InvalidArgument, ReadOnly
from services.values import format_names

if TYPE_CHECKING:
    from collections.abc import Callable

    from gateway.router import Router


class _Watch(Subscription):
    def __init__(self, unwatch: Callable[[], None]) -> None:
        self._unwatch: Callable[[], None] | None = unwatch

    async def close(self) -> None:
        unwatch, self._unwatch = self._unwatch, None
        if unwatch is not None:
            unwatch()


class RouterBackend(Backend):
    """Every service of a router as one tree: ``SERVICE.PATH``; ``properties`` lists the services."""

    def __init__(self, router: Router) -> None:
        self.router = router
        self.info = BackendInfo(type="gateway", url="line")

    def _split(self, path: str) -> tuple[Backend, str]:
        service, dot, rest = path.partition(".")
        backend = self.router.backend(service)
        if not dot or not rest:
            raise InvalidArgument(f"{path!r} names a service; name one of its properties: {service}.PROPERTY")
        return backend, rest

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        if path == "properties":
            return format_names(self.router.names())
        backend, rest = self._split(path)
        return await backend.get(rest, params)

    async def set(self, path: str, value: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        if path == "properties":
            raise ReadOnly("properties (the list of services) is read-only")
        backend, rest = self._split(path)
        return await backend.set(rest, value, params)

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        if path == "properties":

            def changed(name: str, backend: Backend | None) -> None:
                notify(Change("properties", format_names(self.router.names())))

            return _Watch(self.router.watch(changed))
        backend, rest = self._split(path)
        service = path.partition(".")[0]

        def forward(change: Change) -> None:
            notify(Change(f"{service}.{change.path}", change.value, change.gap, change.removed))

        return await backend.listen(rest, forward, params)


class LineListener:
    """A raw-TCP line-protocol server in front of a router; ``aclose`` stops it."""

    def __init__(self, router: Router, *, name: str = "gateway") -> None:
        self.server = DeviceServer(RouterBackend(router), name=name, type="gateway", push=True)
        self.address: tuple[str, int] | None = None

    async def start(self, host: str, port: int) -> tuple[str, int]:
        """Listen on ``host:port`` (0 = any free port); return the bound address."""
        self.address = await self.server.serve_tcp(host, port)
        return self.address

    async def aclose(self) -> None:
        with contextlib.suppress(Exception):
            await self.server.aclose()


def parse_address(address: str) -> tuple[str, int]:
    """``"HOST:PORT"`` → (host, port); InvalidArgument when it is not one."""
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit() or int(port) > 65535:
        raise InvalidArgument(f"bad line_listen address {address!r}; expected HOST:PORT, e.g. 127.0.0.1:7100")
    return host.strip("[]") or "127.0.0.1", int(port)


async def start_line_listener(address: str, router: Router) -> LineListener:
    """Start a :class:`LineListener` on ``address`` ("HOST:PORT") for ``router``."""
    listener = LineListener(router)
    await listener.start(*parse_address(address))
    return listener
