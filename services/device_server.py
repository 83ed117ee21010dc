"""Serve any Property Service over the line protocol, on a TCP port or a serial port.

This is the device side of docs/line-protocol.md in Python: it stands in for a
microcontroller in tests and demos, and lets any :class:`services.backend.Backend`
(a simulated robot, a sensor, a whole gateway's router) be reached by anything
that speaks lines of text::

    python -m services.device_server --service sim-robot --tcp 127.0.0.1:7001
    python -m services.device_server --service sim-sensor --serial /dev/pts/3 --baud 115200
    python -m services.device_server --service sim-robot --name scout4 --connect 127.0.0.1:7100
    python -m services.device_server --service sim-robot --name rover2 --pty

With ``--connect`` the device dials out to a gateway's line listener and
greets; the gateway registers it under its name (docs/line-protocol.md §4).
With ``--pty`` it creates a pseudo-terminal, plays the device's end of the
cable on its master side and prints the other end's path (``serial port
/dev/pts/N``) for a ``serial://`` client to open. With ``--exit-with-parent``
it stops when its stdin reaches its end: the gateway starts its ``[[devices]]``
this way (``gateway.devices``), so they end with it even when it is killed.

Every connection gets its own :class:`DeviceSession`: requests with a tag run
concurrently (bounded), untagged requests one at a time; events for a client
that reads slowly are conflated per property in a bounded outbox, so memory
never grows with a slow reader.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import json
import logging
import os
import signal
import sys
from collections import deque
from collections.abc import Callable, Coroutine, Mapping, Sequence
from typing import Any

from services.backend import Backend, Change, Subscription
from services.eager import Started, step
from services.errors import Code, DeadlineExceeded, PropertyError, ResourceExhausted
from services.line_protocol import (
    MAX_LINE,
    BadLine,
    ErrorReply,
    Event,
    Frame,
    Get,
    Gone,
    Hello,
    HelloRequest,
    LineProtocolError,
    LineReceiver,
    Listen,
    Ok,
    Ping,
    Pong,
    Set,
    Unlisten,
    encode,
)

log = logging.getLogger(__name__)

#: Requests with a tag that one connection may have running at once; further
#: lines are not read until one finishes (backpressure instead of memory).
MAX_IN_FLIGHT = 32
#: Properties one connection may listen to; each costs one outbox slot.
MAX_SUBSCRIPTIONS = 256
#: Replies waiting to be written before the session stops reading (a client
#: that sends bad lines but never reads must not grow the outbox).
MAX_QUEUED_REPLIES = 256
#: A backend call that takes longer gets DEADLINE_EXCEEDED.
CALL_TIMEOUT = 10.0
_READ_SIZE = 65536


class _Outbox:
    """What a session still has to write: replies in order, events conflated per path."""

    def __init__(self) -> None:
        self.replies: deque[bytes] = deque()
        self.events: dict[str, Frame] = {}
        self.conflated = 0
        self.wake = asyncio.Event()
        self.room = asyncio.Event()

    def reply(self, line: bytes) -> None:
        self.replies.append(line)
        self.wake.set()

    def event(self, frame: Event | Gone) -> None:
        if frame.path in self.events:
            self.conflated += 1
            del self.events[frame.path]  # re-insert: the newest change goes last
        self.events[frame.path] = frame
        self.wake.set()

    def take(self) -> tuple[list[bytes], list[Frame]]:
        replies = list(self.replies)
        self.replies.clear()
        events = list(self.events.values())
        self.events.clear()
        self.wake.clear()
        self.room.set()
        return replies, events


class DeviceSession:
    """One line-protocol connection served by one backend."""

    def __init__(
        self,
        backend: Backend,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        *,
        greeting: Hello,
        checksum: bool = False,
        call_timeout: float = CALL_TIMEOUT,
        peer: str = "",
    ) -> None:
        self.backend = backend
        self.reader = reader
        self.writer = writer
        self.greeting = greeting
        self.checksum = checksum
        self.call_timeout = call_timeout
        self.peer = peer or str(writer.get_extra_info("peername") or "?")
        self._receiver = LineReceiver(max_line=greeting.max_line)
        self._outbox = _Outbox()
        self._subscriptions: dict[str, Subscription] = {}
        self._in_flight = asyncio.Semaphore(MAX_IN_FLIGHT)
        self._tasks: set[asyncio.Task[None]] = set()
        self._step_gets = backend.answers_inline

    # -- writing ---------------------------------------------------------

    def _encode(self, frame: Frame) -> bytes:
        return encode(frame, checksum=self.checksum or self._receiver.saw_checksum)

    def _reply(self, frame: Frame) -> None:
        try:
            line = self._encode(frame)
        except LineProtocolError as exc:
            tag = getattr(frame, "tag", None)
            line = self._encode(ErrorReply(int(exc.code), f"cannot send the reply: {exc.message}", tag))
        self._outbox.reply(line)

    async def _write_loop(self) -> None:
        try:
            while True:
                await self._outbox.wake.wait()
                replies, events = self._outbox.take()
                lines = replies
                for frame in events:
                    try:
                        lines.append(self._encode(frame))
                    except LineProtocolError as exc:
                        log.warning("%s: event not sent: %s", self.peer, exc.message)
                self.writer.write(b"".join(lines))
                await self.writer.drain()
        except (ConnectionError, OSError) as exc:
            log.info("%s: cannot write: %s", self.peer, exc)
        finally:
            self._outbox.room.set()

    # -- reading ---------------------------------------------------------

    async def run(self) -> None:
        """Greet, then serve until the peer closes the connection."""
        writer_task = asyncio.create_task(self._write_loop())
        try:
            self._reply(self.greeting)
            while True:
                try:
                    data = await self.reader.read(_READ_SIZE)
                except (ConnectionError, OSError) as exc:
                    log.info("%s: connection lost: %s", self.peer, exc)
                    break
                if not data:
                    break
                for frame in self._receiver.receive_data(data):
                    await self._dispatch(frame)
                while len(self._outbox.replies) >= MAX_QUEUED_REPLIES and not writer_task.done():
                    self._outbox.room.clear()
                    await self._outbox.room.wait()  # set by the writer when it takes replies or stops
                if writer_task.done():
                    break
        finally:
            await self._shutdown(writer_task)

    async def _shutdown(self, writer_task: asyncio.Task[None]) -> None:
        for task in list(self._tasks):
            task.cancel()
        writer_task.cancel()
        await asyncio.gather(writer_task, *self._tasks, return_exceptions=True)
        subscriptions, self._subscriptions = list(self._subscriptions.values()), {}
        for sub in subscriptions:
            with contextlib.suppress(Exception):
                await sub.close()
        with contextlib.suppress(Exception):
            self.writer.close()

    async def _dispatch(self, frame: Frame | BadLine) -> None:
        if isinstance(frame, BadLine):
            log.info("%s: bad line: %s", self.peer, frame.message)
            self._reply(ErrorReply(int(frame.code), frame.message, frame.tag))
        elif isinstance(frame, Ping):
            self._reply(Pong(frame.data, frame.tag))
        elif isinstance(frame, HelloRequest):
            self._reply(dataclasses.replace(self.greeting, tag=frame.tag))
        elif isinstance(frame, Get | Set | Listen | Unlisten):
            if frame.tag is None:
                await self._answer(frame)
                return
            started: Started[str] | None = None
            if type(frame) is Get and self._step_gets:
                # An in-process service usually answers a GET without waiting:
                # step it here and reply at once, with no task and no timer.
                try:
                    first = step(self.backend.get(frame.path, frame.params))
                except Exception as exc:
                    self._reply_failure(frame, exc)
                    return
                if not isinstance(first, Started):
                    self._reply(Ok(first, frame.tag))
                    return
                started = first
            await self._in_flight.acquire()
            task = asyncio.create_task(self._answer(frame, started))
            self._tasks.add(task)
            task.add_done_callback(self._finished)
        elif isinstance(frame, Pong | Hello):
            pass  # answer to a PING of ours / a client introducing itself: nothing to do
        else:
            word = type(frame).__name__.upper().replace("ERRORREPLY", "ERR")
            tag = getattr(frame, "tag", None)
            self._reply(ErrorReply(int(Code.INVALID_ARGUMENT), f"{word} is a reply; send a request", tag))

    def _finished(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        self._in_flight.release()

    async def _answer(
        self,
        frame: Get | Set | Listen | Unlisten,
        started: Started[str] | None = None,
    ) -> None:
        try:
            async with asyncio.timeout(self.call_timeout):
                value = await (self._call(frame) if started is None else started.rest())
        except TimeoutError:
            late = DeadlineExceeded(
                f"{frame.path}: the service did not answer within {self.call_timeout:g} s"
            )
            self._reply(ErrorReply.from_exception(late, frame.tag))
        except Exception as exc:
            self._reply_failure(frame, exc)
        else:
            self._reply(Ok(value, frame.tag))

    def _reply_failure(self, frame: Get | Set | Listen | Unlisten, exc: Exception) -> None:
        if isinstance(exc, PropertyError):
            self._reply(ErrorReply.from_exception(exc, frame.tag))
            return
        log.error("%s: service failed on %r", self.peer, frame, exc_info=exc)
        self._reply(ErrorReply(int(Code.INTERNAL), f"{frame.path}: internal error in the service", frame.tag))

    async def _call(self, frame: Get | Set | Listen | Unlisten) -> str:
        backend = self.backend
        if isinstance(frame, Get):
            return await backend.get(frame.path, frame.params)
        if isinstance(frame, Set):
            return await backend.set(frame.path, frame.value, frame.params)
        if isinstance(frame, Unlisten):
            sub = self._subscriptions.pop(frame.path, None)
            if sub is not None:
                await sub.close()
            return ""
        if not self.greeting.push:
            raise PropertyError(
                f"{frame.path}: this device cannot push events (push=0); poll with GET", Code.UNIMPLEMENTED
            )
        if frame.path not in self._subscriptions:
            if len(self._subscriptions) >= MAX_SUBSCRIPTIONS:
                raise ResourceExhausted(f"at most {MAX_SUBSCRIPTIONS} subscriptions per connection")
            sub = await backend.listen(frame.path, self._notifier(frame.path), frame.params)
            if frame.path in self._subscriptions:  # a concurrent LISTEN of the same path won
                await sub.close()
            else:
                self._subscriptions[frame.path] = sub
        return await backend.get(frame.path, frame.params)

    def _notifier(self, path: str) -> Callable[[Change], None]:
        # Events are sent under the path the client listened to: that is its key.
        def notify(change: Change) -> None:
            if path not in self._subscriptions:
                return
            if change.removed:
                self._outbox.event(Gone(path))
                self._spawn(self._subscriptions.pop(path).close())
            else:
                self._outbox.event(Event(path, change.value))

        return notify

    def _spawn(self, coro: Coroutine[Any, Any, None]) -> None:
        task = asyncio.create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)


class DeviceServer:
    """Serves one backend to any number of line-protocol connections (TCP clients, a serial port)."""

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
    ) -> None:
        self.backend = backend
        self.greeting = Hello(name=name, type=type or backend.info.type, push=push, max_line=max_line)
        self.checksum = checksum
        self.call_timeout = call_timeout
        self.max_connections = max_connections
        self._sessions: set[asyncio.StreamWriter] = set()
        self._servers: list[asyncio.Server] = []
        self._serial_tasks: list[asyncio.Task[None]] = []
        self._pty_fds: list[int] = []

    async def serve_stream(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, peer: str = ""
    ) -> None:
        """Serve one connection until it closes."""
        session = DeviceSession(
            self.backend,
            reader,
            writer,
            greeting=self.greeting,
            checksum=self.checksum,
            call_timeout=self.call_timeout,
            peer=peer,
        )
        await session.run()

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
        log.info("%s: connected", peer)
        try:
            await self.serve_stream(reader, writer, peer)
        finally:
            self._sessions.discard(writer)
            log.info("%s: disconnected", peer)

    async def serve_tcp(self, host: str, port: int) -> tuple[str, int]:
        """Listen on ``host:port`` (0 picks a free port); return the address actually bound."""
        server = await asyncio.start_server(self._on_tcp, host, port, limit=_READ_SIZE)
        self._servers.append(server)
        bound = server.sockets[0].getsockname()
        return str(bound[0]), int(bound[1])

    async def dial(
        self, host: str, port: int, *, retry_initial: float = 0.2, retry_max: float = 10.0
    ) -> None:
        """Dial ``host:port`` (a gateway's line listener) and serve that connection; dial again when it ends.

        The greeting, sent first as on every connection, registers the device
        there. Runs until cancelled; the pause between attempts doubles from
        ``retry_initial`` up to ``retry_max`` seconds while dialling fails or
        the connection is refused at once.
        """
        pause = retry_initial
        loop = asyncio.get_running_loop()
        while True:
            began = loop.time()
            try:
                reader, writer = await asyncio.open_connection(host, port, limit=_READ_SIZE)
            except OSError as exc:
                log.warning("cannot reach %s:%d: %s", host, port, exc)
            else:
                log.info("connected to %s:%d", host, port)
                self._sessions.add(writer)
                try:
                    await self.serve_stream(reader, writer, f"{host}:{port}")
                finally:
                    self._sessions.discard(writer)
                log.warning("connection to %s:%d ended", host, port)
                if loop.time() - began > retry_max:
                    pause = retry_initial  # it was up for a while: a fresh drop, not a refusal
            await asyncio.sleep(pause)
            pause = min(pause * 2, retry_max)

    async def serve_serial(self, port: str, baudrate: int = 115200, *, reopen_delay: float = 1.0) -> None:
        """Open the serial ``port`` (OSError if it cannot be opened) and serve it in the background.

        When the port fails later (a USB adapter unplugged), it is reopened
        every ``reopen_delay`` seconds.
        """
        streams = await self._open_serial(port, baudrate)
        task = asyncio.create_task(self._serial_loop(port, baudrate, reopen_delay, streams))
        self._serial_tasks.append(task)

    @staticmethod
    async def _open_serial(port: str, baudrate: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        import serial
        import serial_asyncio_fast

        try:
            opened: tuple[asyncio.StreamReader, asyncio.StreamWriter]
            opened = await serial_asyncio_fast.open_serial_connection(
                url=port, baudrate=baudrate, limit=_READ_SIZE
            )
        except (serial.SerialException, ValueError) as exc:
            raise OSError(f"cannot open serial port {port}: {exc}") from exc
        return opened

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
                    streams = await self._open_serial(port, baudrate)
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
        import tty

        master, slave = os.openpty()
        self._pty_fds += [master, slave]
        tty.setraw(slave)  # no echo, no line editing, until the client sets its own mode
        path = os.ttyname(slave)
        self._serial_tasks.append(asyncio.create_task(self._pty_loop(master, path, restart_delay)))
        return path

    async def _pty_loop(self, master: int, path: str, restart_delay: float) -> None:
        while True:
            reader, writer, read_transport = await _pipe_streams(master)
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
            with contextlib.suppress(Exception):
                await asyncio.wait_for(server.wait_closed(), 5)
        self._servers.clear()
        self._serial_tasks.clear()
        fds, self._pty_fds = self._pty_fds, []
        for fd in fds:
            os.close(fd)


async def _pipe_streams(fd: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter, asyncio.BaseTransport]:
    """Asyncio streams on a read/write file descriptor (on duplicates of it); the read transport, to close."""
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader(limit=_READ_SIZE)
    protocol = asyncio.StreamReaderProtocol(reader)
    read_transport, _ = await loop.connect_read_pipe(lambda: protocol, os.fdopen(os.dup(fd), "rb", 0))
    write_transport, write_protocol = await loop.connect_write_pipe(
        asyncio.streams.FlowControlMixin, os.fdopen(os.dup(fd), "wb", 0)
    )
    writer = asyncio.StreamWriter(write_transport, write_protocol, reader, loop)
    return reader, writer, read_transport


async def _watch_stdin(stop: asyncio.Event) -> None:
    """Set ``stop`` when stdin reaches its end: the process that started this one is gone."""
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader()
    transport, _ = await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
    try:
        while await reader.read(4096):
            pass
    finally:
        transport.close()
        stop.set()


# -- command line ---------------------------------------------------------


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or int(port) > 65535:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, e.g. 127.0.0.1:7001, not {text!r}")
    return host.strip("[]") or "127.0.0.1", int(port)


def _option(text: str) -> tuple[str, Any]:
    key, sep, raw = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, not {text!r}")
    try:
        return key, json.loads(raw)
    except ValueError:
        return key, raw


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of the device command (shared by ``psgateway device`` and ``python -m``)."""
    parser.add_argument(
        "--service", required=True, help="kind of service to serve, e.g. sim-robot, sim-sensor"
    )
    parser.add_argument("--name", help="name in the greeting (default: the service kind)")
    parser.add_argument(
        "--option",
        action="append",
        type=_option,
        default=[],
        metavar="KEY=VALUE",
        help="service option; VALUE is JSON when it parses as JSON, else text (repeatable)",
    )
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--tcp", type=_host_port, metavar="HOST:PORT", help="listen on TCP (port 0: pick one)")
    where.add_argument(
        "--connect",
        type=_host_port,
        metavar="HOST:PORT",
        help="dial a gateway's line listener and greet: it registers the device under --name",
    )
    where.add_argument(
        "--serial", metavar="PORT", help="serve on a serial port, e.g. /dev/ttyUSB0 or /dev/pts/3"
    )
    where.add_argument(
        "--pty",
        action="store_true",
        help="create a pseudo-terminal, serve its master side and print the serial port to open"
        " ('serial port /dev/pts/N')",
    )
    parser.add_argument("--baud", type=int, default=115200, help="serial baud rate (default 115200)")
    parser.add_argument("--no-push", action="store_true", help="act as a device that cannot push events")
    parser.add_argument("--checksum", action="store_true", help="send a CRC-8 checksum on every line")
    parser.add_argument(
        "--max-line", type=int, default=MAX_LINE, help=f"longest line accepted (default {MAX_LINE})"
    )
    parser.add_argument(
        "--exit-with-parent",
        action="store_true",
        help="stop when stdin reaches its end (a device process that must end with the one that started it)",
    )
    parser.add_argument("--log-level", default="WARNING", help="logging level (default WARNING)")


def _make_backend(kind: str, options: Mapping[str, Any]) -> Backend:
    from services.catalog import create
    from services.core import LocalService

    return LocalService(create(kind, **options))


async def serve(args: argparse.Namespace) -> None:
    """Run the device described by parsed ``args`` until SIGINT/SIGTERM (or stdin's end, if asked)."""
    backend = _make_backend(args.service, dict(args.option))
    await backend.start()
    server = DeviceServer(
        backend,
        name=args.name or args.service,
        push=not args.no_push,
        checksum=args.checksum,
        max_line=args.max_line,
    )
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    tasks: list[asyncio.Task[None]] = []
    if getattr(args, "exit_with_parent", False):
        tasks.append(asyncio.create_task(_watch_stdin(stop)))
    try:
        if args.tcp:
            host, port = await server.serve_tcp(*args.tcp)
            print(f"listening on {host}:{port}", flush=True)
        elif getattr(args, "connect", None):
            host, port = args.connect
            tasks.append(asyncio.create_task(server.dial(host, port)))
            print(f"connecting to {host}:{port}", flush=True)
        elif getattr(args, "pty", False):
            print(f"serial port {server.serve_pty()}", flush=True)
        else:
            await server.serve_serial(args.serial, args.baud)
            print(f"serving on {args.serial}", flush=True)
        await stop.wait()
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await server.aclose()
        await backend.aclose()


def run(args: argparse.Namespace) -> int:
    """Run the device command; return the process exit status."""
    logging.basicConfig(
        level=str(args.log_level).upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    try:
        asyncio.run(serve(args))
    except PropertyError as exc:
        print(f"error: {exc.message}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m services.device_server``."""
    parser = argparse.ArgumentParser(
        prog="python -m services.device_server", description=__doc__.split("\n")[0]
    )
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())
