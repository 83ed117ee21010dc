"""Devices that dial in to the gateway's line listener, served through the ordinary line-protocol proxy.

See :mod:`gateway.fronts.line.listener`: a peer whose first line is a greeting is
a device registering itself; its connection is handed to an
:class:`InboundProxy` served under the greeting's name.
"""

from __future__ import annotations

import asyncio

from gateway.proxies.line_proxy import LineProxy, ProxyOptions
from services.kernel.errors import AlreadyExists

__all__ = ["INBOUND_OPTIONS", "INBOUND_SCHEME", "InboundProxy"]

#: URL scheme of a device that dialled in (``tcp-in://HOST:PORT``, its end of the
#: connection); such a URL names where the device is, it cannot be dialled back.
INBOUND_SCHEME = "tcp-in"
#: How a dialled-in device's proxy behaves. It never dials: "connecting" is waiting
#: for the device to dial in again, so that wait is long and the pause after it short.
INBOUND_OPTIONS = ProxyOptions(connect_timeout=3600.0, backoff_initial=0.05, backoff_max=1.0)


class InboundProxy(LineProxy):
    """A device that dialled in to the line listener, as a Backend.

    It is a :class:`~gateway.proxies.line_proxy.LineProxy` whose streams are
    handed to it (:meth:`offer`) instead of opened: the first when the device
    greets, the next when the same device dials in again after a drop.
    """

    dials = False
    transport = "dial-in"

    def __init__(self, name: str, url: str, options: ProxyOptions = INBOUND_OPTIONS) -> None:
        super().__init__(name, url, options)
        self._streams: asyncio.Queue[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = asyncio.Queue(1)

    def offer(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, url: str) -> None:
        """Take up a new connection from the device (its greeting is the first thing ``reader`` gives).

        Raises AlreadyExists while the device is connected or another connection waits.
        """
        if self.connected or self._streams.full() or self._closing:
            raise AlreadyExists(f"the name {self.name!r} is taken (by the device at {self.url})")
        self._streams.put_nowait((reader, writer))
        self.url = url
        self.info.url = url

    async def open_stream(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        return await self._streams.get()

    async def aclose(self) -> None:
        await super().aclose()
        while not self._streams.empty():
            _, writer = self._streams.get_nowait()
            writer.close()
