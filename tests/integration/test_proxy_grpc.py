"""The grpc:// proxy (federation): one gateway serving a service of another through the v1 contract."""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator, Awaitable
from contextlib import asynccontextmanager
from typing import Any

import pytest
from support.ports import free_port, silent_port
from support.waiting import eventually

from clients import errors as client_errors
from clients.aio import SYNC, AsyncClient, Event, Mark
from gateway.app import Gateway
from gateway.backends import open_proxy
from gateway.config import loads_config
from gateway.proxies import GrpcProxy
from services.apps.registry import check_url
from services.kernel.backend import Change
from services.kernel.errors import Code, InvalidArgument, PropertyError

FAST = {"timeout": 2.0, "connect_timeout": 1.0, "backoff_initial": 0.05, "backoff_max": 0.5}

REMOTE_CONFIG = """
[gateway]
listen = "127.0.0.1:0"

[[services]]
name = "scout1"
type = "sim-robot"
options = { start = [0.0, 0.0], speed = 5.0 }

[[services]]
name = "scout2"
type = "sim-robot"
options = { start = [1.0, 0.0] }
"""


async def expect_error(code: Code, call: Awaitable[object]) -> PropertyError:
    with pytest.raises(PropertyError) as info:
        await call
    assert info.value.code == code, info.value
    return info.value


@asynccontextmanager
async def proxy_to(url: str, name: str = "far1", **options: object) -> AsyncIterator[GrpcProxy]:
    proxy = open_proxy(name, url, {**FAST, **options})
    assert isinstance(proxy, GrpcProxy)
    await proxy.start()
    try:
        yield proxy
    finally:
        await proxy.aclose()


def xy(text: str) -> tuple[float, float]:
    numbers = text.strip("()").split()
    return float(numbers[0]), float(numbers[1])


def test_malformed_urls_and_options_are_refused_clearly() -> None:
    for url in (
        "grpc://127.0.0.1/scout1",
        "grpc://127.0.0.1:99999/scout1",
        "grpc://:5000/scout1",
        "grpc://127.0.0.1:5000/robots.scout1",
        "grpc://127.0.0.1:5000/a/b",
    ):
        with pytest.raises(InvalidArgument) as info:
            open_proxy("far1", url, {})
        assert "far1" in info.value.message and "grpc://HOST:PORT/SERVICE" in info.value.message, url
    for options in (
        {"nope": 1},
        {"timeout": "-1"},
        {"timeout": "soon"},
        {"backoff_initial": 5, "backoff_max": 1},
    ):
        with pytest.raises(InvalidArgument) as info:
            open_proxy("far1", "grpc://127.0.0.1:5000/scout1", options)
        assert "grpc proxy option" in info.value.message, options
    with pytest.raises(InvalidArgument, match="timeout"):
        open_proxy("far1", "grpc://127.0.0.1:5000/scout1?timeout=0", {})
    same_name = open_proxy("scout3", "grpc://127.0.0.1:5000?timeout=0.5", {})
    assert isinstance(same_name, GrpcProxy)
    assert (same_name.remote, same_name.target, same_name.options.timeout) == (
        "scout3",
        "127.0.0.1:5000",
        0.5,
    )
    assert same_name.info.url == "grpc://127.0.0.1:5000?timeout=0.5"


async def test_an_unreachable_gateway_is_unavailable_at_once() -> None:
    async with proxy_to(f"grpc://127.0.0.1:{free_port()}/scout1") as proxy:
        err = await expect_error(Code.UNAVAILABLE, proxy.get("location"))
        assert "scout1 on gateway 127.0.0.1:" in err.message
        await expect_error(Code.UNAVAILABLE, proxy.set("behaviors.stop", ""))
        await expect_error(Code.UNAVAILABLE, proxy.listen("location", lambda change: None))
        await expect_error(Code.UNAVAILABLE, proxy.check())
        await expect_error(Code.UNAVAILABLE, proxy.wait_connected(0.3))
        assert proxy.info.type == "unknown"  # never reached: nobody said what it is
    await proxy.aclose()  # idempotent
    await expect_error(Code.UNAVAILABLE, proxy.get("location"))


async def test_a_gateway_that_never_answers_gives_deadline_exceeded() -> None:
    async with (
        silent_port() as port,  # accepts the connection and never speaks HTTP/2
        proxy_to(f"grpc://127.0.0.1:{port}/scout1", timeout=0.3) as proxy,
    ):
        err = await expect_error(Code.DEADLINE_EXCEEDED, proxy.get("location"))
        assert err.message == f"scout1 on gateway 127.0.0.1:{port}: no answer within 0.3 s"
        await expect_error(Code.DEADLINE_EXCEEDED, proxy.listen("location", lambda change: None))
        await expect_error(Code.UNAVAILABLE, proxy.wait_connected(0.3))


async def test_proxy_calls_and_shared_listens_against_an_in_process_gateway() -> None:
    async with (
        Gateway(loads_config(REMOTE_CONFIG)) as remote,
        proxy_to(f"grpc://{remote.address}/scout1") as proxy,
    ):
        await proxy.wait_connected(5)
        assert proxy.info.type == "mobile_robot"  # from the remote registry
        assert "location" in await proxy.properties()
        await proxy.check()
        assert xy(await proxy.get("location")) == (0, 0)
        err = await expect_error(Code.NOT_FOUND, proxy.get("nope"))
        assert err.message.startswith(f"scout1 on gateway {remote.address}: ") and "nope" in err.message
        await expect_error(Code.INVALID_ARGUMENT, proxy.set("behaviors.moveto", "(1 2)"))
        await expect_error(Code.NOT_FOUND, proxy.listen("nope", lambda change: None))

        first: asyncio.Queue[Change] = asyncio.Queue(1000)
        second: asyncio.Queue[Change] = asyncio.Queue(1000)
        sub1 = await proxy.listen("location", first.put_nowait)
        sub2 = await proxy.listen("location", second.put_nowait)
        assert len(proxy.shared_listens) == 1  # one remote Listen for both
        # The remote subscription is live once listen returns: this move is not missed.
        await proxy.set("behaviors.moveto", "<marker><location>(1 1)</location></marker>")
        for queue in (first, second):
            async with asyncio.timeout(10):
                while xy((change := await queue.get()).value) != (1, 1):
                    assert not change.gap and not change.removed
        await sub1.close()
        await sub1.close()  # idempotent
        assert len(proxy.shared_listens) == 1
        await expect_error(Code.FAILED_PRECONDITION, proxy.set("location", "(0.5 0.5)"))
        await proxy.set("behaviors.moveto", "<marker><location>(0.5 0.5)</location></marker>")
        async with asyncio.timeout(10):
            while xy((await second.get()).value) != (0.5, 0.5):
                pass
        await sub2.close()
        assert not proxy.shared_listens


async def listen_into(
    client: AsyncClient, queue: asyncio.Queue[Event | Mark], service: str, prop: str
) -> None:
    async for item in client.listen(service, prop, updates_only=True, marks=True):
        await queue.put(item)


async def next_event(queue: asyncio.Queue[Event | Mark], within: float = 10.0) -> Event:
    async with asyncio.timeout(within):
        while True:
            item = await queue.get()
            if isinstance(item, Event):
                return item


#: The registry marks a service up again: until then its calls are UNAVAILABLE.
UNAVAILABLE = (client_errors.Unavailable,)


async def test_federation_between_two_gateway_processes(gateway_process: Any) -> None:
    port = free_port()
    remote = gateway_process(REMOTE_CONFIG, extra_args=["--listen", f"127.0.0.1:{port}"])
    assert remote.address == f"127.0.0.1:{port}"
    local = gateway_process(f"""
        [registry]
        period = 0.3
        timeout = 1.0
        misses = 1

        [[services]]
        name = "far1"
        url = "grpc://127.0.0.1:{port}/scout1"
        options = {{ timeout = 2.0, connect_timeout = 1.0, backoff_initial = 0.05, backoff_max = 0.5 }}
    """)
    events: asyncio.Queue[Event | Mark] = asyncio.Queue(10_000)
    async with (
        AsyncClient(local.address, timeout=5) as client,
        AsyncClient(remote.address, timeout=5) as direct,
    ):
        assert await client.get("far1", "location") == await direct.get("scout1", "location")
        with pytest.raises(client_errors.NotFound, match=f"scout1 on gateway 127.0.0.1:{port}: .*nope"):
            await client.get("far1", "nope")
        assert (
            await eventually(lambda: client.get("registry", "services.far1.type"), retry_on=UNAVAILABLE)
            == "mobile_robot"
        )

        listener = asyncio.create_task(listen_into(client, events, "far1", "location"))
        try:
            async with asyncio.timeout(10):
                assert await events.get() is SYNC
            await client.set("far1", "behaviors.moveto", "<marker><location>(2 1)</location></marker>")
            while not math.isclose(xy((event := await next_event(events)).value)[0], 2, abs_tol=1e-9):
                assert not event.gap
            assert xy(event.value) == (2, 1)
            assert xy(await direct.get("scout1", "location")) == (2, 1)

            # Registration by Set on the local registry: URL without a service = the same name there.
            await client.set("registry", "services.scout2", f"grpc://127.0.0.1:{port}")
            assert await client.get("registry", "services.scout2.type") == "mobile_robot"
            assert await client.get("scout2", "location") == await direct.get("scout2", "location")

            # The remote gateway goes away: calls fail with UNAVAILABLE, the Listen stays open.
            assert remote.stop() == 0
            with pytest.raises(client_errors.Unavailable):
                await client.get("far1", "location")
            await asyncio.sleep(0.5)  # the proxy tries to listen again a few times meanwhile
            assert not listener.done()

            # It comes back on the same port (a fresh robot at its start): the Listen goes on with a gap.
            remote = gateway_process(REMOTE_CONFIG, extra_args=["--listen", f"127.0.0.1:{port}"])
            gap = await next_event(events)
            assert gap.gap and not gap.removed
            assert xy(gap.value) == (0, 0)
            assert gap.value == await direct.get("scout1", "location")
            assert await eventually(lambda: client.get("far1", "location"), retry_on=UNAVAILABLE) == gap.value
            await client.set("far1", "behaviors.moveto", "<marker><location>(0 3)</location></marker>")
            while xy((await next_event(events)).value) != (0, 3):
                pass
            assert not listener.done()
            assert "Traceback" not in local.output, local.output
        finally:
            listener.cancel()
            await asyncio.gather(listener, return_exceptions=True)


def test_the_registry_accepts_a_grpc_url_naming_the_remote_service() -> None:
    assert check_url("grpc://127.0.0.1:5000/scout2") == "grpc://127.0.0.1:5000/scout2"
