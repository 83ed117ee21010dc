"""Loopback ports for tests that must name one before anything listens on it."""

from __future__ import annotations

import asyncio
import contextlib
import random
import socket
from collections.abc import AsyncIterator
from pathlib import Path


def free_port() -> int:
    """A loopback TCP port nobody listens on now (bound, then released).

    Another process could take it before the test uses it; the tests that need
    a fixed port (a restart on the same port, an address that refuses) accept
    that small risk.
    """
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
    return port


def free_ports(count: int) -> list[int]:
    """``count`` different loopback TCP ports nobody listens on now: all are held at once while
    they are picked, so the kernel cannot hand out one port twice (``free_port`` twice can)."""
    with contextlib.ExitStack() as stack:
        socks = [stack.enter_context(socket.socket()) for _ in range(count)]
        for sock in socks:
            sock.bind(("127.0.0.1", 0))
        return [int(sock.getsockname()[1]) for sock in socks]


#: Where Linux says its ephemeral ports are, and what it uses when the file is absent.
_EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
_EPHEMERAL_DEFAULT = (32768, 60999)
#: The low end of the ports picked below the ephemeral range (above the well-known services).
_STABLE_LOW = 10000


def stable_ports(count: int) -> list[int]:
    """``count`` free loopback ports below the kernel's ephemeral range.

    A port from :func:`free_port` may be handed by the kernel to any outgoing connection once it
    is released, for instance to a client that keeps trying to reach a stopped server, and the
    server then cannot be started again on it. Ports below the ephemeral range are never handed
    out that way: a server stopped and started again (etcd, in the shared-store tests) finds
    them free unless another test picked the same ones.
    """
    try:
        low, _ = (int(n) for n in _EPHEMERAL_RANGE.read_text().split())
    except (OSError, ValueError):
        low = _EPHEMERAL_DEFAULT[0]
    if low - _STABLE_LOW < 16 * count:
        return free_ports(count)  # no room below the range on this machine
    with contextlib.ExitStack() as stack:
        picked: list[int] = []
        for port in random.sample(range(_STABLE_LOW, low), min(low - _STABLE_LOW, 64 * count)):
            sock = stack.enter_context(socket.socket())
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
            picked.append(port)
            if len(picked) == count:
                return picked
    return free_ports(count)


@contextlib.asynccontextmanager
async def silent_port() -> AsyncIterator[int]:
    """A loopback port whose listener accepts connections and never says a byte (a peer that hangs:
    no HTTP/2, no greeting); the connections and the listener are closed when the block ends."""
    held: list[asyncio.StreamWriter] = []

    async def hold(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        held.append(writer)

    server = await asyncio.start_server(hold, "127.0.0.1", 0)
    try:
        yield server.sockets[0].getsockname()[1]
    finally:
        for writer in held:
            writer.close()
        server.close()
        await server.wait_closed()
