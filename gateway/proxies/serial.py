"""The proxy for ``serial:///dev/ttyUSB0?baudrate=115200`` line-protocol devices."""

from __future__ import annotations

import asyncio
from collections.abc import Mapping
from typing import Any
from urllib.parse import unquote, urlsplit

from gateway.options import url_options
from gateway.proxies.line_proxy import LineProxy, ProxyOptions
from services.device.transports import serial_streams
from services.kernel.backend import Backend
from services.kernel.errors import InvalidArgument

_SERIAL_KEYS = frozenset({"baudrate"})


class SerialProxy(LineProxy):
    """A Property Service on a serial line (a microcontroller on RS-232 or USB) as a Backend.

    Opening a port tells the device nothing, so the proxy asks for the
    greeting with ``HELLO`` first. When the port fails (adapter unplugged)
    the proxy reopens it with backoff, like a lost TCP connection.
    """

    ask_hello_first = True
    serial_line = True
    transport = "serial"

    def __init__(self, name: str, url: str, port: str, baudrate: int, options: ProxyOptions) -> None:
        super().__init__(name, url, options)
        self.port = port
        self.baudrate = baudrate

    async def open_stream(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        import serial

        try:
            return await serial_streams(self.port, self.baudrate, 65536)
        except (serial.SerialException, ValueError) as exc:
            raise OSError(f"cannot open {self.port}: {exc}") from exc


def open_serial_backend(name: str, url: str, options: Mapping[str, Any]) -> Backend:
    """The factory for ``serial:///dev/PORT?baudrate=N[&option=value...]`` (not started)."""
    parts = urlsplit(url)
    port = unquote(parts.path)
    if parts.scheme != "serial" or parts.netloc or not port.startswith("/"):
        raise InvalidArgument(
            f"service {name!r}: bad URL {url!r}; expected serial:///dev/ttyUSB0?baudrate=115200"
        )
    raw_baud = url_options(url, options).get("baudrate", 115200)
    try:
        baudrate = int(raw_baud)
    except (TypeError, ValueError):
        baudrate = 0
    if baudrate <= 0:
        raise InvalidArgument(f"service {name!r}: bad baudrate {raw_baud!r} in {url!r}")
    return SerialProxy(name, url, port, baudrate, ProxyOptions.parse(url, options, skip=_SERIAL_KEYS))
