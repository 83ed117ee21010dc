"""The proxy for ``tcp://host:port`` line-protocol devices."""

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from typing import Any
from urllib.parse import urlsplit

from gateway.proxies.connection import LineConnection
from gateway.proxies.line_proxy import LineProxy, ProxyOptions
from services.kernel.backend import Backend
from services.kernel.errors import InvalidArgument


class TcpProxy(LineProxy):
    """A raw-TCP Property Service (a Wi-Fi board, ``python -m services.device --tcp``) as a Backend."""

    def __init__(self, name: str, url: str, host: str, port: int, options: ProxyOptions) -> None:
        super().__init__(name, url, options)
        self.host = host
        self.port = port

    async def attach(self, connection: LineConnection) -> None:
        # The connection is the socket's protocol: each read is decoded where it arrives.
        await asyncio.get_running_loop().create_connection(lambda: connection, self.host, self.port)


def open_tcp_backend(name: str, url: str, options: Mapping[str, Any]) -> Backend:
    """The factory for ``tcp://HOST:PORT[?option=value...]`` (not started)."""
    parts = urlsplit(url)
    try:
        port = parts.port
    except ValueError:
        port = None
    if parts.scheme != "tcp" or not parts.hostname or port is None or parts.path not in ("", "/"):
        raise InvalidArgument(f"service {name!r}: bad URL {url!r}; expected tcp://HOST:PORT")
    return TcpProxy(name, url, parts.hostname, port, ProxyOptions.parse(url, options))
