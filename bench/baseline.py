"""The bare server: the PropertyService contract on a dict, with no routing.

It is the yardstick for the gateway: the least a grpc.aio server in Python
must do to answer the same calls. Values live in one dict keyed by
(service, property); a Set creates the key. Listen fans each Set out to its
subscribers through plain bounded asyncio queues and sends one event per
message. Session answers Gets and Sets, one reply message per request
message. There are no parameters, wildcards, throttles or conflation.

Beside the contract it serves one more method, ``/bench.Floor/Echo``
(:data:`ECHO_METHOD`): a bidirectional stream of the Session's own messages
that answers each request of a SessionRequest with a reply carrying its id and
the stored value, and does nothing else. One request, one reply, one in
flight over it is grpc.aio's floor for a call over a bidirectional stream,
the yardstick of the gateway's Session Get (part (q) of ``python -m bench``).

Run ``python -m bench.baseline --listen 127.0.0.1:0``; it prints
``listening on HOST:PORT`` to stderr, like ``psgateway serve``, and stops on
SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import signal
import sys
from collections.abc import AsyncIterator
from typing import Any

import grpc
from google.protobuf.timestamp_pb2 import Timestamp

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

Key = tuple[str, str]

#: The floor: a bidirectional stream of SessionRequest in, SessionResponse out, on the bare server only.
ECHO_SERVICE = "bench.Floor"
ECHO_METHOD = f"/{ECHO_SERVICE}/Echo"

#: Events a subscriber may have waiting; beyond this its stream ends with
#: RESOURCE_EXHAUSTED. Large enough that no benchmark run ever reaches it.
QUEUE_BOUND = 100_000


class _Subscriber:
    """One Listen stream: its queue and its sequence counter."""

    __slots__ = ("overflowed", "queue", "sequence")

    def __init__(self) -> None:
        self.queue: asyncio.Queue[pb.Event] = asyncio.Queue(QUEUE_BOUND)
        self.sequence = 0
        self.overflowed = False

    def push(self, service: str, prop: str, value: str, time: Timestamp) -> None:
        self.sequence += 1
        event = pb.Event(service=service, property=prop, value=value, sequence=self.sequence, time=time)
        try:
            self.queue.put_nowait(event)
        except asyncio.QueueFull:
            self.overflowed = True


class BaselineServicer(pb_grpc.PropertyServiceServicer):  # type: ignore[misc]
    """PropertyService on a dict: the least work a grpc.aio server can do for the contract."""

    def __init__(self) -> None:
        self.values: dict[Key, str] = {}
        self.subscribers: dict[Key, set[_Subscriber]] = {}

    def _value(self, service: str, prop: str) -> str | None:
        return self.values.get((service, prop))

    async def Get(
        self, request: pb.GetRequest, context: grpc.aio.ServicerContext[Any, Any]
    ) -> pb.GetResponse:
        value = self._value(request.service, request.property)
        if value is None:
            await context.abort(grpc.StatusCode.NOT_FOUND, f"no property {request.property!r}")
        response = pb.GetResponse(value=value)
        for ref in request.more:
            service = ref.service or request.service
            more = self._value(service, ref.property)
            if more is None:
                await context.abort(grpc.StatusCode.NOT_FOUND, f"no property {ref.property!r}")
            response.more.add(service=service, property=ref.property, value=more)
        return response

    def _set(self, service: str, prop: str, value: str) -> None:
        self.values[(service, prop)] = value
        subscribers = self.subscribers.get((service, prop))
        if subscribers:
            now = Timestamp()
            now.GetCurrentTime()
            for subscriber in subscribers:
                subscriber.push(service, prop, value, now)

    async def Set(
        self, request: pb.SetRequest, context: grpc.aio.ServicerContext[Any, Any]
    ) -> pb.SetResponse:
        self._set(request.service, request.property, request.value)
        return pb.SetResponse(value=request.value)

    async def Listen(
        self, request: pb.ListenRequest, context: grpc.aio.ServicerContext[Any, Any]
    ) -> AsyncIterator[pb.ListenResponse]:
        keys = [(request.service, request.property)]
        keys += [(ref.service or request.service, ref.property) for ref in request.more]
        subscriber = _Subscriber()
        for key in keys:
            self.subscribers.setdefault(key, set()).add(subscriber)
        try:
            if not request.options.updates_only:
                first = pb.ListenResponse()
                now = Timestamp()
                now.GetCurrentTime()
                for service, prop in keys:
                    value = self._value(service, prop)
                    if value is not None:
                        subscriber.sequence += 1
                        first.events.add(
                            service=service,
                            property=prop,
                            value=value,
                            sequence=subscriber.sequence,
                            time=now,
                        )
                if first.events:
                    yield first
                yield pb.ListenResponse(sync=True)
            while True:
                event = await subscriber.queue.get()
                if subscriber.overflowed:
                    await context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, "listener too slow")
                yield pb.ListenResponse(events=[event])
        finally:
            for key in keys:
                subscribers = self.subscribers.get(key)
                if subscribers is not None:
                    subscribers.discard(subscriber)
                    if not subscribers:
                        del self.subscribers[key]

    async def Session(
        self, request_iterator: AsyncIterator[pb.SessionRequest], context: grpc.aio.ServicerContext[Any, Any]
    ) -> AsyncIterator[pb.SessionResponse]:
        async for message in request_iterator:
            response = pb.SessionResponse()
            for request in message.requests:
                reply = response.replies.add(id=request.id)
                kind = request.WhichOneof("call")
                if kind == "get":
                    value = self._value(request.get.service, request.get.property)
                    if value is None:
                        reply.status.code = grpc.StatusCode.NOT_FOUND.value[0]
                        reply.status.message = f"no property {request.get.property!r}"
                    else:
                        reply.get.value = value
                elif kind == "set":
                    self._set(request.set.service, request.set.property, request.set.value)
                    reply.set.value = request.set.value
                else:
                    reply.status.code = grpc.StatusCode.UNIMPLEMENTED.value[0]
                    reply.status.message = f"the bare server does not answer {kind} in a session"
            yield response


def echo_handler(servicer: BaselineServicer) -> grpc.GenericRpcHandler[Any, Any]:
    """The floor method: each request answered with its id and the stored value, one message per message.

    No oneof dispatch, no status, no Set: what is left is grpc.aio's own work
    for a message each way over a stream, protobuf parsing and building, and
    one dict look-up, which any Get must do.
    """
    values = servicer.values

    async def echo(
        request_iterator: AsyncIterator[pb.SessionRequest], context: grpc.aio.ServicerContext[Any, Any]
    ) -> AsyncIterator[pb.SessionResponse]:
        async for message in request_iterator:
            response = pb.SessionResponse()
            for request in message.requests:
                reply = response.replies.add(id=request.id)
                reply.get.value = values.get((request.get.service, request.get.property), "")
            yield response

    return grpc.method_handlers_generic_handler(
        ECHO_SERVICE,
        {
            "Echo": grpc.stream_stream_rpc_method_handler(
                echo,
                request_deserializer=pb.SessionRequest.FromString,
                response_serializer=pb.SessionResponse.SerializeToString,
            )
        },
    )


async def until_stopped() -> None:
    """Return on SIGTERM or SIGINT, or when stdin reaches end of file.

    The benchmark holds the write end of a server's stdin, so a server
    whose benchmark died (killed, crashed) sees end of file and stops too.
    """
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, stop.set)
    stdin = sys.stdin.fileno()

    def on_stdin() -> None:
        if not os.read(stdin, 4096):
            loop.remove_reader(stdin)
            stop.set()

    # A regular file or /dev/null cannot be watched; signals still work then.
    if not os.isatty(stdin):
        with contextlib.suppress(OSError, ValueError):
            loop.add_reader(stdin, on_stdin)
    await stop.wait()


async def serve(listen: str) -> None:
    """Serve on ``listen`` until SIGTERM or SIGINT."""
    server = grpc.aio.server()
    servicer = BaselineServicer()
    pb_grpc.add_PropertyServiceServicer_to_server(servicer, server)
    server.add_generic_rpc_handlers((echo_handler(servicer),))
    port = server.add_insecure_port(listen)
    host = listen.rsplit(":", 1)[0]
    await server.start()
    print(f"listening on {host}:{port}", file=sys.stderr, flush=True)
    await until_stopped()
    await server.stop(grace=1.0)


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m bench.baseline --listen HOST:PORT``."""
    parser = argparse.ArgumentParser(prog="python -m bench.baseline", description=__doc__.splitlines()[0])
    parser.add_argument("--listen", default="127.0.0.1:0", help="address to serve on (default %(default)s)")
    args = parser.parse_args(argv)
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve(args.listen))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
