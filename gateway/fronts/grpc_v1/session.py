"""The Session call: many Get, Set and Listen requests over one bidirectional stream.

One reader task parses incoming ``SessionRequest``s; the handler's own task
is the writer, draining the reply queue and every ready Listen into one
``SessionResponse`` per wake-up. A Get or Set is started right in the reader,
translated into the engine's types, and read through its one
:class:`~gateway.engine.handle.CallHandle`: answered at once when it is done
(an in-process service usually answers without waiting, so it costs no task),
else answered from the handle's done-callback. Once the requests of a message
are started, every backend they went to sends what it holds
(:meth:`services.kernel.backend.Backend.flush`: a device gets the message's lines in
one write). At most ``limits.session_max_in_flight``
run at once and at most ``limits.session_max_queued_replies`` wait to be
written; beyond either, the reader stops reading (backpressure). A Listen's
large value counts against the hub's budget while it is written, as a gRPC
Listen's does (:mod:`gateway.engine.listen.budget`); one that does not fit ends that
Listen with RESOURCE_EXHAUSTED, and the Session goes on.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import secrets
from collections import deque
from collections.abc import Coroutine, Mapping
from typing import Any

import grpc

from gateway.config import Limits
from gateway.engine.calls import Calls
from gateway.engine.handle import CallHandle
from gateway.engine.identity import ANONYMOUS
from gateway.engine.listen import ListenHub, ListenStream
from gateway.engine.listen.budget import COUNTED_BYTES, GRPC_COPIES
from gateway.engine.listen.drain import Wake
from gateway.engine.listen.hub import SHUTTING_DOWN
from gateway.engine.rules import Subject
from gateway.engine.sizes import BATCH_BYTES, SURELY_FITS_CHARS, check_fits, reply_size
from gateway.engine.status import to_property_error
from gateway.engine.types import GetCall, is_snapshot
from gateway.fronts.grpc_v1.listen_encoding import (
    listen_reply_wire,
    listen_request,
    listen_response,
    reply_wire,
    take_wire,
)
from gateway.fronts.grpc_v1.messages import Undecodable, get_call, get_response, set_call
from gateway.fronts.grpc_v1.status import abort, status_message
from gateway.logs import RequestContext, current_request
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.backend import NO_PARAMS, Backend
from services.kernel.eager import Started, step
from services.kernel.errors import Code, InvalidArgument, NotFound, PropertyError, Unavailable
from services.kernel.values import Value, value_size

log = logging.getLogger(__name__)

#: Replies in one SessionResponse; bounds one message's size.
MAX_REPLIES_PER_MESSAGE = 1024


async def _finish(started: Started[None]) -> None:
    await started.rest()


class _Ready:
    """What a Listen of a Session calls when it has something to send: the Session marks it ready.

    One per Listen: a slotted instance is a quarter of the size of a closure over ``rid``.
    """

    __slots__ = ("rid", "session")

    def __init__(self, session: Session, rid: int) -> None:
        self.session = session
        self.rid = rid

    def __call__(self) -> None:
        self.session._ready_listen(self.rid)


class _Answered:
    """What a pending call's handle calls once it is done: the Session answers the request."""

    __slots__ = ("kind", "params", "path", "rid", "service", "session")

    def __init__(
        self, session: Session, rid: int, kind: str, service: str, path: str, *, params: Mapping[str, str]
    ) -> None:
        self.session = session
        self.rid = rid
        self.kind = kind
        self.service = service
        self.path = path
        self.params = params

    def __call__(self, handle: CallHandle) -> None:
        self.session._answered(self.rid, handle, self.kind, self.service, self.path, params=self.params)


class Session:
    """The state of one Session call: :meth:`run` serves it until the client half-closes,
    disconnects, or the gateway stops (:meth:`stop`)."""

    def __init__(
        self,
        calls: Calls,
        hub: ListenHub,
        limits: Limits,
        context: grpc.aio.ServicerContext[Any, Any],
        subject: Subject = ANONYMOUS,
        *,
        logged: RequestContext | None = None,
        requests: dict[str, int] | None = None,
    ) -> None:
        """``subject``: who opened the Session; every request in it is checked as theirs.

        ``logged``: the stream's log context; request ``N`` in it logs as ``STREAM_ID/N``.
        ``requests``: counts of the requests read, by call (``get``, ``set``, ``listen``, ``cancel``,
        ``none``), raised here for the metrics; None counts nothing."""
        self._logged = logged
        #: Marked with this Session's token: an anonymous caller holds licences under it.
        self._subject = dataclasses.replace(subject, session=secrets.token_hex(8))
        self._calls = calls
        #: The source time of a value a Get read (Calls.value_time), looked up once.
        self._value_time = calls.value_time
        self._hub = hub
        self._context = context
        self._limits = limits
        self._timeout = calls.timeout
        #: Replies waiting to be written, each with its size in bytes (at most a few bytes over).
        self._replies: deque[tuple[pb.Reply, int]] = deque()
        #: The writer's wake-up; one waiter, so the lighter Wake rather than an asyncio.Event.
        self._wake = Wake()
        self._room = asyncio.Event()
        self._room.set()
        #: ids of Gets and Sets running in a task, and of Listens (starting or live).
        self._active: set[int] = set()
        self._tasks: dict[int, asyncio.Future[Any] | CallHandle] = {}
        #: The backends of the calls started from the message being read, told to flush after it.
        self._started_on: set[Backend] = set()
        self._listens: dict[int, ListenStream] = {}
        self._ready: dict[int, None] = {}
        #: ids of Listens still starting (their task is in _tasks).
        self._starting: set[int] = set()
        self._reader_done = False
        self._stopping = False
        #: The call ends with this status (a message that did not parse).
        self._error: PropertyError | None = None
        self._requests = requests
        #: Bytes of the message being written counted against the hub's budget (its large Listen values).
        self._held = 0

    @property
    def error(self) -> PropertyError | None:
        """The status the call ends with when it is not OK (a message that did not parse)."""
        return self._error

    @property
    def listen_count(self) -> int:
        """Listens open in this Session."""
        return len(self._listens)

    @property
    def queued_replies(self) -> int:
        """Replies waiting to be written (bounded by ``limits.session_max_queued_replies``)."""
        return len(self._replies)

    # -- the writer (the handler's task) ------------------------------------

    async def run(self) -> None:
        reader = asyncio.get_running_loop().create_task(self._read())
        context = self._context
        wake = self._wake
        try:
            # The writer, written out here rather than in a coroutine of its own: one coroutine
            # less to resume for every message written.
            while True:
                await wake.wait()
                if self._stopping or (self._reader_done and self._listens):
                    self._end_listens()
                response = self._collect()
                if response:
                    await context.write(response)
                    if self._held:
                        self._hub.budget.give_back(self._held)
                        self._held = 0
                    if self._replies or self._ready:
                        wake.set()
                if len(self._replies) < self._limits.session_max_queued_replies:
                    self._room.set()
                if self._stopping and not self._replies:
                    break
                if self._reader_done and not self._active and not self._replies and not self._ready:
                    break
            if self._error is not None:
                await abort(self._context, self._error, "Session")
        finally:
            self._hub.budget.give_back(self._held)  # a message the client never took
            self._held = 0
            reader.cancel()
            for task in list(self._tasks.values()):
                task.cancel()
            for stream in self._listens.values():
                stream.close()
            self._listens.clear()
            await asyncio.gather(reader, *self._tasks.values(), return_exceptions=True)
            # Its holder vanished: the licences acquired on this Session end with it.
            self._calls.session_ended(self._subject)

    def _collect(self) -> bytes:
        """The next SessionResponse, serialized ("" when there is nothing to send): at most
        MAX_REPLIES_PER_MESSAGE replies, about BATCH_BYTES.

        A reply bigger than the budget goes alone: a client drops the whole stream on a message
        over its limit (4 MiB by default), so batching must never add up to one. The Listens'
        replies are added serialized (``listen_encoding.take_wire``): a repeated field's entries
        may follow one another on the wire, so they are appended to the other replies' message.
        """
        replies: list[pb.Reply] = []
        size = 0
        queue = self._replies
        while queue and len(replies) < MAX_REPLIES_PER_MESSAGE:
            n = queue[0][1]
            if replies and size + n > BATCH_BYTES:
                return pb.SessionResponse(replies=replies).SerializeToString()
            size += n
            replies.append(queue.popleft()[0])
        count = len(replies)
        listened: list[bytes] = []
        for rid in list(self._ready):
            stream = self._listens.get(rid)
            if stream is None:
                del self._ready[rid]
                continue
            drained = False
            while size < BATCH_BYTES and count < MAX_REPLIES_PER_MESSAGE:
                response = take_wire(stream)
                if response is None:
                    drained = True
                    break
                reply = listen_reply_wire(rid, response)
                if len(reply) >= COUNTED_BYTES and not self._counted(rid, len(reply), listened):
                    break  # that Listen is ended; the others' replies go in the next message
                size += len(reply)
                count += 1
                listened.append(reply)
            if not drained:
                break  # the rest goes in the next message; rid stays ready
            del self._ready[rid]
            if stream.error is not None:
                listened.append(reply_wire(pb.Reply(id=rid, status=status_message(stream.error))))
                self._drop_listen(rid)
            elif stream.ended and not self._stopping:
                self._drop_listen(rid)
        head = pb.SessionResponse(replies=replies).SerializeToString() if replies else b""
        return head + b"".join(listened) if listened else head

    def _counted(self, rid: int, size: int, listened: list[bytes]) -> bool:
        """Count a large Listen reply against the hub's budget until it is written, as a gRPC
        Listen counts its message; when it does not fit, end Listen ``rid`` with the refusal."""
        budget = self._hub.budget
        counted = GRPC_COPIES * size
        if budget.take(counted):
            self._held += counted
            return True
        refusal = budget.refusal(counted, "Listen")
        listened.append(reply_wire(pb.Reply(id=rid, status=status_message(refusal))))
        self._drop_listen(rid)
        return False

    def _end_listens(self) -> None:
        """Flush what every Listen has ready and end it (half-close or shutdown)."""
        for rid, stream in list(self._listens.items()):
            while (taken := stream.take()) is not None:
                reply = pb.Reply(id=rid, listen=listen_response(taken))
                self._replies.append((reply, reply.ByteSize()))
            self._drop_listen(rid)
        for rid in list(self._starting):
            task = self._tasks.get(rid)
            if task is not None:
                task.cancel()
        self._ready.clear()

    def _drop_listen(self, rid: int) -> None:
        stream = self._listens.pop(rid, None)
        if stream is not None:
            stream.close()
        self._active.discard(rid)
        self._ready.pop(rid, None)

    def _push(self, reply: pb.Reply, size: int | None = None) -> None:
        self._replies.append((reply, reply.ByteSize() if size is None else size))
        self._wake.set()

    def _fail(self, rid: int, exc: BaseException, what: str) -> None:
        err = to_property_error(exc, what)
        if log.isEnabledFor(logging.DEBUG):
            log.debug("request %d: %s: %s", rid, what, err.message, extra={"code": err.code.name})
        self._push(pb.Reply(id=rid, status=status_message(err)))

    def stop(self) -> None:
        """The gateway is stopping: end listens, stop reading, flush, end with UNAVAILABLE."""
        self._stopping = True
        if self._error is None:
            self._error = Unavailable(SHUTTING_DOWN)
        self._wake.set()

    # -- the reader --------------------------------------------------------

    async def _read(self) -> None:
        context = self._context
        limits = self._limits
        try:
            while not self._stopping:
                message = await context.read()
                if message is grpc.aio.EOF:  # type: ignore[attr-defined]
                    break
                if isinstance(message, Undecodable):
                    # No id to answer on: the call ends with it once what was read is answered.
                    self._error = message.error
                    break
                # Checked before every request, not every message: one message may carry
                # as many requests as fit in 4 MiB (over 100,000), and the bounds must hold inside it.
                for request in message.requests:
                    while (
                        len(self._tasks) >= limits.session_max_in_flight
                        or len(self._replies) >= limits.session_max_queued_replies
                    ) and not self._stopping:
                        self._room.clear()
                        await self._room.wait()
                    if self._stopping:
                        break
                    self._dispatch(request)
                # The message's requests to devices go out now, one write a device.
                started_on = self._started_on
                while started_on:
                    started_on.pop().flush()
        finally:
            self._reader_done = True
            self._wake.set()

    def _dispatch(self, request: pb.Request) -> None:
        rid = request.id
        which = request.WhichOneof("call")
        if self._requests is not None:
            self._requests[which or "none"] += 1
        logged = self._logged
        if logged is not None:
            # Set here, in the reader: the tasks and reply callbacks this request starts copy it,
            # so every line they log (the proxy's line to the device too) names this request.
            call = request.get if which == "get" else request.set if which == "set" else None
            current_request.set(
                RequestContext(
                    f"{logged.request_id}/{rid}",
                    call.service if call is not None else None,
                    call.property if call is not None else None,
                    logged.subject,
                )
            )
        if which == "cancel":
            self._cancel(rid, request.cancel.id)
            return
        if which is None:
            self._fail(
                rid, InvalidArgument(f"request {rid} has no call (get, set, listen or cancel)"), "Session"
            )
            return
        if rid in self._active:
            self._fail(
                rid, InvalidArgument(f"request id {rid} is already in use by a running request"), which
            )
            return
        if which == "listen":
            self._start_listen(rid, request.listen)
        elif which == "get":
            self._get(rid, request.get)
        else:
            self._set(rid, request.set)

    def _get(self, rid: int, request: pb.GetRequest) -> None:
        try:
            call = get_call(request)
            if call.more or is_snapshot(call):
                self._spawn(rid, self._get_more(rid, call))
                return
            handle = self._calls.start_get(call, self._timeout, self._subject)
        except Exception as exc:
            self._fail(rid, exc, f"{request.service}: get {request.property}")
            return
        self._follow(rid, handle, "get", request.service, request.property, params=call.parameters)

    def _set(self, rid: int, request: pb.SetRequest) -> None:
        try:
            handle = self._calls.start_set(set_call(request), self._timeout, self._subject)
        except Exception as exc:
            self._fail(rid, exc, f"{request.service}: set {request.property}")
            return
        self._follow(rid, handle, "set", request.service, request.property)

    def _follow(
        self,
        rid: int,
        handle: CallHandle,
        kind: str,
        service: str,
        path: str,
        *,
        params: Mapping[str, str] = NO_PARAMS,
    ) -> None:
        """Answer request ``rid`` from its call's handle: now when it is done, else once it is."""
        if handle.done:  # answered inline: the commonest case
            self._answer(rid, kind, handle.result(), service, path, params=params)
            return
        self._active.add(rid)
        self._tasks[rid] = handle
        backend = handle.backend
        if backend is not None:
            self._started_on.add(backend)
        handle.add_done_callback(_Answered(self, rid, kind, service, path, params=params))

    def _answered(
        self, rid: int, handle: CallHandle, kind: str, service: str, path: str, *, params: Mapping[str, str]
    ) -> None:
        """Request ``rid``'s call is done: its answer or its error goes in the reply queue."""
        if self._tasks.get(rid) is not handle:
            return  # the Session is ending
        del self._tasks[rid]
        self._active.discard(rid)
        if handle.cancelled():
            return
        error = handle.exception()
        if error is not None:
            self._fail(rid, error, f"{service}: {kind} {path}")
        else:
            self._answer(rid, kind, handle.result(), service, path, params=params)
        self._room.set()

    async def _get_more(self, rid: int, call: GetCall) -> None:
        try:
            reply = await self._calls.get(call, self._timeout, self._subject)
            self._push(pb.Reply(id=rid, get=get_response(reply)))
        except Exception as exc:
            self._fail(rid, exc, "Get")

    def _answer(
        self, rid: int, kind: str, value: Value | None, service: str, path: str, *, params: Mapping[str, str]
    ) -> None:
        if value is None:
            value = ""
        # Filled in place: building the answer apart would copy it into the reply.
        reply = pb.Reply(id=rid)
        response: pb.GetResponse | pb.SetResponse
        if kind == "get":
            response = reply.get
            stamp = response.time
            when = self._value_time(service, path, params, value)
            stamp.seconds, stamp.nanos = divmod(when, 1_000_000_000)
        else:
            response = reply.set
        if isinstance(value, str):
            response.value = value
        else:
            response.data = value
        if len(value) > SURELY_FITS_CHARS:
            try:
                check_fits(reply_size(value), lambda: f"request {rid} ({kind})")
            except PropertyError as exc:
                self._fail(rid, exc, kind)
                return
        # The value's bytes and at most 21 of envelope (id, oneof and value tags and lengths).
        self._push(reply, value_size(value) + 24)

    def _spawn(self, rid: int, coro: Coroutine[Any, Any, None], listen: bool = False) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        if listen:
            self._starting.add(rid)
        self._active.add(rid)
        self._tasks[rid] = task

        def done(_: asyncio.Task[None]) -> None:
            self._starting.discard(rid)
            if self._tasks.get(rid) is task:
                del self._tasks[rid]
                if rid not in self._listens:
                    self._active.discard(rid)
            self._room.set()
            self._wake.set()

        task.add_done_callback(done)

    # -- listens -----------------------------------------------------------

    def _start_listen(self, rid: int, request: pb.ListenRequest) -> None:
        try:
            stream = self._hub.listen(listen_request(request), _Ready(self, rid), self._subject)
        except Exception as exc:
            self._fail(rid, exc, "Listen")
            return
        # Started here, in the reader: a Listen of a topic that is open already (one another
        # stream shares, an in-process service's) starts without waiting and needs no task.
        self._active.add(rid)
        first = step(self._run_listen(rid, stream))
        if isinstance(first, Started):
            self._active.discard(rid)
            self._spawn(rid, _finish(first), listen=True)
        elif rid not in self._listens:
            self._active.discard(rid)

    async def _run_listen(self, rid: int, stream: ListenStream) -> None:
        """Start ``stream`` and make it Listen ``rid``; a failure is answered on ``rid``, not
        raised: in a task of its own, nobody would retrieve it (a traceback in the log a client
        could ask for 100,000 times a message)."""
        try:
            await stream.start()
        except asyncio.CancelledError:
            stream.close()
            raise
        except Exception as exc:
            stream.close()
            self._fail(rid, exc, "Listen")
            return
        if stream.closed or self._reader_done or self._stopping:
            stream.close()
            return
        self._listens[rid] = stream
        self._ready_listen(rid)

    def _ready_listen(self, rid: int) -> None:
        self._ready[rid] = None
        self._wake.set()

    def _cancel(self, rid: int, target: int) -> None:
        stream = self._listens.get(target)
        task = self._tasks.get(target)
        if stream is None and (task is None or target not in self._starting):
            self._fail(rid, NotFound(f"no running Listen has id {target}"), "Cancel")
            return
        if stream is not None:
            self._drop_listen(target)
        elif task is not None:
            task.cancel()
            del self._tasks[target]
            self._active.discard(target)
        cancelled = PropertyError(f"Listen {target} cancelled by request {rid}", Code.CANCELLED)
        self._push(pb.Reply(id=target, status=status_message(cancelled)))
        self._push(pb.Reply(id=rid))
