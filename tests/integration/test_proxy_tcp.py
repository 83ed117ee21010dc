"""The TCP proxy against a real device process and against misbehaving devices on real sockets."""

from __future__ import annotations

import asyncio
import logging
import os
import signal
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager

import pytest
from line_device_support import device_process, started_tcp_proxy, tcp_device
from support.group_support import MemoryDirectory
from support.ports import free_port

from gateway.proxies import TcpProxy, open_tcp_backend
from services.apps.registry import Registry, RegistryService
from services.kernel.backend import Change
from services.kernel.errors import Code, PropertyError

FAST = {
    "timeout": 1.0,
    "connect_timeout": 2.0,
    "backoff_initial": 0.05,
    "backoff_max": 0.3,
    "poll_interval": 0.05,
}


@asynccontextmanager
async def proxy_for(url: str, **options: object) -> AsyncIterator[TcpProxy]:
    async with started_tcp_proxy(url, {**FAST, **options}) as proxy:
        yield proxy


async def expect_error(code: Code, call: Awaitable[object]) -> PropertyError:
    with pytest.raises(PropertyError) as info:
        await call
    assert info.value.code == code, info.value
    return info.value


async def test_get_set_errors_and_pipelining_through_a_real_device() -> None:
    with tcp_device("--service", "sim-robot", "--name", "scout1") as (host, port):
        async with proxy_for(f"tcp://{host}:{port}") as proxy:
            await proxy.wait_connected(5)
            assert proxy.info.type == "mobile_robot"
            assert await proxy.get("location") == "(0 0 0 0 0 0)"
            assert await proxy.set("speed", "1.5") == "1.5"
            values = await asyncio.gather(*(proxy.get("speed") for _ in range(100)))
            assert values == ["1.5"] * 100
            assert "location" in await proxy.properties()
            await expect_error(Code.NOT_FOUND, proxy.get("nosuch"))
            await expect_error(Code.FAILED_PRECONDITION, proxy.set("location", "(1 2)"))
            await expect_error(Code.INVALID_ARGUMENT, proxy.get("bad path"))


async def test_listeners_share_one_device_listen_and_see_moves() -> None:
    with tcp_device("--service", "sim-robot", "--option", "tick_hz=50") as (host, port):
        async with proxy_for(f"tcp://{host}:{port}") as proxy:
            await proxy.wait_connected(5)
            first: asyncio.Queue[Change] = asyncio.Queue()
            second: asyncio.Queue[Change] = asyncio.Queue()
            sub1 = await proxy.listen("location.x", first.put_nowait)
            sub2 = await proxy.listen("location.x", second.put_nowait)
            assert proxy.shared_listens.paths() == ["location.x"]
            await proxy.set("speed", "5")
            await proxy.set("behaviors.moveto", "<marker><location>(1 0)</location></marker>")
            a = await asyncio.wait_for(first.get(), 5)
            b = await asyncio.wait_for(second.get(), 5)
            assert float(a.value) > 0 and float(b.value) > 0 and not a.gap
            await sub1.close()
            assert proxy.shared_listens.paths() == ["location.x"]
            await sub2.close()
            assert proxy.shared_listens.paths() == []


async def test_lost_device_gives_unavailable_then_reconnects_and_listeners_get_a_gap() -> None:
    port = free_port()
    with device_process("--service", "sim-robot", "--tcp", f"127.0.0.1:{port}") as (proc, _):
        async with proxy_for(f"tcp://127.0.0.1:{port}") as proxy:
            await proxy.wait_connected(5)
            changes: asyncio.Queue[Change] = asyncio.Queue()
            await proxy.listen("speed", changes.put_nowait)
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(5)
            with pytest.raises(PropertyError) as info:
                for _ in range(100):
                    await proxy.get("speed")
                    await asyncio.sleep(0.02)
            assert info.value.code == Code.UNAVAILABLE
            await expect_error(Code.UNAVAILABLE, proxy.get("speed"))
            with device_process(
                "--service", "sim-robot", "--tcp", f"127.0.0.1:{port}", "--option", "speed=2"
            ):
                change = await asyncio.wait_for(changes.get(), 10)
                assert change == Change("speed", "2", gap=True)
                assert await proxy.get("speed") == "2"
                await proxy.set("speed", "3")
                assert await asyncio.wait_for(changes.get(), 5) == Change("speed", "3")


async def test_device_that_cannot_push_is_polled_and_only_changes_are_forwarded() -> None:
    with tcp_device("--service", "sim-robot", "--no-push") as (host, port):
        async with proxy_for(f"tcp://{host}:{port}") as proxy:
            await proxy.wait_connected(5)
            assert proxy.hello is not None and not proxy.hello.push
            changes: asyncio.Queue[Change] = asyncio.Queue()
            await proxy.listen("speed", changes.put_nowait)
            await asyncio.sleep(0.3)  # several polls of an unchanged value
            assert changes.empty()
            await proxy.set("speed", "1.25")
            assert await asyncio.wait_for(changes.get(), 5) == Change("speed", "1.25")
            await asyncio.sleep(0.3)
            assert changes.empty()


# -- misbehaving devices, written here with raw sockets ---------------------------------------------

Script = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


@asynccontextmanager
async def fake_device(script: Script) -> AsyncIterator[str]:
    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(b"HELLO 1 name=fake type=thing push=1\n")
        try:
            await script(reader, writer)
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        finally:
            writer.close()

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    host, port = server.sockets[0].getsockname()[:2]
    try:
        yield f"tcp://{host}:{port}"
    finally:
        server.close()


async def requests(reader: asyncio.StreamReader) -> AsyncIterator[tuple[str, str]]:
    """(tag, rest) of each request line."""
    while True:
        try:
            line = (await reader.readuntil(b"\n")).decode().rstrip("\n")
        except (asyncio.IncompleteReadError, ConnectionError):
            return
        tag, _, rest = line.partition(" ")
        yield tag, rest


async def test_garbage_and_over_long_replies_fail_only_their_call() -> None:
    async def script(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        async for tag, rest in requests(reader):
            if rest == "GET garbage":
                writer.write(f"{tag} \x01\x02 blah\n".encode() + b"\xff\xfe\n")
            elif rest == "GET long":
                writer.write(f"{tag} OK ".encode() + b"x" * 5000 + b"\n")
            else:
                writer.write(f"{tag} OK fine\n".encode())

    async with fake_device(script) as url, proxy_for(url) as proxy:
        await proxy.wait_connected(5)
        results = await asyncio.gather(
            proxy.get("garbage"),
            proxy.get("ok1"),
            proxy.get("long"),
            proxy.get("ok2"),
            return_exceptions=True,
        )
        assert isinstance(results[0], PropertyError) and results[0].code == Code.DATA_LOSS
        assert "malformed reply" in results[0].message
        assert isinstance(results[2], PropertyError) and results[2].code == Code.RESOURCE_EXHAUSTED
        assert results[1] == results[3] == "fine"
        assert await proxy.get("after") == "fine"


async def test_slow_device_and_half_line_then_silence_give_deadline_exceeded_for_that_call() -> None:
    async def script(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        async for tag, rest in requests(reader):
            if rest == "GET slow":
                continue  # never answers
            if rest == "GET half":
                writer.write(f"{tag} OK hal".encode())  # then silence
                continue
            writer.write(f"{tag} OK fine\n".encode())

    async with fake_device(script) as url, proxy_for(url, timeout=0.3) as proxy:
        await proxy.wait_connected(5)
        slow = asyncio.ensure_future(proxy.get("slow"))
        assert await proxy.get("quick") == "fine"
        await expect_error(Code.DEADLINE_EXCEEDED, slow)
        await expect_error(Code.DEADLINE_EXCEEDED, proxy.get("half"))
        assert await proxy.get("quick") == "fine"  # the half line was dropped, not glued to this reply


async def test_disconnect_mid_reply_fails_outstanding_calls_with_unavailable() -> None:
    async def script(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        async for tag, rest in requests(reader):
            if rest == "GET cut":
                writer.write(f"{tag} OK par".encode())
                await writer.drain()
                writer.transport.abort()
                return
            writer.write(f"{tag} OK fine\n".encode())

    async with fake_device(script) as url, proxy_for(url, backoff_initial=5, backoff_max=5) as proxy:
        await proxy.wait_connected(5)
        error = await expect_error(Code.UNAVAILABLE, proxy.get("cut"))
        assert "closed the connection" in error.message or "lost" in error.message
        await expect_error(Code.UNAVAILABLE, proxy.get("next"))


async def test_device_without_greeting_is_asked_and_bad_urls_are_refused() -> None:
    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        async for tag, _rest in requests(reader):
            if tag == "HELLO":  # the proxy asks untagged
                writer.write(b"HELLO 1 name=quiet\n")
            else:
                writer.write(f"{tag} OK q\n".encode())

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with proxy_for(f"tcp://127.0.0.1:{port}", connect_timeout=1.0) as proxy:
            await proxy.wait_connected(5)
            assert proxy.hello is not None and proxy.hello.name == "quiet"
            assert await proxy.get("x") == "q"
    finally:
        server.close()
    for url in (
        "tcp://nohost",
        "tcp://h:99999",
        "tcp://h:1/path",
        "tcp://h:1?timeout=abc",
        "tcp://h:1?bogus=1",
    ):
        with pytest.raises(PropertyError) as info:
            open_tcp_backend("dev", url, {})
        assert info.value.code == Code.INVALID_ARGUMENT


async def test_unreachable_device_is_unavailable_at_once() -> None:
    async with proxy_for(f"tcp://127.0.0.1:{free_port()}") as proxy:
        error = await expect_error(Code.UNAVAILABLE, proxy.get("x"))
        assert "not connected" in error.message


async def test_waiting_for_a_device_whose_host_refuses_ends_before_the_wait_does() -> None:
    """Nothing listens at the address: the waiter hears "connection refused", not a bare timeout."""
    async with proxy_for(f"tcp://127.0.0.1:{free_port()}") as proxy:
        with pytest.raises(PropertyError) as info:
            await proxy.wait_connected(600)
        assert info.value.code == Code.UNAVAILABLE
        assert "connection refused for" in info.value.message and "after 600 s" not in info.value.message
        # While it goes on refusing, the next waiter is answered at once too.
        with pytest.raises(PropertyError, match="connection refused for"):
            await proxy.wait_connected(600)


def unlisten_failures(caplog: pytest.LogCaptureFixture) -> list[tuple[int, str]]:
    return [(r.levelno, r.getMessage()) for r in caplog.records if "UNLISTEN" in r.getMessage()]


async def test_unlisten_failing_on_a_live_connection_is_logged_but_not_at_shutdown(
    caplog: pytest.LogCaptureFixture,
) -> None:
    async def script(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        async for tag, rest in requests(reader):
            if rest.startswith("UNLISTEN"):
                writer.write(f"{tag} ERR 13 the device lost track\n".encode())
            else:
                writer.write(f"{tag} OK 1\n".encode())

    caplog.set_level(logging.DEBUG, logger="gateway.proxies.line_proxy")
    async with fake_device(script) as url, proxy_for(url) as proxy:
        await proxy.wait_connected(5)
        sub = await proxy.listen("a", lambda change: None)
        await sub.close()
        assert unlisten_failures(caplog) == [
            (logging.INFO, f"device dev at {url}: UNLISTEN a failed: the device lost track")
        ]
        caplog.clear()
        sub = await proxy.listen("b", lambda change: None)
        await proxy.aclose()  # the gateway closes its proxies before the last listeners let go
        await sub.close()
    failures = unlisten_failures(caplog)
    assert failures and all(level == logging.DEBUG for level, _ in failures), failures


# -- liveness checks ----------------------------------------------------------------------------


def answering(lines: list[str]) -> Script:
    """A device script that records every request line and answers PING with PONG, the rest with OK."""

    async def script(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        async for tag, rest in requests(reader):
            lines.append(rest)
            writer.write(f"{tag} PONG\n".encode() if rest.startswith("PING") else f"{tag} OK 1\n".encode())

    return script


async def test_check_of_a_live_device_sends_no_get_and_a_killed_one_fails() -> None:
    lines: list[str] = []
    async with fake_device(answering(lines)) as url, proxy_for(url) as proxy:
        await proxy.wait_connected(5)
        await proxy.check()  # it greeted a moment ago: alive without asking
        assert lines == []
        proxy.heard_within = 0.0  # silent for too long: a PING has to come back
        await proxy.check()
        assert lines == ["PING"]
    port = free_port()
    with device_process("--service", "sim-robot", "--tcp", f"127.0.0.1:{port}") as (proc, _):
        async with proxy_for(f"tcp://127.0.0.1:{port}") as proxy:
            await proxy.wait_connected(5)
            await proxy.check()
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(5)
            with pytest.raises(PropertyError) as info:
                for _ in range(100):
                    await proxy.check()
                    await asyncio.sleep(0.02)
            assert info.value.code == Code.UNAVAILABLE


async def test_registry_checks_a_proxied_device_without_listing_its_properties() -> None:
    lines: list[str] = []
    directory = MemoryDirectory()
    registry = Registry(directory=directory, period=0, timeout=1.0, misses=1, static=["dev"])
    try:
        await directory.add("registry", RegistryService(registry))
        async with fake_device(answering(lines)) as url:
            proxy = open_tcp_backend("dev", url, FAST)
            assert isinstance(proxy, TcpProxy)
            await directory.add("dev", proxy)
            await proxy.wait_connected(5)
            for _ in range(3):
                await registry.check_all()
            assert registry.state_of("dev") == "up"
            assert not [line for line in lines if line.startswith("GET properties")], lines
            await proxy.aclose()
        await registry.check_all()
        assert registry.state_of("dev") == "down"
    finally:
        await directory.aclose()
