"""Loopback ports for tests that must name one before anything listens on it."""

from __future__ import annotations

import contextlib
import socket


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
