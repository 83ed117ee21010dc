"""One live line-protocol connection to a device, with requests pipelined by tag.

:class:`LineConnection` owns the reader task of one stream (a TCP socket or a
serial port). Requests get a fresh tag each and may be in flight together;
replies resolve them in any order. EVENT and GONE lines go to a callback.
Whatever the device sends wrong affects only the request it belongs to:

* a reply that does not arrive in time → DEADLINE_EXCEEDED for that call (a
  half line left behind by a device that fell silent is dropped, so it cannot
  corrupt the next reply);
* a malformed or over-long reply line that begins with a tag → an error for
  that call; without a tag → a log line;
* the stream ends (even mid-reply) → UNAVAILABLE at once for every
  outstanding call, and for every later one.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import time
from collections.abc import Callable

from services.errors import Code, DeadlineExceeded, PropertyError, ResourceExhausted, Unavailable
from services.line_protocol import (
    MAX_LINE,
    BadLine,
    ErrorReply,
    Event,
    Frame,
    Gone,
    Hello,
    HelloRequest,
    LineProtocolError,
    LineReceiver,
    Ok,
    Ping,
    Pong,
    Request,
    encode,
)

log = logging.getLogger(__name__)

_READ_SIZE = 65536
_TAG_DIGITS = "0123456789abcdefghijklmnopqrstuvwxyz"


def _tag_text(n: int) -> str:
    out = ""
    while True:
        n, digit = divmod(n, 36)
        out = _TAG_DIGITS[digit] + out
        if not n:
            return out


class LineConnection:
    """The client side of one line-protocol stream (see the module docstring)."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        *,
        label: str,
        on_event: Callable[[Event | Gone], None],
        checksum: bool = False,
        max_in_flight: int = 256,
    ) -> None:
        self.label = label
        self._reader = reader
        self._writer = writer
        self._on_event = on_event
        self._checksum = checksum
        self._receiver = LineReceiver()
        self._pending: dict[str, asyncio.Future[Frame]] = {}
        self._tags = itertools.count()
        self._slots = asyncio.Semaphore(max_in_flight)
        self._closed = asyncio.Event()
        self._close_reason = "connection closed"
        self._last_data = time.monotonic()
        self.hello: asyncio.Future[Hello] = asyncio.get_running_loop().create_future()
        #: Longest line the device accepts (from its greeting).
        self.max_line = MAX_LINE
        self._task = asyncio.create_task(self._read_loop(), name=f"line-connection {label}")

    # -- state -------------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    async def wait_closed(self) -> None:
        await self._closed.wait()

    def close(self, reason: str = "connection closed") -> None:
        """Close the stream and fail every outstanding call with UNAVAILABLE. Idempotent."""
        if self._closed.is_set():
            return
        self._close_reason = reason
        self._closed.set()
        for future in self._pending.values():
            if not future.done():
                future.set_exception(Unavailable(f"{self.label}: {reason}"))
        self._pending.clear()
        if not self.hello.done():
            self.hello.set_exception(Unavailable(f"{self.label}: {reason}"))
        with contextlib.suppress(Exception):
            self._writer.close()
        if asyncio.current_task() is not self._task:
            self._task.cancel()

    async def aclose(self, reason: str = "connection closed") -> None:
        self.close(reason)
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await self._task

    # -- requests ----------------------------------------------------------

    def _send(self, frame: Frame) -> None:
        self._writer.write(encode(frame, checksum=self._checksum, max_line=self.max_line))

    async def request(self, frame: Request, deadline_s: float) -> Frame:
        """Send ``frame`` under a fresh tag and return the reply frame (Ok, Pong or Hello).

        An ERR reply is raised as the PropertyError of its code; no reply in
        ``deadline_s`` seconds raises DeadlineExceeded; a closed connection
        raises Unavailable.
        """
        if self._closed.is_set():
            raise Unavailable(f"{self.label}: {self._close_reason}")
        timeout = deadline_s
        deadline = asyncio.get_running_loop().time() + timeout
        try:
            async with asyncio.timeout_at(deadline):
                await self._slots.acquire()
        except TimeoutError:
            raise DeadlineExceeded(f"{self.label}: too many requests in flight for {timeout:g} s") from None
        tag = _tag_text(next(self._tags) % 36**8)
        future: asyncio.Future[Frame] = asyncio.get_running_loop().create_future()
        try:
            tagged = _with_tag(frame, tag)
            try:
                self._send(tagged)
            except LineProtocolError as exc:
                raise PropertyError(
                    f"{self.label}: cannot send the request: {exc.message}", exc.code
                ) from None
            if self._closed.is_set():
                raise Unavailable(f"{self.label}: {self._close_reason}")
            self._pending[tag] = future
            try:
                async with asyncio.timeout_at(deadline):
                    reply = await future
            except TimeoutError:
                self._drop_stale_half_line(timeout)
                raise DeadlineExceeded(f"{self.label}: no reply within {timeout:g} s") from None
        finally:
            self._pending.pop(tag, None)
            self._slots.release()
        if isinstance(reply, ErrorReply):
            raise reply.to_exception()
        return reply

    def _drop_stale_half_line(self, timeout: float) -> None:
        # A device that sent half a line and fell silent would otherwise glue
        # that half to the front of its next line and spoil that reply too.
        silent_for = time.monotonic() - self._last_data
        if self._receiver.pending and silent_for >= timeout:
            dropped = self._receiver.discard_partial()
            log.warning(
                "%s: dropped %d bytes of an unfinished line after %.1f s of silence",
                self.label,
                dropped,
                silent_for,
            )

    def ask_hello(self) -> None:
        """Ask the device to introduce itself (a serial device greeted long before the port was opened)."""
        with contextlib.suppress(LineProtocolError):
            self._send(HelloRequest())

    # -- receiving ---------------------------------------------------------

    async def _read_loop(self) -> None:
        reason = "the device closed the connection"
        try:
            while True:
                data = await self._reader.read(_READ_SIZE)
                if not data:
                    if self._receiver.pending:
                        reason = "the device closed the connection in the middle of a line"
                    break
                self._last_data = time.monotonic()
                for frame in self._receiver.receive_data(data):
                    self._handle(frame)
        except (ConnectionError, OSError) as exc:
            reason = f"connection lost: {exc}"
        except asyncio.CancelledError:
            reason = self._close_reason
        if not self._closed.is_set():
            log.warning("%s: %s", self.label, reason)
        self.close(reason)

    def _handle(self, frame: Frame | BadLine) -> None:
        if isinstance(frame, Event | Gone):
            try:
                self._on_event(frame)
            except Exception:
                log.exception("%s: event handler failed on %r", self.label, frame)
            return
        if isinstance(frame, Hello) and frame.tag is None:
            self._greeted(frame)
            return
        if isinstance(frame, Ping):
            with contextlib.suppress(LineProtocolError):
                self._send(Pong(frame.data, frame.tag))
            return
        if isinstance(frame, BadLine):
            self._bad_line(frame)
            return
        tag = getattr(frame, "tag", None)
        if isinstance(frame, Ok | ErrorReply | Pong | Hello) and tag is not None:
            if isinstance(frame, Hello):
                self._greeted(frame)
            future = self._pending.pop(tag, None)
            if future is not None and not future.done():
                future.set_result(frame)
            elif not isinstance(frame, Hello):
                log.info("%s: reply for tag #%s came too late or was not asked for; ignored", self.label, tag)
            return
        if isinstance(frame, ErrorReply):
            log.warning("%s: device reports: ERR %d %s", self.label, frame.code, frame.message)
            return
        log.warning("%s: unexpected line from the device ignored: %r", self.label, frame)

    def _greeted(self, hello: Hello) -> None:
        self.max_line = hello.max_line
        if not self.hello.done():
            self.hello.set_result(hello)

    def _bad_line(self, bad: BadLine) -> None:
        future = self._pending.pop(bad.tag, None) if bad.tag is not None else None
        log.warning(
            "%s: bad line from the device%s: %s",
            self.label,
            f" (reply to #{bad.tag})" if bad.tag else "",
            bad.message,
        )
        if future is None or future.done():
            return
        if bad.code == Code.RESOURCE_EXHAUSTED:
            error: PropertyError = ResourceExhausted(
                f"{self.label}: the device's reply was too long: {bad.message}"
            )
        else:
            error = PropertyError(
                f"{self.label}: the device sent a malformed reply: {bad.message}", Code.DATA_LOSS
            )
        future.set_exception(error)


def _with_tag(frame: Request, tag: str) -> Request:
    import dataclasses

    return dataclasses.replace(frame, tag=tag)
