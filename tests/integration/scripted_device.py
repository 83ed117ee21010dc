r"""A line-protocol device played by the test on a real TCP socket or a real pty.

It is the kind of device docs/device-spec.md describes for a small
microcontroller: a table of properties, one subscription per path, requests
handled one at a time in arrival order with a pause each (the time an 8-bit
device takes), and, when it states ``rxbuf=N``, a receive buffer of N bytes
that it records as overrun when the client puts more unanswered bytes on the
wire. Everything it received is kept in :attr:`ScriptedDevice.lines`, so a
test can say what the gateway sent and what it did not.

Its values are kept as they travel on the line: a binary value (protocol 1.2)
as ``\=`` and base64. With ``binary=False`` it is a 1.1 device: a SET whose
value is ``\=...`` gets the ``ERR 3 bad escape`` a 1.1 codec answers.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from line_device_support import pty_client, pty_pair

from services.kernel.line_protocol import (
    MAX_LINE,
    BadLine,
    ErrorReply,
    Event,
    Frame,
    Get,
    Gone,
    HelloRequest,
    LineReceiver,
    Listen,
    Ok,
    Ping,
    Pong,
    Set,
    Unlisten,
    crc8,
    encode_value,
    escape_value,
)

#: The message of a 1.1 codec for ``\=`` in a value: an escape it does not know.
ONE_ONE_BAD_ESCAPE = "bad escape: '\\=' (use \\n, \\r, \\\\ or \\s)"


class ScriptedDevice:
    """See the module docstring. ``greeting`` is the whole greeting line, without LF."""

    def __init__(
        self,
        greeting: str,
        props: dict[str, str],
        *,
        delay: float = 0.0,
        rxbuf: int | None = None,
        greet_first: bool = True,
        answer_pings: bool = True,
        binary: bool = True,
        max_listens: int | None = None,
    ) -> None:
        self.greeting = greeting
        self.props = dict(props)
        self.delay = delay
        self.rxbuf = rxbuf
        self.greet_first = greet_first
        self.answer_pings = answer_pings
        self.binary = binary
        #: Its subscription table: a LISTEN of one more path is answered ``ERR 8`` (None: no limit).
        self.max_listens = max_listens
        #: Request lines to lose, by how their words (after a tag) start, and how many times: each
        #: is answered only with the untagged ``ERR 15`` of a receive buffer that overran.
        self.losing: dict[str, int] = {}
        #: Replies to spoil on the way, by how the request's words start, and how many times: the
        #: reply goes out with a checksum that does not match.
        self.damaging: dict[str, int] = {}
        #: Pulled out (:meth:`unplug`): silent until plugged in again.
        self.unplugged = False
        #: Every line received (without LF), in order, over all connections.
        self.lines: list[str] = []
        #: Lines the client sent that are replies to the device's own requests.
        self.replies: asyncio.Queue[str] = asyncio.Queue(maxsize=100)
        self.subscribed: set[str] = set()
        self.connections = 0
        #: The most requests, and bytes of them, received and not answered yet at one moment.
        self.max_unanswered = 0
        self.max_unanswered_bytes = 0
        self.overrun = False
        self._writer: asyncio.StreamWriter | None = None
        self._queue: asyncio.Queue[tuple[Frame | BadLine, int, bool, bool]] = asyncio.Queue(maxsize=1000)
        self._unanswered = 0
        self._unanswered_bytes = 0
        self._tasks: set[asyncio.Task[None]] = set()

    # -- what the test does ----------------------------------------------------

    def send(self, line: str, *, checksum: bool = False) -> None:
        """Write one line to the client (LF added; with ``$...*HH`` when ``checksum``)."""
        assert self._writer is not None, "no client connected"
        body = line.encode()
        self._writer.write(b"$" + body + b"*%02X\n" % crc8(body) if checksum else body + b"\n")

    def unplug(self) -> None:
        """The cable is pulled: the connection drops, and until :meth:`plug_in` the device neither
        greets nor answers a client that connects."""
        self.unplugged = True
        if self._writer is not None:
            self._writer.transport.abort()

    def plug_in(self) -> None:
        """Back: it greets a client that connects, and answers again (a HELLO among the rest)."""
        self.unplugged = False

    def restart(self) -> None:
        """A reset: subscriptions and pending requests are forgotten, the greeting is sent unasked."""
        self.subscribed.clear()
        while not self._queue.empty():
            self._queue.get_nowait()
        self._unanswered = self._unanswered_bytes = 0
        self.send(self.greeting)

    def change(self, path: str, value: str | bytes) -> None:
        """A new value (bytes are kept, and sent, as ``\\=`` and base64)."""
        self.props[path] = value = encode_value(value) if isinstance(value, bytes) else value
        if path in self.subscribed:
            self.send(f"EVENT {path} {value}")

    def remove(self, path: str) -> None:
        """The property goes (a tool unplugged): GONE to a subscriber, which is then forgotten."""
        del self.props[path]
        if path in self.subscribed:
            self.subscribed.discard(path)
            self.send(f"GONE {path}")

    def seen(self, prefix: str) -> list[str]:
        """The received lines whose words (after a tag) start with ``prefix``."""
        return [line for line in self.lines if _untagged(line).startswith(prefix)]

    # -- serving ---------------------------------------------------------------

    async def serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        self._writer = writer
        self.subscribed.clear()
        if self.greet_first and not self.unplugged:
            self.send(self.greeting)
        worker = asyncio.create_task(self._work())
        # It takes lines as long as its greeting says (maxline=), and never fewer than 1024 bytes:
        # the lines that refuse a greeting must reach the test whole.
        stated = re.search(r"\bmaxline=(\d+)", self.greeting)
        receiver = LineReceiver(max_line=max(int(stated.group(1)) if stated else 0, MAX_LINE))
        buffer = b""
        try:
            while data := await reader.read(4096):
                buffer += data
                *complete, buffer = buffer.split(b"\n")
                for raw in complete:
                    self.lines.append(raw.decode(errors="replace"))
                    for frame in receiver.receive_data(raw + b"\n"):
                        self._received(frame, len(raw) + 1, raw.lstrip(b" ").startswith(b"$"))
        except (ConnectionError, OSError):
            pass
        finally:
            worker.cancel()
            await asyncio.gather(worker, return_exceptions=True)
            if self._writer is writer:
                self._writer = None
            writer.close()

    def _received(self, frame: Frame | BadLine, size: int, checked: bool) -> None:
        if isinstance(frame, Ok | ErrorReply | Pong):
            self.replies.put_nowait(self.lines[-1])
            return
        if isinstance(frame, Event | Gone):
            return
        self._unanswered += 1
        self._unanswered_bytes += size
        self.max_unanswered = max(self.max_unanswered, self._unanswered)
        self.max_unanswered_bytes = max(self.max_unanswered_bytes, self._unanswered_bytes)
        if self.rxbuf is not None and self._unanswered_bytes > self.rxbuf:
            self.overrun = True
        words = _untagged(self.lines[-1])
        if _take_one(self.losing, words):
            self._unanswered = max(0, self._unanswered - 1)
            self._unanswered_bytes = max(0, self._unanswered_bytes - size)
            self.send("ERR 15 bytes lost: the receive buffer was full")
            return
        self._queue.put_nowait((frame, size, checked, _take_one(self.damaging, words)))

    async def _work(self) -> None:
        while True:
            frame, size, checked, damaged = await self._queue.get()
            if self.delay:
                await asyncio.sleep(self.delay)
            reply = self._answer(frame)
            self._unanswered = max(0, self._unanswered - 1)
            self._unanswered_bytes = max(0, self._unanswered_bytes - size)
            if reply is not None and self._writer is not None and not self.unplugged:
                if damaged:
                    body = reply.encode()
                    self._writer.write(b"$" + body + b"*%02X\n" % (crc8(body) ^ 0x5A))
                else:
                    self.send(reply, checksum=checked)

    def _answer(self, frame: Frame | BadLine) -> str | None:
        tag = getattr(frame, "tag", None)
        head = f"#{tag} " if tag else ""
        match frame:
            case Get(path):
                return f"{head}OK {self.props[path]}" if path in self.props else f"{head}ERR 5 no {path}"
            case Set(path, value):
                if path not in self.props:
                    return f"{head}ERR 5 no {path}"
                if isinstance(value, bytes):
                    if not self.binary:  # what a 1.1 codec says of "\=": an escape it does not know
                        return f"{head}ERR 3 {escape_value(ONE_ONE_BAD_ESCAPE)}"
                    value = encode_value(value)
                self.props[path] = value
                if path in self.subscribed:
                    self.send(f"{head}OK {value}")
                    self.send(f"EVENT {path} {value}")
                    return None
                return f"{head}OK {value}"
            case Listen(path):
                if path not in self.props:
                    return f"{head}ERR 5 no {path}"
                if (
                    self.max_listens is not None
                    and path not in self.subscribed
                    and len(self.subscribed) >= self.max_listens
                ):
                    return f"{head}ERR 8 too many subscriptions"
                self.subscribed.add(path)
                return f"{head}OK {self.props[path]}"
            case Unlisten(path):
                self.subscribed.discard(path)
                return f"{head}OK"
            case Ping(data):
                if not self.answer_pings:
                    return None
                return f"{head}PONG {data}".rstrip(" ")
            case HelloRequest():
                return f"{head}{self.greeting}"
            case BadLine(code, message):
                return f"{head}ERR {int(code)} {message}"
        return f"{head}ERR 12 not here"


def _take_one(counts: dict[str, int], words: str) -> bool:
    """Whether ``words`` start with a prefix in ``counts`` that has some left; counts one down."""
    for prefix, left in counts.items():
        if left > 0 and words.startswith(prefix):
            counts[prefix] = left - 1
            return True
    return False


def _untagged(line: str) -> str:
    line = line[1:-3] if line.startswith("$") else line
    if line.startswith("#"):
        line = line.partition(" ")[2]
    return line


@asynccontextmanager
async def tcp_scripted(device: ScriptedDevice) -> AsyncIterator[str]:
    """Serve ``device`` on a free TCP port of 127.0.0.1; yields its ``tcp://`` URL."""
    tasks: set[asyncio.Task[None]] = set()

    def accepted(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.create_task(device.serve(reader, writer))
        tasks.add(task)
        task.add_done_callback(tasks.discard)

    server = await asyncio.start_server(accepted, "127.0.0.1", 0)
    host, port = server.sockets[0].getsockname()[:2]
    try:
        yield f"tcp://{host}:{port}"
    finally:
        server.close()
        for task in list(tasks):
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        with contextlib.suppress(Exception):
            await server.wait_closed()


@asynccontextmanager
async def pty_scripted(device: ScriptedDevice) -> AsyncIterator[str]:
    """Serve ``device`` on the master side of a real pty; yields the slave's path (the serial port)."""
    with pty_pair() as (master, path):
        client = await pty_client(master)
        task = asyncio.create_task(device.serve(client.reader, client.writer))
        try:
            yield path
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
            await client.close()
