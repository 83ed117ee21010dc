"""Serve any Property Service over the line protocol, on a TCP port or a serial port.

This is the device side of docs/device-spec.md in Python: it stands in for a
microcontroller in tests and demos, and lets any :class:`services.kernel.backend.Backend`
(a simulated robot, a sensor, a whole gateway's router) be reached by anything
that speaks lines of text. Every connection gets its own
:class:`~services.device.session.DeviceSession`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import ssl
from collections.abc import Callable
from dataclasses import replace

from services.device.alternates import ALTERNATES_FIELD, GatewayAddresses
from services.device.session import CALL_TIMEOUT, KEEPALIVE_TIMEOUT, READ_SIZE, DeviceSession
from services.device.transports import open_pty, open_serial, pipe_streams
from services.kernel.backend import Backend
from services.kernel.errors import Code
from services.kernel.line_protocol import MAX_LINE, ErrorReply, Hello, encode

__all__ = ["DeviceServer"]

log = logging.getLogger(__name__)

#: Seconds of silence from the gateway a device dialled before it sends a keep-alive ``PING``: a
#: gateway's own PINGs and liveness checks come every few seconds, so a gateway silent for longer
#: is asked, and one that stays silent (frozen) is left for another within about 5 s.
DIAL_KEEPALIVE = 2.0
#: Seconds ``aclose`` waits for a listening socket to close.
_CLOSE_WAIT = 5.0


class DeviceServer:
    """Serves one backend to any number of line-protocol connections (TCP clients, a serial port)."""

    #: The level of the "connected" and "disconnected" lines of each TCP connection.
    connection_log_level = logging.INFO

    def __init__(
        self,
        backend: Backend,
        *,
        name: str,
        type: str | None = None,
        push: bool = True,
        checksum: bool = False,
        max_line: int = MAX_LINE,
        call_timeout: float = CALL_TIMEOUT,
        max_connections: int = 64,
        secret: str = "",
        inflight: int | None = None,
        rxbuf: int | None = None,
        keepalive: float = DIAL_KEEPALIVE,
        keepalive_timeout: float = KEEPALIVE_TIMEOUT,
    ) -> None:
        """``secret``: carried in the greeting (``secret=...``) for a gateway that configures this
        device by name; it proves the device is the one configured (docs/line-protocol.md §5).
        ``inflight`` and ``rxbuf``: the flow control the greeting states (docs/device-spec.md §5); with
        ``inflight`` a connection also takes at most that many requests at once. ``keepalive`` and
        ``keepalive_timeout``: on a connection the device dialled, a gateway silent for
        ``keepalive`` seconds is sent ``PING`` and left for the next when it does not answer within
        ``keepalive_timeout`` (a frozen gateway keeps the TCP connection open); 0: never."""
        self.backend = backend
        self.greeting = Hello(
            name=name,
            type=type or backend.info.type,
            push=push,
            max_line=max_line,
            inflight=inflight,
            rxbuf=rxbuf,
        )
        #: The greeting on a connection this device dialled: only there does it carry the secret.
        self.dial_greeting = replace(self.greeting, extra={"secret": secret}) if secret else self.greeting
        self.checksum = checksum
        self.call_timeout = call_timeout
        self.keepalive = keepalive
        self.keepalive_timeout = keepalive_timeout
        self.max_connections = max_connections
        self._sessions: set[asyncio.StreamWriter] = set()
        self._servers: list[asyncio.Server] = []
        self._serial_tasks: list[asyncio.Task[None]] = []
        self._pty_fds: list[int] = []

    async def serve_stream(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, peer: str = ""
    ) -> None:
        """Serve one connection until it closes."""
        await self.session(reader, writer, peer).run()

    def session(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        peer: str,
        backend: Backend | None = None,
        *,
        greeting: Hello | None = None,
        on_greeting: Callable[[Hello], None] | None = None,
        keepalive: float = 0.0,
    ) -> DeviceSession:
        """The protocol session of one connection, with this server's greeting, checksum and timeout;
        ``backend`` serves this connection instead of the server's (a per-connection view of it),
        ``greeting`` replaces the server's; ``on_greeting`` hears the peer's greeting; ``keepalive``:
        see :class:`DeviceSession` (its timeout is this server's)."""
        return DeviceSession(
            backend if backend is not None else self.backend,
            reader,
            writer,
            greeting=greeting or self.greeting,
            checksum=self.checksum,
            call_timeout=self.call_timeout,
            peer=peer,
            on_greeting=on_greeting,
            keepalive=keepalive,
            keepalive_timeout=self.keepalive_timeout,
        )

    async def _on_tcp(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if len(self._sessions) >= self.max_connections:
            writer.write(encode(ErrorReply(int(Code.RESOURCE_EXHAUSTED), "too many connections; try later")))
            with contextlib.suppress(ConnectionError):
                await writer.drain()
            writer.close()
            return
        self._sessions.add(writer)
        host, port = tuple(writer.get_extra_info("peername") or ("?", "?"))[:2]
        peer = f"{host}:{port}"
        log.log(self.connection_log_level, "%s: connected", peer)
        try:
            await self.serve_stream(reader, writer, peer)
        finally:
            self._sessions.discard(writer)
            log.log(self.connection_log_level, "%s: disconnected", peer)

    def tcp_protocol(self) -> asyncio.StreamReaderProtocol:
        """The protocol of one accepted TCP connection, served as :meth:`serve_tcp` serves each (for
        a listener that accepts connections itself)."""
        reader = asyncio.StreamReader(limit=READ_SIZE)
        return asyncio.StreamReaderProtocol(reader, self._on_tcp)

    async def serve_tcp(
        self, host: str, port: int, *, ssl_context: ssl.SSLContext | None = None
    ) -> tuple[str, int]:
        """Listen on ``host:port`` (0 picks a free port), over TLS with ``ssl_context``; the bound address."""
        server = await asyncio.start_server(self._on_tcp, host, port, limit=READ_SIZE, ssl=ssl_context)
        self._servers.append(server)
        bound = server.sockets[0].getsockname()
        return str(bound[0]), int(bound[1])

    async def dial(
        self, host: str, port: int, *, retry_initial: float = 0.2, retry_max: float = 10.0
    ) -> None:
        """Dial ``host:port`` (a gateway's line listener) and serve that connection; dial again when it ends.

        The greeting, sent first as on every connection, registers the device
        there. Runs until cancelled. A gateway silent for ``keepalive`` seconds
        is sent ``PING``; one that does not answer (frozen: its TCP connection
        stays open) is left as if it had closed the connection. A gateway of a cluster names the other
        gateways in its greeting (``alternates=``): when the connection ends or
        cannot be made, the next of them is dialled, in turn
        (:class:`~services.device.alternates.GatewayAddresses`). The pause before a
        new round of attempts doubles from ``retry_initial`` up to ``retry_max``
        seconds while dialling fails or the connection is refused at once: a
        round is one attempt at every address known, also when each gateway
        greets (naming the others) and then refuses the name.
        """
        gateways = GatewayAddresses((host, port))
        pause = retry_initial
        loop = asyncio.get_running_loop()
        while True:
            if gateways.pause_due():
                await asyncio.sleep(pause)
                pause = min(pause * 2, retry_max)
                gateways.rested()
            (host, port), _ = gateways.take()
            began = loop.time()
            try:
                reader, writer = await asyncio.open_connection(host, port, limit=READ_SIZE)
            except OSError as exc:
                log.warning("cannot reach %s:%d: %s", host, port, exc)
                continue
            log.info("connected to %s:%d", host, port)
            self._sessions.add(writer)
            here = (host, port)

            def greeted(hello: Hello, here: tuple[str, int] = here) -> None:
                gateways.connected(here, hello.extra.get(ALTERNATES_FIELD, ""))

            try:
                session = self.session(
                    reader,
                    writer,
                    f"{host}:{port}",
                    greeting=self.dial_greeting,
                    on_greeting=greeted,
                    keepalive=self.keepalive,
                )
                await session.run()
            finally:
                self._sessions.discard(writer)
            log.warning("connection to %s:%d ended", host, port)
            if loop.time() - began > retry_max:
                pause = retry_initial  # it was up for a while: a fresh drop, not a refusal
                gateways.rested()  # the next addresses at once, without a pause

    async def serve_serial(self, port: str, baudrate: int = 115200, *, reopen_delay: float = 1.0) -> None:
        """Open the serial ``port`` (OSError if it cannot be opened) and serve it in the background.

        When the port fails later (a USB adapter unplugged), it is reopened
        every ``reopen_delay`` seconds.
        """
        streams = await open_serial(port, baudrate)
        task = asyncio.create_task(self._serial_loop(port, baudrate, reopen_delay, streams))
        self._serial_tasks.append(task)

    async def _serial_loop(
        self,
        port: str,
        baudrate: int,
        reopen_delay: float,
        streams: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None,
    ) -> None:
        while True:
            if streams is None:
                try:
                    streams = await open_serial(port, baudrate)
                except OSError as exc:
                    log.warning("%s", exc)
            if streams is not None:
                log.info("%s: serving at %d baud", port, baudrate)
                await self.serve_stream(*streams, peer=port)
                log.info("%s: serial port closed", port)
                streams = None
            await asyncio.sleep(reopen_delay)

    def serve_pty(self, *, restart_delay: float = 0.5) -> str:
        """Create a pseudo-terminal, serve its master side in the background; return the other end's path.

        That path (``/dev/pts/N``) is the serial port a client opens. The
        server keeps it open itself, in raw mode, so that the line stays up
        (and never echoes) while no client has it open, as a real serial
        line does when nobody listens. A session that ends is started again
        after ``restart_delay`` seconds.
        """
        master, slave, path = open_pty()
        self._pty_fds += [master, slave]
        self._serial_tasks.append(asyncio.create_task(self._pty_loop(master, path, restart_delay)))
        return path

    async def _pty_loop(self, master: int, path: str, restart_delay: float) -> None:
        while True:
            reader, writer, read_transport = await pipe_streams(master)
            try:
                await self.serve_stream(reader, writer, peer=path)
            finally:
                read_transport.close()
                writer.close()
            log.info("%s: session ended; serving the line again", path)
            await asyncio.sleep(restart_delay)

    async def aclose(self) -> None:
        """Stop listening and end every session. Idempotent."""
        for server in self._servers:
            server.close()
        # Closing a connection ends its session the ordinary way (the read sees EOF).
        for writer in list(self._sessions):
            writer.close()
        for task in self._serial_tasks:
            task.cancel()
        await asyncio.gather(*self._serial_tasks, return_exceptions=True)
        for server in self._servers:
            try:
                await asyncio.wait_for(server.wait_closed(), _CLOSE_WAIT)
            except TimeoutError:
                log.warning("a listening socket did not close within %g s", _CLOSE_WAIT)
        self._servers.clear()
        self._serial_tasks.clear()
        fds, self._pty_fds = self._pty_fds, []
        for fd in fds:
            os.close(fd)
