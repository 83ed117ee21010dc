"""The kit's end of the wire: send lines to a device, read its lines back, keep a transcript.

The probe is the client of docs/device-spec.md, reduced to what a check needs: one request at a
time (so a device's flow control is never exceeded), lines written in pieces no longer than the
receive buffer the device states, the device's own PINGs answered, and every line either way
kept in :attr:`Probe.transcript` so that a failed check can show what was said.
"""

from __future__ import annotations

import asyncio
import contextlib
from dataclasses import dataclass
from urllib.parse import parse_qsl, unquote, urlsplit

from services.kernel.errors import Code
from services.kernel.line_protocol import (
    BadLine,
    ErrorReply,
    Event,
    Frame,
    Gone,
    Hello,
    LineProtocolError,
    Ping,
    Pong,
    crc8,
    decode_line,
    encode,
)

#: The longest line the probe reads from a device: a device sends lines of up to 1024 bytes
#: (docs/device-spec.md §1.2); room is left for one that sends more, so that the check that
#: catches it can show the line rather than a read error.
READ_LIMIT = 1 << 20
#: Bytes written at once on a serial line when the device states no ``rxbuf``: a UART ring of an
#: 8-bit part is seldom smaller, and a device that reads as the bytes come never holds more than a
#: piece. On TCP the socket's own buffers stand between, and a line goes out whole.
DEFAULT_PIECE = 32
#: Pause between two pieces of one line: at 9600 baud 32 bytes take 33 ms on the wire, so the
#: device has emptied its ring before the next piece comes.
PIECE_PAUSE_S = 0.04
#: Longest line shown in a transcript; the rest is elided (a check sends over-long lines).
SHOWN_BYTES = 120


@dataclass(frozen=True, slots=True)
class Heard:
    """One line from the device: its bytes (without LF) and what the codec makes of them."""

    raw: bytes
    frame: Frame | BadLine

    @property
    def text(self) -> str:
        """The line as text, for messages."""
        return self.raw.decode("utf-8", "backslashreplace")


def decode(raw: bytes) -> Frame | BadLine:
    """The frame of one line from the device, or a BadLine saying why it is none."""
    try:
        return decode_line(raw, READ_LIMIT)
    except LineProtocolError as exc:
        return BadLine(exc.code, exc.message, exc.tag, raw.lstrip(b" ")[:1] == b"$")


def checked(text: str) -> bytes:
    """``text`` as a ``$`` line with its CRC-8 (docs/device-spec.md §6.1), without the LF."""
    body = text.encode()
    return b"$%s*%02X" % (body, crc8(body))


def show(raw: bytes) -> str:
    """A line as a transcript shows it: escapes for what is not printable, long ones cut."""
    text = raw.decode("utf-8", "backslashreplace").replace("\r", "\\r").replace("\t", "\\t")
    return text if len(text) <= SHOWN_BYTES else f"{text[:SHOWN_BYTES]}... ({len(raw)} bytes)"


async def open_url(url: str) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """Open ``tcp://HOST:PORT`` or ``serial:///dev/PORT?baudrate=N``; OSError or ValueError if not."""
    parts = urlsplit(url)
    if parts.scheme == "tcp":
        if not parts.hostname or parts.port is None:
            raise ValueError(f"bad URL {url!r}: expected tcp://HOST:PORT")
        return await asyncio.open_connection(parts.hostname, parts.port, limit=READ_LIMIT)
    if parts.scheme == "serial":
        port = unquote(parts.path)
        if parts.netloc or not port.startswith("/"):
            raise ValueError(f"bad URL {url!r}: expected serial:///dev/ttyUSB0?baudrate=115200")
        query = dict(parse_qsl(parts.query))
        try:
            baudrate = int(query.get("baudrate", "115200"))
        except ValueError:
            raise ValueError(f"bad baudrate {query['baudrate']!r} in {url!r}") from None
        import serial
        import serial_asyncio_fast

        try:
            opened: tuple[asyncio.StreamReader, asyncio.StreamWriter]
            opened = await serial_asyncio_fast.open_serial_connection(
                url=port, baudrate=baudrate, limit=READ_LIMIT
            )
        except (serial.SerialException, ValueError) as exc:
            raise OSError(f"cannot open {port}: {exc}") from exc
        return opened
    raise ValueError(f"bad URL {url!r}: expected tcp://HOST:PORT or serial:///dev/PORT")


class Probe:
    """One connection to the device under test; see the module docstring."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        timeout: float,
        *,
        serial: bool = False,
    ) -> None:
        self.reader = reader
        self.writer = writer
        #: Seconds to wait for a line the device owes.
        self.timeout = timeout
        #: The device is on a serial line: lines go out in pieces its receive ring holds.
        self.serial = serial
        #: Every line, ``> `` what the probe sent, ``< `` what the device sent.
        self.transcript: list[str] = []
        #: The device's greeting, once heard.
        self.greeting: Hello | None = None
        self._tags = 0

    @property
    def piece(self) -> int | None:
        """Bytes written at once: the device's ``rxbuf`` when it states one; None: the whole line."""
        stated = self.greeting.rxbuf if self.greeting is not None else None
        return stated or (DEFAULT_PIECE if self.serial else None)

    def tag(self) -> str:
        """A tag not used before on this connection (``k1``, ``k2``, ...)."""
        self._tags += 1
        return f"k{self._tags:x}"

    async def send(self, line: bytes) -> None:
        """Write ``line`` and its LF, in pieces the device's receive buffer holds."""
        self.transcript.append(f"> {show(line)}")
        data = line + b"\n"
        piece = self.piece or len(data)
        for start in range(0, len(data), piece):
            if start:
                await asyncio.sleep(PIECE_PAUSE_S)
            self.writer.write(data[start : start + piece])
            await self.writer.drain()

    async def line(self, wait: float | None = None) -> Heard | None:
        """The next line from the device, or None when none came in time (or the device hung up).

        The device's PINGs are answered here and not returned: a device MAY ask whether its
        client is there (docs/device-spec.md §8.2).
        """
        while True:
            try:
                async with asyncio.timeout(self.timeout if wait is None else wait):
                    raw = await self.reader.readuntil(b"\n")
            except (TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, OSError):
                return None
            raw = raw[:-1]
            self.transcript.append(f"< {show(raw)}")
            if raw.endswith(b"\r"):
                raw = raw[:-1]
            frame = decode(raw)
            if type(frame) is Ping:
                answer = encode(Pong(frame.data, frame.tag), checksum=raw.lstrip(b" ").startswith(b"$"))
                self.transcript.append(f"> {show(answer[:-1])}")
                self.writer.write(answer)
                await self.writer.drain()
                continue
            return Heard(raw, frame)

    async def reply(self, wait: float | None = None) -> Heard | None:
        """The next line that is not an EVENT or GONE (those may come at any time, §3.3)."""
        while True:
            heard = await self.line(wait)
            if heard is None or type(heard.frame) not in (Event, Gone):
                return heard

    async def ask(self, line: bytes, wait: float | None = None) -> Heard | None:
        """Send one request line; its reply, or None when none came in time."""
        await self.send(line)
        return await self.reply(wait)

    async def settle(self) -> None:
        """Bring the conversation back in step after a check that failed.

        A reply the device owed may still be on its way: a PING with a fresh tag is sent, and
        lines are read until its PONG comes or the time is up.
        """
        tag = self.tag()
        with contextlib.suppress(OSError):
            await self.send(f"#{tag} PING settle".encode())
            while (heard := await self.line()) is not None:
                if type(heard.frame) is Pong and heard.frame.tag == tag:
                    return

    async def close(self) -> None:
        """Close the connection; a device that is gone already is no error."""
        with contextlib.suppress(OSError):
            self.writer.close()
            async with asyncio.timeout(1.0):
                await self.writer.wait_closed()


def is_error(heard: Heard | None, code: Code, tag: str | None) -> bool:
    """Whether ``heard`` is ``ERR code`` carrying exactly ``tag`` (None: untagged)."""
    return (
        heard is not None
        and type(heard.frame) is ErrorReply
        and heard.frame.code == code
        and heard.frame.tag == tag
    )
