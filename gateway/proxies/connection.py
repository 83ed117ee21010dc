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
import logging
import time
from collections import deque
from collections.abc import Callable

from services.errors import (
    Code,
    DataLoss,
    DeadlineExceeded,
    PropertyError,
    ResourceExhausted,
    Unavailable,
    error_for,
)
from services.line_protocol import (
    MAX_LINE,
    BadLine,
    Cancel,
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
    Request,
    Set,
    Unlisten,
    encode,
)

log = logging.getLogger(__name__)

_READ_SIZE = 65536
#: Tags are the request counter in hex, at most 8 digits.
_TAG_MASK = 0xFFFFFFFF


class _Pending:
    """One request waiting for its reply: its future, its timer, its time limit."""

    __slots__ = ("cancel_when_abandoned", "future", "timeout", "timer")

    def __init__(self, future: asyncio.Future[Frame], timer: asyncio.TimerHandle, timeout: float) -> None:
        self.future = future
        self.timer = timer
        self.timeout = timeout
        #: A SET: when nobody waits for its reply any more, the device is told to drop it.
        self.cancel_when_abandoned = False


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
        self._loop = asyncio.get_running_loop()
        self._pending: dict[str, _Pending] = {}
        self._next_tag = 0
        #: Free request slots, and the requests waiting for one (oldest first).
        self._free = max_in_flight
        self._slot_waiters: deque[asyncio.Future[None]] = deque()
        #: Lines queued in this loop iteration after the first one went out; see _write_line.
        self._outgoing: list[bytes] = []
        self._flush_due = False
        self._closed = asyncio.Event()
        self._close_reason = "connection closed"
        self._last_data = time.monotonic()
        self.hello: asyncio.Future[Hello] = self._loop.create_future()
        #: Longest line the device accepts (from its greeting).
        self.max_line = MAX_LINE
        self._task = asyncio.create_task(self._read_loop(), name=f"line-connection {label}")

    # -- state -------------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    @property
    def close_reason(self) -> str:
        """Why the connection closed (or will read so, once it does)."""
        return self._close_reason

    @property
    def last_heard(self) -> float:
        """``time.monotonic()`` when the device last sent anything."""
        return self._last_data

    async def wait_closed(self) -> None:
        await self._closed.wait()

    def close(self, reason: str = "connection closed") -> None:
        """Close the stream and fail every outstanding call with UNAVAILABLE. Idempotent."""
        if self._closed.is_set():
            return
        self._close_reason = reason
        self._closed.set()
        for pending in self._pending.values():
            pending.timer.cancel()
            if not pending.future.done():
                pending.future.set_exception(Unavailable(f"{self.label}: {reason}"))
        self._pending.clear()
        for waiter in self._slot_waiters:
            if not waiter.done():
                waiter.set_exception(Unavailable(f"{self.label}: {reason}"))
        self._slot_waiters.clear()
        self._outgoing.clear()
        if not self.hello.done():
            self.hello.set_exception(Unavailable(f"{self.label}: {reason}"))
        try:
            self._writer.close()
        except OSError as exc:  # the stream broke already: closing it is all that was left to do
            log.debug("%s: closing the stream: %s", self.label, exc)
        except Exception:
            log.exception("%s: closing the stream failed", self.label)
        if asyncio.current_task() is not self._task:
            self._task.cancel()

    async def aclose(self, reason: str = "connection closed") -> None:
        self.close(reason)
        # The reader ends cancelled (expected); anything else it raised is a bug worth a traceback.
        (outcome,) = await asyncio.gather(self._task, return_exceptions=True)
        if isinstance(outcome, Exception):
            log.error("%s: the reader failed", self.label, exc_info=outcome)

    # -- requests ----------------------------------------------------------

    def _send(self, frame: Frame) -> None:
        self._write_line(encode(frame, checksum=self._checksum, max_line=self.max_line))

    def _write_line(self, line: bytes) -> None:
        # The first line of a loop iteration goes out at once (no added latency);
        # lines queued after it in the same iteration go out together in one send.
        if self._flush_due:
            self._outgoing.append(line)
            return
        self._flush_due = True
        self._loop.call_soon(self._flush)
        self._writer.write(line)

    def _flush(self) -> None:
        self._flush_due = False
        lines = self._outgoing
        if lines:
            self._outgoing = []
            if not self._closed.is_set():
                self._writer.write(b"".join(lines))

    def start_request(self, frame: Request, deadline_s: float) -> asyncio.Future[Frame] | None:
        """Send ``frame`` now under a fresh tag; return the future of its reply (Ok, Pong or Hello).

        The future fails with the PropertyError of an ERR reply, with
        DeadlineExceeded when no reply came in ``deadline_s`` seconds, with
        Unavailable when the connection closes. Returns None, sending
        nothing, when every request slot is taken (:meth:`request` waits for
        one). Raises Unavailable on a closed connection and PropertyError for
        a frame that cannot be written.
        """
        if self._free <= 0 or self._slot_waiters:
            if self._closed.is_set():
                raise Unavailable(f"{self.label}: {self._close_reason}")
            return None
        self._free -= 1
        return self._issue(frame, deadline_s, self._loop.time() + deadline_s)

    async def request(self, frame: Request, deadline_s: float) -> Frame:
        """Send ``frame`` under a fresh tag and return the reply frame (Ok, Pong or Hello).

        An ERR reply is raised as the PropertyError of its code; no reply in
        ``deadline_s`` seconds raises DeadlineExceeded; a closed connection
        raises Unavailable.
        """
        future = self.start_request(frame, deadline_s)
        if future is None:
            deadline = self._loop.time() + deadline_s
            await self._wait_slot(deadline, deadline_s)
            future = self._issue(frame, deadline_s, deadline)
        return await future

    def _issue(self, frame: Request, timeout: float, deadline: float) -> asyncio.Future[Frame]:
        """Send ``frame`` in the slot the caller holds; the reply or the timeout frees the slot."""
        if self._closed.is_set():
            self._release_slot()
            raise Unavailable(f"{self.label}: {self._close_reason}")
        self._next_tag = tag_number = (self._next_tag + 1) & _TAG_MASK
        tag = format(tag_number, "x")
        try:
            line = encode(_with_tag(frame, tag), checksum=self._checksum, max_line=self.max_line)
        except LineProtocolError as exc:
            self._release_slot()
            raise error_for(exc.code, f"{self.label}: cannot send the request: {exc.message}") from None
        loop = self._loop
        future: asyncio.Future[Frame] = loop.create_future()
        pending = _Pending(future, loop.call_at(deadline, self._expire, tag), timeout)
        self._pending[tag] = pending
        if type(frame) is Set:
            pending.cancel_when_abandoned = True
            future.add_done_callback(lambda done: self._abandoned(done, tag))
        self._write_line(line)
        return future

    def _abandoned(self, future: asyncio.Future[Frame], tag: str) -> None:
        """The caller of a SET gave up (its own deadline): tell the device to drop the request."""
        pending = self._pending.get(tag)
        if future.cancelled() and pending is not None:
            self._send_cancel(pending, tag)

    def _send_cancel(self, pending: _Pending, tag: str) -> None:
        # The client is told DEADLINE_EXCEEDED; a device that has not started the SET
        # yet (it was frozen, or busy) must not apply it when it gets to it
        # (docs/line-protocol.md, CANCEL). Once per request.
        if not pending.cancel_when_abandoned or self._closed.is_set():
            return
        pending.cancel_when_abandoned = False
        with contextlib.suppress(LineProtocolError):
            self._send(Cancel(tag))

    def _expire(self, tag: str) -> None:
        pending = self._pending.pop(tag, None)
        if pending is None:
            return
        self._release_slot()
        self._send_cancel(pending, tag)
        if not pending.future.done():
            self._drop_stale_half_line(pending.timeout)
            pending.future.set_exception(
                DeadlineExceeded(f"{self.label}: no reply within {pending.timeout:g} s")
            )

    async def _wait_slot(self, deadline: float, limit_s: float) -> None:
        loop = self._loop
        waiter: asyncio.Future[None] = loop.create_future()
        self._slot_waiters.append(waiter)
        timer = loop.call_at(deadline, _time_out, waiter)
        try:
            await waiter
        except TimeoutError:
            raise DeadlineExceeded(f"{self.label}: too many requests in flight for {limit_s:g} s") from None
        except BaseException:
            if waiter.done() and not waiter.cancelled() and waiter.exception() is None:
                self._release_slot()  # handed a slot just as the caller gave up: pass it on
            raise
        finally:
            timer.cancel()

    def _release_slot(self) -> None:
        waiters = self._slot_waiters
        while waiters:
            waiter = waiters.popleft()
            if not waiter.done():
                waiter.set_result(None)
                return
        self._free += 1

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
        kind = type(frame)
        if kind is Ok or kind is ErrorReply or kind is Pong or kind is Hello:
            reply: Ok | ErrorReply | Pong | Hello = frame  # type: ignore[assignment]
            tag = reply.tag
            if tag is not None:
                self._resolve(reply, tag)
                return
            if kind is Hello:
                self._greeted(reply)  # type: ignore[arg-type]
                return
            if kind is ErrorReply:
                log.warning("%s: device reports: ERR %d %s", self.label, reply.code, reply.message)  # type: ignore[union-attr]
                return
        elif kind is Event or kind is Gone:
            try:
                self._on_event(frame)  # type: ignore[arg-type]
            except Exception:
                log.exception("%s: event handler failed on %r", self.label, frame)
            return
        elif kind is Ping:
            with contextlib.suppress(LineProtocolError):
                self._send(Pong(frame.data, frame.tag))  # type: ignore[union-attr]
            return
        elif kind is BadLine:
            self._bad_line(frame)  # type: ignore[arg-type]
            return
        log.warning("%s: unexpected line from the device ignored: %r", self.label, frame)

    def _resolve(self, reply: Ok | ErrorReply | Pong | Hello, tag: str) -> None:
        if type(reply) is Hello:
            self._greeted(reply)
        pending = self._pending.pop(tag, None)
        if pending is None:
            if type(reply) is not Hello:
                log.info("%s: reply for tag #%s came too late or was not asked for; ignored", self.label, tag)
            return
        pending.timer.cancel()
        self._release_slot()
        future = pending.future
        if future.done():
            return
        if type(reply) is ErrorReply:
            future.set_exception(reply.to_exception())
        else:
            future.set_result(reply)

    def _greeted(self, hello: Hello) -> None:
        self.max_line = hello.max_line
        if not self.hello.done():
            self.hello.set_result(hello)

    def _bad_line(self, bad: BadLine) -> None:
        pending = self._pending.pop(bad.tag, None) if bad.tag is not None else None
        if pending is not None:
            pending.timer.cancel()
            self._release_slot()
        future = pending.future if pending is not None else None
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
            error = DataLoss(f"{self.label}: the device sent a malformed reply: {bad.message}")
        future.set_exception(error)


def _time_out(waiter: asyncio.Future[None]) -> None:
    if not waiter.done():
        waiter.set_exception(TimeoutError())


def _with_tag(frame: Request, tag: str) -> Request:
    kind = type(frame)
    if kind is Get:
        return Get(frame.path, frame.params, tag)  # type: ignore[union-attr]
    if kind is Set:
        return Set(frame.path, frame.value, frame.params, tag)  # type: ignore[union-attr]
    if kind is Listen:
        return Listen(frame.path, frame.params, tag)  # type: ignore[union-attr]
    if kind is Unlisten:
        return Unlisten(frame.path, frame.params, tag)  # type: ignore[union-attr]
    if kind is Ping:
        return Ping(frame.data, tag)  # type: ignore[union-attr]
    return HelloRequest(tag)
