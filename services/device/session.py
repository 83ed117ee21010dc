"""One line-protocol connection served by one backend: the device side of docs/device-spec.md.

Requests with a tag run concurrently (bounded), untagged requests one at a
time; events for a client that reads slowly are conflated per property in a
bounded outbox, so memory never grows with a slow reader.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from collections.abc import Callable, Coroutine
from typing import Any

from services.device.outbox import Outbox
from services.kernel.backend import Backend, Change, Subscription, close_quietly
from services.kernel.eager import Started, step
from services.kernel.errors import Code, DeadlineExceeded, NotFound, PropertyError, ResourceExhausted
from services.kernel.line_protocol import (
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
    Set,
    Unlisten,
    encode,
)
from services.kernel.model import ServiceModel
from services.kernel.model_codec import HINT_TAGS, MODEL_PATH, model_to_text
from services.kernel.values import Value

__all__ = [
    "CALL_TIMEOUT",
    "KEEPALIVE_TIMEOUT",
    "MAX_IN_FLIGHT",
    "MAX_QUEUED_REPLIES",
    "MAX_QUEUED_REPLY_BYTES",
    "MAX_SUBSCRIPTIONS",
    "READ_SIZE",
    "DeviceSession",
]

log = logging.getLogger(__name__)

#: Requests with a tag that one connection may have running at once; further
#: lines are not read until one finishes (backpressure instead of memory).
MAX_IN_FLIGHT = 32
#: Properties one connection may listen to; each costs one outbox slot.
MAX_SUBSCRIPTIONS = 256
#: Replies waiting to be written before the session stops reading (a client
#: that sends bad lines but never reads must not grow the outbox).
MAX_QUEUED_REPLIES = 256
#: The same in bytes: replies that carry binary values are long lines (docs/line-protocol.md
#: §11), and 256 of them could hold a gigabyte. 8 MiB holds one line of the longest kind. What
#: waits is then at most this, the batch the writer holds, and the replies of the requests
#: running (MAX_IN_FLIGHT).
MAX_QUEUED_REPLY_BYTES = 8 * 1024 * 1024
#: A backend call that takes longer gets DEADLINE_EXCEEDED.
CALL_TIMEOUT = 10.0
#: Bytes asked of a stream per read (and the stream reader's buffer limit).
READ_SIZE = 65536
#: Seconds the peer has to answer the device's keep-alive PING (its PONG, or any other line).
KEEPALIVE_TIMEOUT = 3.0


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
        on_greeting: Callable[[Hello], None] | None = None,
        keepalive: float = 0.0,
        keepalive_timeout: float = KEEPALIVE_TIMEOUT,
    ) -> None:
        """``on_greeting`` hears the peer's greeting (a gateway's line listener greets a device that
        dialled it, and may name other gateways to dial when it is gone, docs/line-protocol.md §5).
        ``keepalive``: after that many seconds without a line from the peer, the device sends
        ``PING``, and ends the connection when nothing comes back within ``keepalive_timeout``
        (a peer that is frozen keeps its TCP connection open, docs/line-protocol.md §9); 0: never."""
        self.backend = backend
        self.reader = reader
        self.writer = writer
        self.greeting = greeting
        self.checksum = checksum
        self.call_timeout = call_timeout
        self.peer = peer or str(writer.get_extra_info("peername") or "?")
        self._on_greeting = on_greeting
        self.keepalive = keepalive
        self.keepalive_timeout = keepalive_timeout
        #: Loop time of the last bytes from the peer (the keep-alive's measure of silence).
        self._heard = 0.0
        self._receiver = LineReceiver(max_line=greeting.max_line)
        self._send_limit = max(MAX_LINE, greeting.max_line)
        self._outbox = Outbox()
        self._subscriptions: dict[str, Subscription] = {}
        # A device that states inflight=N takes no more than N requests at once (docs/device-spec.md §5).
        self._in_flight = asyncio.Semaphore(min(greeting.inflight or MAX_IN_FLIGHT, MAX_IN_FLIGHT))
        self._tasks: set[asyncio.Task[None]] = set()
        #: SETs running now by tag, so that a CANCEL can stop one still waiting on its backend.
        self._running_sets: dict[str, asyncio.Task[None]] = {}
        self._step_gets = backend.answers_inline
        #: A good $-line came, and no plain HELLO since: every line goes out checksummed
        #: (docs/device-spec.md §6.5).
        self._checksum_mode = False

    # -- writing ---------------------------------------------------------

    def _encode(self, frame: Frame, checksummed: bool = False) -> bytes:
        # Checksum mode (after a good $-line), or the reply to a $-line: mirrored (docs/device-spec.md
        # §6.4, §6.5). Lines out are bounded by the client's limit, which a device is not told: the
        # protocol's 1024 bytes, or this device's own when larger (a peer that takes long lines,
        # docs/line-protocol.md §11).
        return encode(
            frame, checksum=self.checksum or self._checksum_mode or checksummed, max_line=self._send_limit
        )

    def _reply(self, frame: Frame, checksummed: bool = False) -> None:
        try:
            line = self._encode(frame, checksummed)
        except LineProtocolError as exc:
            tag = getattr(frame, "tag", None)
            line = self._encode(
                ErrorReply(int(exc.code), f"cannot send the reply: {exc.message}", tag), checksummed
            )
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
        loop = asyncio.get_running_loop()
        self._heard = loop.time()
        watchdog = asyncio.create_task(self._keep_alive()) if self.keepalive > 0 else None
        try:
            self._reply(self.greeting)
            while True:
                try:
                    data = await self.reader.read(READ_SIZE)
                except (ConnectionError, OSError) as exc:
                    log.info("%s: connection lost: %s", self.peer, exc)
                    break
                if not data:
                    break
                self._heard = loop.time()
                frames = self._receiver.receive_data(data)
                checked = dict(zip(map(id, frames), self._receiver.last_checked, strict=True))
                for frame in self._not_cancelled(frames):
                    # Room is checked line by line: one read may hold thousands of GETs, and each
                    # reply may carry a long binary value.
                    if not await self._room(writer_task):
                        break
                    await self._dispatch(frame, checked[id(frame)])
                if not await self._room(writer_task):
                    break
        finally:
            if watchdog is not None:
                watchdog.cancel()
                await asyncio.gather(watchdog, return_exceptions=True)
            await self._shutdown(writer_task)

    async def _keep_alive(self) -> None:
        """PING a peer silent for ``keepalive`` seconds; end the connection when it stays silent."""
        loop = asyncio.get_running_loop()
        while True:
            silent = loop.time() - self._heard
            if silent < self.keepalive:
                await asyncio.sleep(self.keepalive - silent)
                continue
            asked = loop.time()
            self._reply(Ping("keepalive"))
            await asyncio.sleep(self.keepalive_timeout)
            if self._heard < asked:
                log.warning(
                    "%s: no answer to a keep-alive PING within %g s; ending the connection",
                    self.peer,
                    self.keepalive_timeout,
                )
                self.writer.transport.abort()  # the read sees the end; the session closes as on EOF
                return

    async def _room(self, writer_task: asyncio.Task[None]) -> bool:
        """Wait while the replies not yet written are too many or too long; False once the writer stopped."""
        outbox = self._outbox
        while (
            len(outbox.replies) >= MAX_QUEUED_REPLIES or outbox.reply_bytes >= MAX_QUEUED_REPLY_BYTES
        ) and not writer_task.done():
            outbox.room.clear()
            await outbox.room.wait()  # set by the writer when it takes replies or stops
        return not writer_task.done()

    def _not_cancelled(self, frames: list[Frame | BadLine]) -> list[Frame | BadLine]:
        """The frames of one read, less every SET that a CANCEL in the same read takes back.

        A device that was frozen (or busy) finds the SET and the client's
        CANCEL of it waiting together: the SET must not be applied.
        """
        cancelled = {f.tag for f in frames if type(f) is Cancel}
        if not cancelled:
            return frames
        kept: list[Frame | BadLine] = []
        for frame in frames:
            if type(frame) is Set and frame.tag in cancelled:
                log.info(
                    "%s: SET %s (#%s) cancelled by the client before it started",
                    self.peer,
                    frame.path,
                    frame.tag,
                )
                continue
            kept.append(frame)
        return kept

    def _track_set(self, tag: str, task: asyncio.Task[None]) -> None:
        self._running_sets[tag] = task
        task.add_done_callback(lambda _: self._running_sets.pop(tag, None))

    def _cancel(self, tag: str | None) -> None:
        task = self._running_sets.get(tag) if tag is not None else None
        if task is not None:
            task.cancel()  # still waiting on the backend: whether it took effect is the backend's
            log.info("%s: SET #%s cancelled by the client while running", self.peer, tag)

    async def _shutdown(self, writer_task: asyncio.Task[None]) -> None:
        for task in list(self._tasks):
            task.cancel()
        writer_task.cancel()
        await asyncio.gather(writer_task, *self._tasks, return_exceptions=True)
        subscriptions, self._subscriptions = list(self._subscriptions.values()), {}
        for sub in subscriptions:
            await close_quietly(sub)
        try:
            self.writer.close()
        except OSError as exc:  # the connection is gone already
            log.debug("%s: closing: %s", self.peer, exc)

    async def _dispatch(self, frame: Frame | BadLine, checked: bool = False) -> None:
        if checked and not isinstance(frame, BadLine):
            self._checksum_mode = True
        elif not checked and isinstance(frame, HelloRequest):
            self._checksum_mode = False  # a client starting afresh, e.g. a serial port opened again
        if isinstance(frame, BadLine):
            log.info("%s: bad line: %s", self.peer, frame.message)
            self._reply(ErrorReply(int(frame.code), frame.message, frame.tag), checked)
        elif isinstance(frame, Ping):
            self._reply(Pong(frame.data, frame.tag), checked)
        elif isinstance(frame, HelloRequest):
            self._reply(dataclasses.replace(self.greeting, tag=frame.tag), checked)
        elif isinstance(frame, Get | Set | Listen | Unlisten):
            if frame.tag is None:
                await self._answer(frame)
                return
            started: Started[Value] | None = None
            if type(frame) is Get and self._step_gets and frame.path != MODEL_PATH:
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
            if type(frame) is Set:
                self._track_set(frame.tag, task)
        elif isinstance(frame, Cancel):
            self._cancel(frame.tag)  # no reply: the client has stopped waiting for this tag
        elif isinstance(frame, Hello):
            if self._on_greeting is not None:  # a client introducing itself: nothing to answer
                self._on_greeting(frame)
        elif isinstance(frame, Pong):
            pass  # answer to a PING of ours
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
        started: Started[Value] | None = None,
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

    async def _call(self, frame: Get | Set | Listen | Unlisten) -> Value:
        backend = self.backend
        if isinstance(frame, Get):
            if frame.path == MODEL_PATH and not frame.params:
                return self._model_reply(await backend.describe(), frame.tag)
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

    def _model_reply(self, model: ServiceModel, tag: str | None) -> str:
        """The device describes itself (docs/device-spec.md §9): the model in one reply line.

        A model too long for a line goes without its docs, then without the tags that only say
        how to show a value (resolution, then gui), then without any tags (length, choices,
        value, parameters); one still too long is NOT_FOUND, as from a device that does not
        describe itself. Each form is measured as the reply line it becomes (this tag, a
        checksum whether or not one is asked for), not against a guess.
        """
        # Widest first: docs and tags; then tags without docs, the hints dropped one by one; then
        # the names, types and bounds alone.
        forms = [(True, True, HINT_TAGS)] + [(False, True, HINT_TAGS[i:]) for i in range(len(HINT_TAGS) + 1)]
        for docs, tags, hints in [*forms, (False, False, ())]:
            text = model_to_text(model, docs=docs, tags=tags, hints=hints)
            try:
                encode(Ok(text, tag), checksum=True, max_line=MAX_LINE)
            except LineProtocolError:
                continue
            return text
        raise NotFound(f"{MODEL_PATH}: a model of {len(model.properties)} properties does not fit in a line")

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
