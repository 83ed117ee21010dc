"""The serial proxy on real pseudo-terminals: a real device process, and a misbehaving one."""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import pytest
from line_device_support import LineClient, device_process, pty_client, pty_pair

from gateway.proxies import SerialProxy, open_serial_backend
from services.kernel.backend import Change
from services.kernel.errors import Code, PropertyError
from services.kernel.line_protocol import crc8

FAST = {"timeout": 1.0, "connect_timeout": 2.0, "backoff_initial": 0.05, "backoff_max": 0.3}


@asynccontextmanager
async def serial_proxy(path: str, **options: object) -> AsyncIterator[SerialProxy]:
    proxy = open_serial_backend("dev", f"serial://{path}?baudrate=115200", {**FAST, **options})
    assert isinstance(proxy, SerialProxy)
    await proxy.start()
    try:
        yield proxy
    finally:
        await proxy.aclose()


@asynccontextmanager
async def null_modem(a: int, b: int) -> AsyncIterator[None]:
    """Copy bytes between two pty masters, as a crossed serial cable would."""
    loop = asyncio.get_running_loop()

    def pump(src: int, dst: int) -> None:
        with contextlib.suppress(OSError):  # the far side is not open yet
            os.write(dst, os.read(src, 4096))

    loop.add_reader(a, pump, a, b)
    loop.add_reader(b, pump, b, a)
    try:
        yield
    finally:
        loop.remove_reader(a)
        loop.remove_reader(b)


async def test_a_device_process_on_a_serial_line_through_the_proxy() -> None:
    with (
        pty_pair() as (dev_master, dev_path),
        pty_pair() as (gw_master, gw_path),
        device_process("--service", "sim-robot", "--name", "tty-robot", "--serial", dev_path),
    ):
        if True:
            async with null_modem(dev_master, gw_master), serial_proxy(gw_path) as proxy:
                await proxy.wait_connected(5)
                assert proxy.hello is not None and proxy.hello.name == "tty-robot"
                assert await proxy.get("speed") == "0.5"
                changes: asyncio.Queue[Change] = asyncio.Queue()
                await proxy.listen("speed", changes.put_nowait)
                assert await proxy.set("speed", "1") == "1"
                assert await asyncio.wait_for(changes.get(), 5) == Change("speed", "1")
                values = await asyncio.gather(*(proxy.get("location.x") for _ in range(30)))
                assert values == ["0"] * 30
                with pytest.raises(PropertyError) as info:
                    await proxy.get("nosuch")
                assert info.value.code == Code.NOT_FOUND


async def fake_serial_device(client: LineClient, *, checksum: bool) -> None:
    """Answers on the pty master: garbage for 'garbage', nothing for 'slow', checksummed lines when asked."""
    while True:
        try:
            line = await client.line(30)
        except (AssertionError, TimeoutError, OSError):
            return
        if line.startswith("$"):
            assert int(line[-2:], 16) == crc8(line[1:-3].encode())
            line = line[1:-3]
        tag, _, rest = line.partition(" ")
        if tag == "HELLO":
            # It answers pipelined requests and says so (one that says nothing gets one at a time).
            reply = "HELLO 1 name=mcu type=sensor push=0 maxline=128 inflight=3"
        elif rest == "GET garbage":
            await client.send(b"\x01\x02~~ noise\n")
            continue
        elif rest == "GET slow":
            continue
        elif rest.startswith("GET"):
            reply = f"{tag} OK {rest[4:]}-value"
        else:
            reply = f"{tag} ERR 12 not here"
        body = reply.encode()
        await client.send(b"$" + body + b"*%02X\n" % crc8(body) if checksum else body + b"\n")


@pytest.mark.parametrize("checksum", [False, True])
async def test_misbehaving_serial_device_affects_only_the_call_concerned(checksum: bool) -> None:
    with pty_pair() as (master, path):
        client = await pty_client(master)
        device = asyncio.ensure_future(fake_serial_device(client, checksum=checksum))
        try:
            async with serial_proxy(path, timeout=0.4, checksum=checksum) as proxy:
                await proxy.wait_connected(5)
                assert proxy.hello is not None and proxy.hello.max_line == 128
                results = await asyncio.gather(
                    proxy.get("garbage"), proxy.get("slow"), proxy.get("data"), return_exceptions=True
                )
                assert isinstance(results[0], PropertyError) and results[0].code == Code.DEADLINE_EXCEEDED
                assert isinstance(results[1], PropertyError) and results[1].code == Code.DEADLINE_EXCEEDED
                assert results[2] == "data-value"
                with pytest.raises(PropertyError) as info:
                    await proxy.set("x", "v" * 200)  # longer than the device's maxline=128
                assert info.value.code == Code.RESOURCE_EXHAUSTED
                with pytest.raises(PropertyError) as info:
                    await proxy.set("x", "1")
                assert info.value.code == Code.UNIMPLEMENTED
                assert await proxy.get("temp") == "temp-value"
        finally:
            device.cancel()
            await asyncio.gather(device, return_exceptions=True)
            await client.close()


async def test_missing_serial_port_is_unavailable_and_bad_urls_are_refused() -> None:
    async with serial_proxy("/dev/does-not-exist") as proxy:
        with pytest.raises(PropertyError) as info:
            await proxy.get("x")
        assert info.value.code == Code.UNAVAILABLE
    for url in ("serial://host/dev/x", "serial:///dev/x?baudrate=fast", "serial:relative"):
        with pytest.raises(PropertyError) as info:
            open_serial_backend("dev", url, {})
        assert info.value.code == Code.INVALID_ARGUMENT
