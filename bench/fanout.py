"""Listen fan-out: the gateway beside the bare server and grpc.aio's own floor, and the ways a
gateway carries listens (a Listen stream each, or many inside one Session).

Run ``python -m bench.fanout`` (``--quick`` for a short run, ``--rounds N``). Two tables:

**Beside the floor.** Three servers take turns on fresh processes, driven by the same client code
as part (c) of ``python -m bench`` (:func:`bench.listen.run_listen`: 100 subscribers, one-by-one
Sets, and bursts of ten Sets in one Session message):

* the bare server (``bench.baseline``) and the gateway (``bench.gateway_server``), as in part (c);
* the **floor**, this module's own server (``python -m bench.fanout --serve``): a Set hands every
  Listen stream the same pre-serialized ``ListenResponse`` (one event for a Set; one event per
  Set for a Session message of Sets). No per-stream encoding, sequence numbers or conflation:
  what is left is grpc.aio's own cost of waking a stream's task and writing one message, the
  least any grpc.aio server pays.

**The gateway's ways.** The same 100 subscribers on the gateway, one-by-one Sets: each a Listen
stream of its own; each a listen inside a Session of its own (one client, one listen); and 25
listens inside each of four Sessions (a client with many listens, the SDK's default way to carry
them: the events of all its listens that are ready go in one message). ``--set-rate`` paces the
Sets, for the latency at a given load.

The figure is the server's CPU per delivered event (user + system, all its threads, psutil),
which does not depend on how fast the client reads, with events/s and Set-to-delivery latency
beside it. A server that sends one event per message cannot spend less per event than the
floor's one-by-one figure, and bare / floor in the batched mode is the most any grpc.aio server
could reach over the bare server's events/s there.
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import contextlib
import sys
from collections.abc import AsyncIterator
from typing import Any

import grpc

from bench.baseline import until_stopped
from bench.listen import ListenResult, run_listen
from bench.servers import ServerProcess
from bench.target import BATCH_PROPERTIES, VALUE_PROPERTY
from protos.propertyservice.v1 import property_service_pb2 as pb

SERVERS = {
    "floor": ["bench.fanout", "--serve", "--listen", "127.0.0.1:0"],
    "bare": ["bench.baseline", "--listen", "127.0.0.1:0"],
    "gateway": ["bench.gateway_server", "--listen", "127.0.0.1:0"],
}
MODES = {"one-by-one": (VALUE_PROPERTY,), "batched": BATCH_PROPERTIES}
#: Listen streams the floor serves at most; more are refused.
MAX_STREAMS = 10_000
#: Messages a stream may have waiting; the oldest goes beyond it (no benchmark run comes near).
QUEUE_BOUND = 100_000
SERVICE_NAME = pb.DESCRIPTOR.services_by_name["PropertyService"].full_name


class _Stream:
    """One Listen stream of the floor: the messages it has not written yet, and its waiter."""

    __slots__ = ("pending", "waiter")

    def __init__(self) -> None:
        self.pending: collections.deque[bytes] = collections.deque(maxlen=QUEUE_BOUND)
        self.waiter: asyncio.Future[None] | None = None


class FloorServer:
    """Set and Session hand every Listen stream one shared, pre-serialized response."""

    def __init__(self) -> None:
        self._streams: set[_Stream] = set()

    def _wake(self, events: list[pb.Event]) -> None:
        message = pb.ListenResponse(events=events).SerializeToString()
        for stream in self._streams:
            stream.pending.append(message)
            waiter = stream.waiter
            if waiter is not None and not waiter.done():
                waiter.set_result(None)

    async def Set(self, request: pb.SetRequest, context: Any) -> pb.SetResponse:
        self._wake([pb.Event(service=request.service, property=request.property, value=request.value)])
        return pb.SetResponse(value=request.value)

    async def Session(self, requests: AsyncIterator[pb.SessionRequest], context: Any) -> AsyncIterator[bytes]:
        async for message in requests:
            response = pb.SessionResponse()
            events = []
            for request in message.requests:
                response.replies.add(id=request.id).set.value = request.set.value
                call = request.set
                events.append(pb.Event(service=call.service, property=call.property, value=call.value))
            self._wake(events)
            yield response.SerializeToString()

    async def Listen(self, request: pb.ListenRequest, context: Any) -> AsyncIterator[bytes]:
        if len(self._streams) >= MAX_STREAMS:
            await context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, "too many streams")
        loop = asyncio.get_running_loop()
        stream = _Stream()
        self._streams.add(stream)
        try:
            yield pb.ListenResponse(sync=True).SerializeToString()
            while True:
                if not stream.pending:
                    stream.waiter = loop.create_future()
                    await stream.waiter
                yield stream.pending.popleft()
        finally:
            self._streams.discard(stream)


async def serve(listen: str) -> None:
    """Serve the floor on ``listen`` until SIGTERM, SIGINT or end of file on stdin."""
    floor = FloorServer()
    server = grpc.aio.server()
    handlers = {
        "Set": grpc.unary_unary_rpc_method_handler(
            floor.Set,
            request_deserializer=pb.SetRequest.FromString,
            response_serializer=pb.SetResponse.SerializeToString,
        ),
        # Responses are yielded serialized: the serializer hands the bytes on.
        "Session": grpc.stream_stream_rpc_method_handler(
            floor.Session, request_deserializer=pb.SessionRequest.FromString, response_serializer=bytes
        ),
        "Listen": grpc.unary_stream_rpc_method_handler(
            floor.Listen, request_deserializer=pb.ListenRequest.FromString, response_serializer=bytes
        ),
    }
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(SERVICE_NAME, handlers),))
    port = server.add_insecure_port(listen)
    await server.start()
    print(f"listening on {listen.rsplit(':', 1)[0]}:{port}", file=sys.stderr, flush=True)
    await until_stopped()
    await server.stop(grace=1.0)


async def measure(
    sets: int, rounds: int, subscribers: int, time_limit: float
) -> dict[tuple[str, str], ListenResult]:
    """Each mode on each server, ``rounds`` times in turn; the round with least CPU per event of each."""
    best: dict[tuple[str, str], ListenResult] = {}
    for mode, properties in MODES.items():
        for _ in range(rounds):
            for kind, argv in SERVERS.items():
                server = await ServerProcess.start(kind, argv)
                try:
                    result = await run_listen(
                        server,
                        mode=mode,
                        properties=properties,
                        subscribers=subscribers,
                        sets=sets,
                        channels=max(subscribers // 25, 1),
                        set_rate=0.0,
                        time_limit=time_limit,
                    )
                finally:
                    await server.stop()
                print(
                    f"  {mode:10} {kind:7} {_cpu_per_event(result):7.1f} µs/event, "
                    f"{result.events_per_s:9,.0f} events/s"
                )
                kept = best.get((mode, kind))
                if result.complete and (kept is None or _cpu_per_event(result) < _cpu_per_event(kept)):
                    best[(mode, kind)] = result
    return best


def _cpu_per_event(result: ListenResult) -> float:
    return 1e6 * result.window.server_cpu_s / max(result.events, 1)


def report(best: dict[tuple[str, str], ListenResult]) -> None:
    """The table: per mode and server, CPU per event, events per message, events/s, and the ratios."""
    print()
    print("mode        server   µs CPU/event  events/msg    events/s   CPU vs floor   events/s vs bare")
    for mode in MODES:
        floor, bare = best.get((mode, "floor")), best.get((mode, "bare"))
        for kind in SERVERS:
            result = best.get((mode, kind))
            if result is None:
                print(f"{mode:11} {kind:8} (no complete round)")
                continue
            cpu = _cpu_per_event(result)
            versus_floor = f"{cpu / _cpu_per_event(floor):5.2f} x" if floor else "  n/a"
            versus_bare = f"{result.events_per_s / bare.events_per_s:5.2f} x" if bare else "  n/a"
            print(
                f"{mode:11} {kind:8} {cpu:12.1f} {result.events_per_message:11.1f} "
                f"{result.events_per_s:11,.0f}   {versus_floor:>12}   {versus_bare:>16}"
            )


#: The gateway's ways of carrying the subscribers' listens: listens per Session (0: a Listen stream each).
WAYS = {"a Listen stream each": 0, "a Session each": 1, "25 in a Session": 25}


async def measure_ways(
    sets: int, rounds: int, subscribers: int, set_rate: float, time_limit: float
) -> dict[str, ListenResult]:
    """Each way on a fresh gateway, ``rounds`` times in turn; the round with least CPU per event of each."""
    best: dict[str, ListenResult] = {}
    for _ in range(rounds):
        for way, per_session in WAYS.items():
            server = await ServerProcess.start("gateway", SERVERS["gateway"])
            try:
                result = await run_listen(
                    server,
                    mode="one-by-one",
                    properties=(VALUE_PROPERTY,),
                    subscribers=subscribers,
                    sets=sets,
                    channels=max(subscribers // 25, 1),
                    set_rate=set_rate,
                    time_limit=time_limit,
                    per_session=per_session,
                )
            finally:
                await server.stop()
            print(f"  {way:22} {_cpu_per_event(result):7.1f} µs/event, {result.events_per_s:9,.0f} events/s")
            kept = best.get(way)
            if result.complete and (kept is None or _cpu_per_event(result) < _cpu_per_event(kept)):
                best[way] = result
    return best


def report_ways(best: dict[str, ListenResult]) -> None:
    """The table of the gateway's ways: CPU per event, events per message, events/s, latency."""
    print()
    print("way                    µs CPU/event  events/msg    events/s   Set→delivery p50 / p99 µs")
    for way in WAYS:
        result = best.get(way)
        if result is None:
            print(f"{way:22} (no complete round)")
            continue
        print(
            f"{way:22} {_cpu_per_event(result):12.1f} {result.events_per_message:11.1f} "
            f"{result.events_per_s:11,.0f}   {result.latency.p50_us:10,.0f} / {result.latency.p99_us:,.0f}"
        )


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m bench.fanout``; ``--serve --listen HOST:PORT`` runs the floor."""
    parser = argparse.ArgumentParser(prog="python -m bench.fanout", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--serve", action="store_true", help="run the floor server (what the benchmark starts)"
    )
    parser.add_argument("--listen", default="127.0.0.1:0", help="with --serve: address to serve on")
    parser.add_argument("--quick", action="store_true", help="300 Sets a round instead of 2,000")
    parser.add_argument("--rounds", type=int, default=2, help="rounds per server and mode (default 2)")
    parser.add_argument("--subscribers", type=int, default=100, help="Listen streams (default 100)")
    parser.add_argument(
        "--part", choices=("all", "floor", "ways"), default="all", help="both tables (default) or one"
    )
    parser.add_argument(
        "--set-rate", type=float, default=0.0, help="the gateway's ways: Sets per second (default: unpaced)"
    )
    args = parser.parse_args(argv)
    with contextlib.suppress(KeyboardInterrupt):
        if args.serve:
            asyncio.run(serve(args.listen))
            return 0
        sets = 300 if args.quick else 2000
        print(f"Listen fan-out to {args.subscribers} streams, {sets} Sets a round, {args.rounds} rounds")
        if args.part in ("all", "floor"):
            report(asyncio.run(measure(sets, args.rounds, args.subscribers, time_limit=120.0)))
        if args.part in ("all", "ways"):
            pace = f"{args.set_rate:g} Sets/s" if args.set_rate else "Sets as fast as answered"
            print(f"\nThe gateway's ways of carrying {args.subscribers} listens ({pace})")
            ways = measure_ways(sets, args.rounds, args.subscribers, args.set_rate, time_limit=120.0)
            report_ways(asyncio.run(ways))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
