"""Loopback ports for tests that must name one before anything listens on it."""

from __future__ import annotations

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
