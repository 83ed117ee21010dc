"""Test your own services with the SDK: a real gateway in the test's process, no TCP port.

:func:`serve` runs a real :class:`~gateway.app.Gateway` (router, listen hub,
the PropertyService with Get, Set, Listen and Session, the built-in
``registry``) in this process, listening on a unix-domain socket in a fresh
temporary folder, and yields a :class:`clients.AsyncClient` connected to it.
When the block ends the client closes, the gateway stops, the services are
closed and the folder with the socket is removed::

    from gateway.testing import serve

    async def test_my_lamp() -> None:
        async with serve(Lamp(), name="lamp") as client:
            await client.set("lamp", "on", True)
            assert await client.get("lamp", "on") == "true"

Several services are served by a dict (``serve({"lamp": Lamp(), "bot":
Robot()})``); a service is a :class:`services.kernel.core.Resource` (served as
``services.kernel.core.serve`` serves it) or any built
:class:`services.kernel.backend.Backend`. ``config`` sets limits and timeouts
(``Config(limits=Limits(max_streams=2))``); its ``listen`` address is
replaced by the socket. :func:`serve_sync` is the same for blocking tests
and yields a :class:`clients.Client`; :func:`running_gateway` yields the
gateway itself, for tests that speak gRPC with the generated stub on
``grpc.aio.insecure_channel(gateway.address)``; with
``Config(http=HttpSection(listen="127.0.0.1:0"))`` the gateway also serves its HTTP/JSON
front end on a free loopback port, at ``gateway.http.url``. ``docs/testing.md`` has the
whole story.
"""

from __future__ import annotations

import asyncio
import tempfile
import threading
from collections.abc import AsyncIterator, Coroutine, Iterator, Mapping
from contextlib import asynccontextmanager, contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Any, TypeVar

from clients import DEFAULT_TIMEOUT, AsyncClient, Client
from gateway.app import Gateway
from gateway.config import Config
from services.kernel.backend import Backend
from services.kernel.core import Resource
from services.kernel.core import serve as backend_for

T = TypeVar("T")

#: What :func:`serve` accepts as one service.
Service = Resource | Backend

#: Seconds the blocking variant waits for the gateway to start or stop; a gateway of in-process
#: services starts in milliseconds, so this only turns a hang into an error.
START_STOP_WAIT = 30.0


def _backends(services: Service | Mapping[str, Service], name: str | None) -> dict[str, Backend]:
    if isinstance(services, Mapping):
        if name is not None:
            raise TypeError("name= names one service; a dict of services names each by its key")
        named = dict(services)
    elif name is None:
        raise TypeError("serve one service as serve(service, name='...'), or several as a dict")
    else:
        named = {name: services}
    return {key: s if isinstance(s, Backend) else backend_for(s) for key, s in named.items()}


@asynccontextmanager
async def running_gateway(
    services: Service | Mapping[str, Service], *, name: str | None = None, config: Config | None = None
) -> AsyncIterator[Gateway]:
    """A started gateway serving ``services`` on a unix-domain socket; ``gateway.address`` is its target."""
    config = config if config is not None else Config()
    backends = _backends(services, name)
    # Not tempfile's default folder when TMPDIR is long: a socket path must stay under ~100 bytes.
    with tempfile.TemporaryDirectory(prefix="psgw-", dir=_short_tmp()) as folder:
        listen = f"unix:{Path(folder) / 'gateway.sock'}"
        gateway = Gateway(replace(config, gateway=replace(config.gateway, listen=listen)), backends=backends)
        async with gateway:
            yield gateway


@asynccontextmanager
async def serve(
    services: Service | Mapping[str, Service],
    *,
    name: str | None = None,
    config: Config | None = None,
    timeout: float | None = DEFAULT_TIMEOUT,  # noqa: ASYNC109 - the client's per-call bound, handed on
) -> AsyncIterator[AsyncClient]:
    """Serve ``services`` in this process and yield an SDK client of them (calls bounded by ``timeout``)."""
    async with (
        running_gateway(services, name=name, config=config) as gateway,
        AsyncClient(gateway.address, timeout=timeout) as client,
    ):
        yield client


@contextmanager
def serve_sync(
    services: Service | Mapping[str, Service],
    *,
    name: str | None = None,
    config: Config | None = None,
    timeout: float | None = DEFAULT_TIMEOUT,
) -> Iterator[Client]:
    """:func:`serve` for blocking tests: the gateway runs on an event loop in a thread of its own."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="gateway.testing", daemon=True)
    thread.start()

    def on_loop(coro: Coroutine[Any, Any, T]) -> T:
        return asyncio.run_coroutine_threadsafe(coro, loop).result(START_STOP_WAIT)

    try:
        running = running_gateway(services, name=name, config=config)
        gateway = on_loop(running.__aenter__())
        try:
            with Client(gateway.address, timeout=timeout) as client:
                yield client
        finally:
            on_loop(running.__aexit__(None, None, None))
    finally:
        loop.call_soon_threadsafe(loop.stop)
        thread.join(START_STOP_WAIT)
        loop.close()


def _short_tmp() -> str | None:
    default = tempfile.gettempdir()
    return default if len(default) < 60 else "/tmp"
