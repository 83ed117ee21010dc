"""One live line-protocol connection to a device, with requests pipelined by tag.

:class:`LineConnection` is the asyncio protocol of one stream to a device: a
TCP socket it is connected to directly (:meth:`asyncio.loop.create_connection`),
or a serial port or a dialled-in socket whose stream it reads in one task
(:meth:`LineConnection.read_from`). Requests get a fresh tag each and may be
in flight together; replies resolve them in any order. EVENT and GONE lines
go to a callback.

What one request costs (docs/performance.md, "Get through the TCP proxy"):

* the lines of every request started in one turn of the event loop go out
  in one ``write`` at the end of that turn, so a batch of Gets from one
  Session message is one send to the device and, as the device answers a
  batch in one write, one read back; a caller that knows its batch is
  complete (the Session, once a message's requests are started) sends it
  at once with :meth:`LineConnection.flush` (the proxy's :meth:`~services.kernel.backend.Backend.flush`)
  rather than a loop turn later;
* every complete line of one read is decoded and resolved right in
  ``data_received``: no reader task to wake, no copy into a stream buffer;
* one timer per connection, armed at the earliest deadline of the requests
  in flight, instead of one per request.

Whatever the device sends wrong affects only the request it belongs to:

* a reply that does not arrive in time → DEADLINE_EXCEEDED for that call (a
  half line left behind by a device that fell silent is dropped, so it cannot
  corrupt the next reply);
* a malformed or over-long reply line that begins with a tag → an error for
  that call; without a tag → a log line;
* the stream ends (even mid-reply) → UNAVAILABLE at once for every
  outstanding call, and for every later one;
* it greets again unasked (it restarted) → UNAVAILABLE for every outstanding
  call, and ``on_restart`` tells the proxy (docs/line-protocol.md §4);
* a greeting it cannot accept (another version, a bad field) → an ERR line to
  the device and the ``hello`` future fails with that refusal (§3).

Flow control (§7; docs/device-spec.md §5): the connection never has more unanswered requests
than the device's ``inflight`` (1 on a serial line that states nothing), nor
more bytes of them than its ``rxbuf``; a request that finds no room waits for
it in order.
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import logging
import time
from collections import deque
from collections.abc import Callable
from typing import Protocol, cast

from gateway.logs import current_request_id, outside_requests
from services.kernel.errors import (
    Code,
    DataLoss,
    DeadlineExceeded,
    FailedPrecondition,
    PropertyError,
    ResourceExhausted,
    Unavailable,
    error_for,
)
from services.kernel.line_protocol import (
    MAX_LINE,
    PROTOCOL_REVISION,
    PROTOCOL_VERSION,
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
    decode_line,
    encode,
)

log = logging.getLogger(__name__)

_READ_SIZE = 65536
#: Seconds that aclose waits for the stream to report itself closed before it aborts it.
_CLOSE_WAIT_S = 1.0
#: Answered requests whose deadline is still ahead, beyond which the heap of deadlines is rebuilt
#: from the requests in flight: it never holds more than about twice those, plus this.
_STALE_DEADLINES = 256
#: Most bytes of a sent line shown on the debug line: enough for a path and a short value; a
#: base64 image must not fill the log.
LOGGED_LINE_BYTES = 200

#: How long after the gateway's untagged HELLO a greeting is taken as its answer (§4).
ASKED_GREETING_WINDOW_S = 2.0
#: Times a request is sent again when the device reports bytes lost (an untagged ``ERR 15``) or its
#: reply arrives damaged, before the call fails with DATA_LOSS: a line that a noisy serial line
#: spoils three times in a row is not noise any more, and the call's own deadline still holds.
RESENDS = 2
#: Tags are the request counter in hex, at most 8 digits.
_TAG_MASK = 0xFFFFFFFF
#: A request is measured with the longest tag it could carry, so that whether it fits the device's
#: line limit never depends on how many requests came before it (§4.2).
_WIDEST_TAG_DIGITS = len(format(_TAG_MASK, "x"))


#: What a device that asks the gateway something on a connection the gateway opened is told.
#: Short: it must fit the smallest line limit (64 bytes) with a tag and a checksum.
_NOT_SERVED = "not served: the gateway is the client here"


class _Pending:
    """One request waiting for its reply: its future, its deadline, its time limit, its line."""

    __slots__ = ("cancel_when_abandoned", "deadline", "future", "line", "tag", "then", "timeout")

    def __init__(
        self, future: asyncio.Future[Frame], tag: str, deadline: float, timeout: float, line: bytes
    ) -> None:
        self.future = future
        self.tag = tag
        self.deadline = deadline
        self.timeout = timeout
        #: The line as sent (its length counts against the device's ``rxbuf`` until answered): sent
        #: again, tag and all, when the device reports it lost (§8).
        self.line = line
        #: A SET: when nobody waits for its reply any more, the device is told to drop it.
        self.cancel_when_abandoned = False
        #: Called with a successful reply as it is read, before the future is resolved.
        self.then: Callable[[Frame], None] | None = None


class LineSink(Protocol):
    """Where a connection writes: an asyncio transport (a socket's, a serial port's)."""

    def write(self, data: bytes) -> None: ...

    def close(self) -> None: ...

    def abort(self) -> None: ...


class LineConnection(asyncio.Protocol):
    """The client side of one line-protocol stream (see the module docstring).

    Made before the stream is open; it begins to serve when the stream is
    attached: by :meth:`asyncio.loop.create_connection` (``lambda: connection``)
    or by :meth:`read_from`.
    """

    def __init__(
        self,
        *,
        label: str,
        on_event: Callable[[Event | Gone], None],
        checksum: bool = False,
        max_in_flight: int = 256,
        serial: bool = False,
        on_restart: Callable[[Hello], None] | None = None,
        receive_limit: int = MAX_LINE,
    ) -> None:
        self.label = label
        self._transport: LineSink | None = None
        #: The task reading a stream (read_from); None when the stream calls data_received itself.
        self._task: asyncio.Task[None] | None = None
        self._stream_writer: asyncio.StreamWriter | None = None
        self._loop = asyncio.get_running_loop()
        #: Done when the stream reports itself closed.
        self._lost: asyncio.Future[None] = self._loop.create_future()
        self._on_event = on_event
        self._on_restart = on_restart
        self._checksum = checksum
        #: The longest line taken from the device (the proxy option ``maxline``); longer is a bad line.
        self._receiver = LineReceiver(max_line=receive_limit)
        self._pending: dict[str, _Pending] = {}
        #: Times each request in flight that was reported lost has been sent again, by tag.
        self._resent: dict[str, int] = {}
        #: (deadline, issue number, request): a heap over the requests in flight (and some answered
        #: ones, dropped lazily), with the one timer armed at its earliest live deadline.
        self._deadlines: list[tuple[float, int, _Pending]] = []
        self._issued = 0
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at = 0.0
        self._next_tag = 0
        #: The proxy's own ceiling on unanswered requests, and whether the stream is a serial line.
        self._ceiling = max_in_flight
        self._serial = serial
        #: Flow control (docs/device-spec.md §5): the most unanswered requests, and bytes of them,
        #: the device takes.
        #: Until the greeting a serial device is taken to handle one request at a time.
        self.inflight_limit = 1 if serial else max_in_flight
        self.rxbuf: int | None = None
        self._in_flight = 0
        self._in_flight_bytes = 0
        #: Requests waiting for room, oldest first: (waiter, bytes of the line).
        self._room_waiters: deque[tuple[asyncio.Future[None], int]] = deque()
        #: Lines written in this turn of the event loop; they go out together at its end.
        self._outgoing: list[bytes] = []
        self._flush_due = False
        self._closed = asyncio.Event()
        self._close_reason = "connection closed"
        self._last_data = time.monotonic()
        self.hello: asyncio.Future[Hello] = self._loop.create_future()
        #: Greetings asked for with an untagged HELLO and not yet matched, and until when they may
        #: come: each such greeting is an answer, not a restart (§4). A serial device greets when
        #: it boots and again when asked; both may arrive after the gateway's HELLO went out.
        self._asked_greetings = 0
        self._asked_until = 0.0
        #: Longest line the device accepts (from its greeting).
        self.max_line = MAX_LINE

    # -- the stream --------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # A stream's transport: a socket's or a serial port's, both of which write.
        self._transport = cast("LineSink", transport)

    def read_from(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Serve a stream opened elsewhere (a serial port, a socket that dialled in): one task reads it."""
        self.connection_made(writer.transport)
        # Held: a StreamWriter that is collected closes its transport.
        self._stream_writer = writer
        self._task = asyncio.create_task(
            self._read_loop(reader), name=f"line-connection {self.label}", context=outside_requests()
        )
        self._task.add_done_callback(self._reader_ended)

    def _reader_ended(self, task: asyncio.Task[None]) -> None:
        # The reader ends cancelled or at the stream's end (expected); anything it raised is a bug
        # worth a traceback, logged here even when nobody awaits the connection's close.
        if not task.cancelled() and (exc := task.exception()) is not None:
            log.error("%s: the reader failed", self.label, exc_info=exc)

    def data_received(self, data: bytes) -> None:
        self._last_data = time.monotonic()
        receiver = self._receiver
        frames = receiver.receive_data(data)
        for frame, checked in zip(frames, receiver.last_checked, strict=True):
            self._handle(frame, checked)

    def eof_received(self) -> bool:
        self._ended(self._eof_reason())
        return False

    def connection_lost(self, exc: Exception | None) -> None:
        self._ended(f"connection lost: {exc}" if exc is not None else self._eof_reason())
        if not self._lost.done():
            self._lost.set_result(None)

    def _eof_reason(self) -> str:
        if self._receiver.pending:
            return "the device closed the connection in the middle of a line"
        return "the device closed the connection"

    def _ended(self, reason: str) -> None:
        if not self._closed.is_set():
            log.warning("%s: %s", self.label, reason)
        self.close(reason)

    async def _read_loop(self, reader: asyncio.StreamReader) -> None:
        try:
            while data := await reader.read(_READ_SIZE):
                self.data_received(data)
            reason = self._eof_reason()
        except (ConnectionError, OSError) as exc:
            reason = f"connection lost: {exc}"
        except asyncio.CancelledError:
            reason = self._close_reason
        self._ended(reason)
        if not self._lost.done():
            self._lost.set_result(None)

    # -- state -------------------------------------------------------------

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    @property
    def close_reason(self) -> str:
        """Why the connection closed (or will read so, once it does)."""
        return self._close_reason

    @property
    def flow_controlled(self) -> bool:
        """The device stated ``inflight`` or ``rxbuf``, or is on a serial line: no CANCEL lines (§7)."""
        return self._serial or self.rxbuf is not None or self.inflight_limit < self._ceiling

    @property
    def in_flight(self) -> tuple[int, int]:
        """Unanswered requests on the wire now: (count, bytes)."""
        return self._in_flight, self._in_flight_bytes

    @property
    def deadlines_held(self) -> int:
        """Deadlines the connection's timer keeps: of the requests in flight, and of answered ones
        not dropped yet; never more than twice those in flight plus a few hundred."""
        return len(self._deadlines)

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
        self._stop_timer()
        self._deadlines.clear()
        for pending in self._pending.values():
            if not pending.future.done():
                pending.future.set_exception(Unavailable(f"{self.label}: {reason}"))
        self._pending.clear()
        for waiter, _ in self._room_waiters:
            if not waiter.done():
                waiter.set_exception(Unavailable(f"{self.label}: {reason}"))
        self._room_waiters.clear()
        self._outgoing.clear()
        if not self.hello.done():
            self.hello.set_exception(Unavailable(f"{self.label}: {reason}"))
            # Marked as heard: whoever awaits the greeting still gets the error, but a caller that
            # stopped waiting (a registration that timed out in asyncio.wait) leaves nobody to
            # retrieve it, and asyncio would log "Future exception was never retrieved".
            self.hello.exception()
        transport = self._transport
        if transport is None:  # never attached: nothing to close, and nobody waits for it
            self._lost.cancel()
        else:
            try:
                transport.close()
            except OSError as exc:  # the stream broke already: closing it is all that was left to do
                log.debug("%s: closing the stream: %s", self.label, exc)
            except Exception:
                log.exception("%s: closing the stream failed", self.label)
        task = self._task
        if task is not None and asyncio.current_task() is not task:
            task.cancel()

    async def aclose(self, reason: str = "connection closed") -> None:
        """Close, and wait (a bounded while) until the stream is closed and its reader has ended."""
        self.close(reason)
        task = self._task
        if task is not None:
            # What the reader raised, if anything, _reader_ended has logged.
            await asyncio.gather(task, return_exceptions=True)
            return
        if self._transport is None or self._lost.done():
            return
        # A device that does not read keeps the last lines in the send buffer: abort after a while.
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(asyncio.shield(self._lost), _CLOSE_WAIT_S)
            return
        self._transport.abort()

    # -- requests ----------------------------------------------------------

    def _send(self, frame: Frame) -> None:
        self._write_line(encode(frame, checksum=self._checksum, max_line=self.max_line))

    def _write_line(self, line: bytes) -> None:
        # Every line of this turn of the loop goes out in one write at its end: a Session message
        # of many Gets is one send to the device (and, answered in one write, one read back).
        self._outgoing.append(line)
        if not self._flush_due:
            self._flush_due = True
            self._loop.call_soon(self.flush)

    def flush(self) -> None:
        """Send the lines held for the end of this loop turn now, in one write (see :meth:`Backend.flush`)."""
        self._flush_due = False
        lines = self._outgoing
        if not lines:
            return
        self._outgoing = []
        transport = self._transport
        if transport is not None and not self._closed.is_set():
            transport.write(lines[0] if len(lines) == 1 else b"".join(lines))

    def start_request(
        self, frame: Request, deadline_s: float, then: Callable[[Frame], None] | None = None
    ) -> asyncio.Future[Frame] | None:
        """Send ``frame`` now under a fresh tag; return the future of its reply (Ok, Pong or Hello).

        ``then``, when given, is called with a successful reply as soon as it
        is read, before the future is resolved (whose done-callbacks run a
        loop turn later); errors, timeouts and a lost connection come only
        through the future.

        The future fails with the PropertyError of an ERR reply, with
        DeadlineExceeded when no reply came in ``deadline_s`` seconds, with
        Unavailable when the connection closes. Returns None, sending
        nothing, when the device has no room for it now (:meth:`request`
        waits for room). Raises Unavailable on a closed connection and
        PropertyError for a frame that cannot be written.
        """
        tag, line = self._prepare(frame)
        if not self._fits(len(line)):
            return None
        self._take(len(line))
        return self._issue(frame, tag, line, deadline_s, self._loop.time() + deadline_s, then=then)

    async def request(self, frame: Request, deadline_s: float) -> Frame:
        """Send ``frame`` under a fresh tag and return the reply frame (Ok, Pong or Hello).

        An ERR reply is raised as the PropertyError of its code; no reply in
        ``deadline_s`` seconds raises DeadlineExceeded; a closed connection
        raises Unavailable.
        """
        tag, line = self._prepare(frame)
        deadline = self._loop.time() + deadline_s
        if self._fits(len(line)):
            self._take(len(line))
        else:
            await self._wait_room(len(line), deadline, deadline_s)
        return await self._issue(frame, tag, line, deadline_s, deadline)

    def _line_limit(self) -> int:
        """The longest line the device takes: min(maxline, rxbuf) (docs/device-spec.md §5.2)."""
        return self.max_line if self.rxbuf is None else min(self.max_line, self.rxbuf)

    def largest_binary(self, path: str) -> int:
        """The most bytes a value of ``path`` can carry, both ways: as ``\\=`` base64 on one line.

        The longer of the two lines is the gateway's ``#TAG SET PATH \\=...`` (to the device, at most
        its line limit) beside the device's ``#TAG OK \\=...`` (from it, at most ``maxline``),
        each with room for a checksum and the LF.
        """
        overhead = len(f"#{2**32} SET {path} \\=") + len("*HH\n")
        room = min(self._line_limit(), self._receiver.max_line) - overhead
        return max(0, room // 4 * 3)

    def _prepare(self, frame: Request) -> tuple[str, bytes]:
        """A fresh tag and the line of ``frame`` under it; PropertyError when it cannot be sent."""
        if self._closed.is_set():
            raise Unavailable(f"{self.label}: {self._close_reason}")
        self._next_tag = tag_number = (self._next_tag + 1) & _TAG_MASK
        tag = format(tag_number, "x")
        limit = self._line_limit()
        try:
            line = encode(
                _with_tag(frame, tag),
                checksum=self._checksum,
                max_line=limit - (_WIDEST_TAG_DIGITS - len(tag)),
            )
        except LineProtocolError as exc:
            reason = exc.message
            if exc.code == Code.RESOURCE_EXHAUSTED:
                widest = encode(
                    _with_tag(frame, "f" * _WIDEST_TAG_DIGITS), checksum=self._checksum, max_line=1 << 30
                )
                reason = f"line too long: {len(widest)} bytes with the longest tag, the device takes {limit}"
            message = f"{self.label}: cannot send the request: {reason}"
            value = frame.value if isinstance(frame, Set) else None
            if isinstance(value, bytes) and exc.code == Code.RESOURCE_EXHAUSTED:
                message += (
                    f" (a binary value of {len(value)} bytes is {4 * -(-len(value) // 3)} characters "
                    "of base64 on the line, docs/line-protocol.md §11)"
                )
            raise error_for(exc.code, message) from None
        return tag, line

    def _fits(self, size: int) -> bool:
        if self._room_waiters:
            return False  # others wait already: they go first
        return self._room_for(size)

    def _room_for(self, size: int) -> bool:
        if self._in_flight >= self.inflight_limit:
            return False
        return self.rxbuf is None or self._in_flight == 0 or self._in_flight_bytes + size <= self.rxbuf

    def _take(self, size: int) -> None:
        self._in_flight += 1
        self._in_flight_bytes += size

    def _issue(
        self,
        frame: Request,
        tag: str,
        line: bytes,
        timeout: float,
        deadline: float,
        *,
        then: Callable[[Frame], None] | None = None,
    ) -> asyncio.Future[Frame]:
        """Send ``line`` in the room the caller holds; the reply or the timeout frees the room."""
        if self._closed.is_set():
            self._release(len(line))
            raise Unavailable(f"{self.label}: {self._close_reason}")
        future: asyncio.Future[Frame] = self._loop.create_future()
        pending = _Pending(future, tag, deadline, timeout, line)
        pending.then = then
        self._pending[tag] = pending
        self._add_deadline(pending)
        if type(frame) is Set and not self.flow_controlled:
            pending.cancel_when_abandoned = True
            future.add_done_callback(lambda done: self._abandoned(done, tag))
        if log.isEnabledFor(logging.DEBUG):
            # The tag ties the device's reply to this line, the request id to the client's call.
            log.debug(
                "%s: sent %r%s as tag %s for request %s",
                self.label,
                line[:LOGGED_LINE_BYTES],
                f" ({len(line) - LOGGED_LINE_BYTES} more bytes)" if len(line) > LOGGED_LINE_BYTES else "",
                tag,
                current_request_id() or "(none)",
            )
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
        # (docs/line-protocol.md §7). Once per request; never under flow control.
        if not pending.cancel_when_abandoned or self._closed.is_set():
            return
        pending.cancel_when_abandoned = False
        with contextlib.suppress(LineProtocolError):
            self._send(Cancel(tag))

    # -- deadlines: one timer for the connection ------------------------------

    def _add_deadline(self, pending: _Pending) -> None:
        deadlines = self._deadlines
        if len(deadlines) > 2 * len(self._pending) + _STALE_DEADLINES:
            # Mostly answered requests: keep only those in flight (amortised: once per that many).
            self._deadlines = deadlines = [entry for entry in deadlines if self._live(entry[2])]
            heapq.heapify(deadlines)
        self._issued += 1
        heapq.heappush(deadlines, (pending.deadline, self._issued, pending))
        if self._timer is None or pending.deadline < self._timer_at:
            self._arm(pending.deadline)

    def _live(self, pending: _Pending) -> bool:
        return self._pending.get(pending.tag) is pending

    def _arm(self, when: float) -> None:
        if self._timer is not None:
            self._timer.cancel()
        self._timer = self._loop.call_at(when, self._expire_due)
        self._timer_at = when

    def _stop_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _expire_due(self) -> None:
        """The timer: every request whose deadline has come fails; then the timer is armed again."""
        self._timer = None
        deadlines = self._deadlines
        now = self._loop.time()
        while deadlines and (deadlines[0][0] <= now or not self._live(deadlines[0][2])):
            _, _, pending = heapq.heappop(deadlines)
            if self._live(pending):
                self._expire(pending)
        if deadlines and self._timer is None and not self._closed.is_set():
            self._arm(deadlines[0][0])

    def _expire(self, pending: _Pending) -> None:
        tag = pending.tag
        del self._pending[tag]
        # A request not answered in time is taken as lost: its room is free again (§7).
        self._release(len(pending.line))
        self._send_cancel(pending, tag)
        if not pending.future.done():
            self._drop_stale_half_line(pending.timeout)
            pending.future.set_exception(
                DeadlineExceeded(f"{self.label}: no reply within {pending.timeout:g} s")
            )

    async def _wait_room(self, size: int, deadline: float, limit_s: float) -> None:
        loop = self._loop
        waiter: asyncio.Future[None] = loop.create_future()
        entry = (waiter, size)
        self._room_waiters.append(entry)
        timer = loop.call_at(deadline, _time_out, waiter)
        try:
            await waiter
        except TimeoutError:
            raise DeadlineExceeded(f"{self.label}: too many requests in flight for {limit_s:g} s") from None
        except BaseException:
            if waiter.done() and not waiter.cancelled() and waiter.exception() is None:
                self._release(size)  # handed room just as the caller gave up: pass it on
            raise
        finally:
            timer.cancel()
            with contextlib.suppress(ValueError):
                self._room_waiters.remove(entry)
            self._hand_room()

    def _release(self, size: int) -> None:
        self._in_flight = max(0, self._in_flight - 1)
        self._in_flight_bytes = max(0, self._in_flight_bytes - size)
        self._hand_room()

    def _hand_room(self) -> None:
        """Give the room there is to the waiting requests, oldest first."""
        waiters = self._room_waiters
        while waiters:
            waiter, size = waiters[0]
            if waiter.done():
                waiters.popleft()
                continue
            if not self._room_for(size):
                return
            waiters.popleft()
            self._take(size)
            waiter.set_result(None)

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

    def ask_hello(self, answer_within: float = ASKED_GREETING_WINDOW_S) -> None:
        """Ask the device to introduce itself (a serial device greeted long before the port was opened).

        An untagged greeting within ``answer_within`` seconds, and before the device has
        answered any other request, is taken as the answer (even after the device greeted by
        itself), never as a restart.
        """
        with contextlib.suppress(LineProtocolError):
            self._send(HelloRequest())
            self._asked_greetings += 1
            self._asked_until = self._loop.time() + answer_within

    def _answers_a_hello(self) -> bool:
        """Whether an untagged greeting, arriving now, answers a HELLO the gateway sent."""
        if self._asked_greetings and self._loop.time() <= self._asked_until:
            self._asked_greetings -= 1
            return True
        self._asked_greetings = 0
        return False

    # -- receiving ---------------------------------------------------------

    def _handle(self, frame: Frame | BadLine, checked: bool = False) -> None:
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
                if reply.code == Code.DATA_LOSS:  # type: ignore[union-attr]
                    # Bytes lost on the way in (an overrun, a checksum that failed): the device
                    # cannot say whose line it was, so every request in flight may be lost (§8).
                    self._resend_all(f"the device lost bytes ({reply.message})")  # type: ignore[union-attr]
                return
        elif kind is Event or kind is Gone:
            try:
                self._on_event(frame)  # type: ignore[arg-type]
            except Exception:
                log.exception("%s: event handler failed on %r", self.label, frame)
            return
        elif kind is Ping:
            self._answer(Pong(frame.data, frame.tag), checked)  # type: ignore[union-attr]
            return
        elif kind is BadLine:
            self._bad_line(frame)  # type: ignore[arg-type]
            return
        elif kind is Get or kind is Set or kind is Listen or kind is Unlisten or kind is HelloRequest:
            # The device asks something on a connection where the gateway is the client
            # (docs/device-spec.md §3.9).
            tag = frame.tag  # type: ignore[union-attr]
            log.info(
                "%s: the device sent a request (%s); told it is not served here", self.label, kind.__name__
            )
            self._answer(ErrorReply(int(Code.UNIMPLEMENTED), _NOT_SERVED, tag), checked)
            return
        log.warning("%s: unexpected line from the device ignored: %r", self.label, frame)

    def _answer(self, reply: Pong | ErrorReply, checksummed: bool = False) -> None:
        """Answer a line of the device: with a checksum when the device uses them (mirrored, spec §6.4)."""
        checksum = self._checksum or checksummed
        try:
            line = encode(reply, checksum=checksum, max_line=self._line_limit())
        except LineProtocolError:  # too long for the device: the code alone still fits
            if type(reply) is not ErrorReply:
                return
            line = encode(ErrorReply(reply.code, "", reply.tag), checksum=checksum)
        self._write_line(line)

    def _resolve(self, reply: Ok | ErrorReply | Pong | Hello, tag: str) -> None:
        pending = self._pending.pop(tag, None)
        if type(reply) is Hello:
            self._greeted(reply)
        elif pending is not None:
            # A device answers in order: once it answered a later request, the answer to the
            # gateway's HELLO is behind, and an untagged greeting from now on is a restart. (A
            # reply to no request of this connection, one a board sent before it was reset as the
            # port opened, says nothing about that.)
            self._asked_greetings = 0
        if pending is None:
            if type(reply) is not Hello:
                log.info("%s: reply for tag #%s came too late or was not asked for; ignored", self.label, tag)
            return
        self._release(len(pending.line))
        future = pending.future
        if future.done():
            return
        if type(reply) is ErrorReply:
            future.set_exception(reply.to_exception())
            return
        then = pending.then
        if then is not None:
            try:
                then(reply)
            except Exception:
                log.exception("%s: the receiver of the reply to tag #%s failed", self.label, tag)
        future.set_result(reply)

    def _greeted(self, hello: Hello) -> None:
        if hello.version != PROTOCOL_VERSION:
            self._refuse(
                FailedPrecondition(
                    f"line protocol version {hello.version} is not supported; "
                    f"this gateway speaks version {PROTOCOL_VERSION} ({PROTOCOL_REVISION})"
                ),
                hello.tag,
            )
            return
        restarted = self.hello.done() and hello.tag is None and not self._answers_a_hello()
        if restarted:
            self._lost_everything("the device restarted (it greeted again)")
        self.max_line = hello.max_line
        ceiling = self._ceiling
        if hello.inflight is not None:
            self.inflight_limit = min(hello.inflight, ceiling)
        else:
            # A serial device that states neither field gets one request at a time (docs/device-spec.md §5.3).
            self.inflight_limit = 1 if self._serial and hello.rxbuf is None else ceiling
        self.rxbuf = hello.rxbuf
        self._hand_room()
        if not self.hello.done():
            self.hello.set_result(hello)
        elif restarted:
            log.warning("%s: the device restarted; its listens are restored", self.label)
            if self._on_restart is not None:
                try:
                    self._on_restart(hello)
                except Exception:
                    log.exception("%s: restart handler failed", self.label)

    def _resend_all(self, why: str) -> None:
        """Every request in flight may have been lost: send each again, or fail it (see _resend)."""
        for pending in list(self._pending.values()):
            if self._pending.get(pending.tag) is pending:
                self._resend(pending, why)

    def _resends_of(self, tag: str) -> int:
        """How many times the request of ``tag`` has been sent again; answered ones are forgotten
        here, so the count never holds more than the requests in flight."""
        resent = self._resent
        if len(resent) > len(self._pending):
            self._resent = resent = {t: n for t, n in resent.items() if t in self._pending}
        return resent.get(tag, 0)

    def _resend(self, pending: _Pending, why: str) -> None:
        """Send the line of ``pending`` again, under its own tag, in the room it holds already.

        Whichever reply comes first answers the call; a second one is ignored as late. A request
        that has been sent again :data:`RESENDS` times, or a SET, fails at once with DATA_LOSS
        instead: a SET may have been applied before its reply was lost, and applying it twice
        may not be harmless (a Set can be an action), so its caller is told, at once rather than
        at its deadline, to read the property before it sets it again (§8).
        """
        future = pending.future
        if future.done():
            return
        tag = pending.tag
        is_set = _is_set(pending.line)
        resends = self._resends_of(tag)
        if resends < RESENDS and not is_set:
            self._resent[tag] = resends + 1
            log.info("%s: request #%s sent again: %s", self.label, tag, why)
            self._write_line(pending.line)
            return
        del self._pending[tag]
        self._resent.pop(tag, None)
        self._release(len(pending.line))
        if is_set:
            message = f"{self.label}: {why}; the SET may or may not have been applied: read it back"
        else:
            message = f"{self.label}: {why}, again after {RESENDS} resends"
        future.set_exception(DataLoss(message))

    def _lost_everything(self, reason: str) -> None:
        """Every unanswered request is lost (the device restarted): fail them, free their room."""
        pending, self._pending = self._pending, {}
        self._deadlines.clear()
        self._stop_timer()
        for entry in pending.values():
            if not entry.future.done():
                entry.future.set_exception(Unavailable(f"{self.label}: {reason}"))
        self._in_flight = 0
        self._in_flight_bytes = 0

    def _refuse(self, error: PropertyError, tag: str | None, checksummed: bool = False) -> None:
        """Refuse the device's greeting: an ERR line to it, the refusal to whoever waits, then close."""
        log.error("%s: refused: %s", self.label, error.message)
        self._answer(ErrorReply.from_exception(error, tag), checksummed)
        refusal = error_for(error.code, f"{self.label}: the device was refused: {error.message}")
        if not self.hello.done():
            self.hello.set_exception(refusal)
        # Close once the ERR line is on its way (close() would drop lines not flushed yet).
        self._loop.call_soon(self._close_after_refusal, error.message)

    def _close_after_refusal(self, message: str) -> None:
        self.flush()
        self.close(f"the device was refused: {message}")

    def _bad_line(self, bad: BadLine) -> None:
        if bad.greeting:
            self._refuse(error_for(bad.code, bad.message), bad.tag, bad.checksummed)
            return
        log.warning(
            "%s: bad line from the device%s: %s",
            self.label,
            f" (reply to #{bad.tag})" if bad.tag else "",
            bad.message,
        )
        if bad.tag is None:
            if bad.code == Code.DATA_LOSS:
                # A line whose checksum failed: its tag cannot be trusted, so it may have been
                # the reply to any request in flight.
                self._resend_all(f"a reply arrived damaged ({bad.message})")
            return
        pending = self._pending.get(bad.tag)
        if pending is None:
            return
        if bad.code != Code.RESOURCE_EXHAUSTED:
            self._resend(pending, f"the device sent a malformed reply: {bad.message}")
            return
        # A reply too long would come back as long: no use asking again.
        del self._pending[bad.tag]
        self._release(len(pending.line))
        if not pending.future.done():
            pending.future.set_exception(
                ResourceExhausted(
                    f"{self.label}: the device's reply was too long: {bad.message} (the proxy option "
                    f"maxline, now {self._receiver.max_line}, is the longest line taken from the device)"
                )
            )


def _is_set(line: bytes) -> bool:
    """Whether ``line`` (as sent, LF included) is a SET: read from the line, since a fault is rare
    and a request that carries no field for it costs nothing on the way that is not."""
    try:
        return type(decode_line(line[:-1], max_line=len(line))) is Set
    except LineProtocolError:  # never for a line the connection wrote; never sent again if it were
        return True


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
