"""Bytes in, frames out: the bounded receive buffer."""

from __future__ import annotations

from services.kernel.errors import Code
from services.kernel.line_protocol._errors import LineProtocolError
from services.kernel.line_protocol._frames import MAX_LINE, BadLine, Frame, HelloRequest
from services.kernel.line_protocol._reader import decode_line, tag_of


class LineReceiver:
    """Splits a byte stream into lines and decodes them; never raises for bad input.

    Holds at most ``max_line`` bytes. A line longer than that is reported once
    as a :class:`BadLine` (RESOURCE_EXHAUSTED, with its tag when it began with
    one) as soon as the limit is passed, and its bytes are dropped up to the
    next LF. Every other bad line becomes a BadLine too; the line after it is
    decoded afresh. Empty lines are ignored.
    """

    def __init__(self, max_line: int = MAX_LINE) -> None:
        self.max_line = max_line
        self._buffer = bytearray()
        self._scanned = 0
        self._discarding = False
        #: A line with a valid checksum has been received (and no plain HELLO since): a device
        #: answers with checksums from then on (docs/device-spec.md §6.5).
        self.saw_checksum = False
        #: For each item the last :meth:`receive_data` returned: whether its line began with ``$``.
        self.last_checked: list[bool] = []

    @property
    def pending(self) -> int:
        """Bytes of an unfinished line held in the buffer."""
        return len(self._buffer)

    def discard_partial(self) -> int:
        """Drop an unfinished line (e.g. a device sent half a line, then fell silent); return its size."""
        dropped = len(self._buffer)
        self._buffer.clear()
        self._scanned = 0
        return dropped

    def _too_long(self, head: bytes | bytearray) -> BadLine:
        return BadLine(
            Code.RESOURCE_EXHAUSTED,
            f"line too long: more than {self.max_line} bytes; discarded up to the next newline",
            tag_of(head[:16]),
            head[:1] == b"$",
        )

    def receive_data(self, data: bytes | bytearray | memoryview) -> list[Frame | BadLine]:
        """Take the next bytes of the stream; return the frames of the lines they complete."""
        out: list[Frame | BadLine] = []
        self.last_checked = []
        chunk = data if type(data) is bytes else bytes(data)
        if not self._buffer and not self._discarding:
            # The usual case: nothing held back, so the chunk's whole lines are read
            # from it in place; only an unfinished last line goes to the buffer.
            max_line = self.max_line
            start = 0
            while (end := chunk.find(b"\n", start)) >= 0:
                line = chunk[start:end]
                if end + 1 - start > max_line:
                    out.append(self._too_long(line))
                    self.last_checked.append(line[:1] == b"$")
                else:
                    self._line(line, out)
                start = end + 1
            if start < len(chunk):
                self._buffer += chunk[start:]
                self._split(out)
            return out
        if self._discarding:
            newline = chunk.find(b"\n")
            if newline < 0:
                return out
            chunk = chunk[newline + 1 :]
            self._discarding = False
        self._buffer += chunk
        self._split(out)
        return out

    def _split(self, out: list[Frame | BadLine]) -> None:
        buffer = self._buffer
        while True:
            newline = buffer.find(b"\n", self._scanned)
            if newline < 0:
                if len(buffer) >= self.max_line:
                    out.append(self._too_long(buffer))
                    self.last_checked.append(buffer[:1] == b"$")
                    buffer.clear()
                    self._discarding = True
                self._scanned = len(buffer)
                return
            line = bytes(buffer[:newline])
            del buffer[: newline + 1]
            self._scanned = 0
            if newline + 1 > self.max_line:
                out.append(self._too_long(line))
                self.last_checked.append(line[:1] == b"$")
                continue
            self._line(line, out)

    def _line(self, line: bytes, out: list[Frame | BadLine]) -> None:
        """Decode one complete line (no LF; at most max_line bytes with it) into ``out``."""
        if line.endswith(b"\r"):
            line = line[:-1]
        if not line.strip(b" "):
            return
        checked = line.lstrip(b" ").startswith(b"$")
        try:
            frame = decode_line(line, self.max_line)
        except LineProtocolError as exc:
            out.append(BadLine(exc.code, exc.message, exc.tag, checked, exc.greeting))
            self.last_checked.append(checked)
            return
        out.append(frame)
        self.last_checked.append(checked)
        if checked:
            self.saw_checksum = True
        elif type(frame) is HelloRequest:
            # A plain HELLO: the client starts afresh, checksum mode ends (docs/device-spec.md §6.5).
            self.saw_checksum = False
