"""Many Listen streams in one process, counting events on command: the client side of the cluster part.

``python -m bench.fanout_listeners --spread A1,A2 --streams 100 --first 0`` opens
100 Listen streams on ``bench`` / ``value``, stream ``k`` to address
``A[(first + k) % len(A)]`` (at most ``STREAMS_PER_CHANNEL`` a connection), reads
each up to its ``sync`` marker and prints ``ready`` on stdout. Then it obeys
its stdin, one word a line: ``start`` zeroes the counts, ``stop`` prints
``{"events": E, "conflated": C, "ended": N}`` as one JSON line (events read
since ``start``, intermediate values the gateways conflated away, streams that
ended, with an error or without) and exits. It also exits at end of file on stdin, and after
``--time-limit`` seconds whatever happens, so that it never outlives the
benchmark.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import sys
from typing import Any

import grpc

from bench.measure import STREAM_END, read_until_sync
from bench.target import SERVICE, VALUE_PROPERTY
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

#: Listen streams one connection carries, as in part (c).
STREAMS_PER_CHANNEL = 25
#: Every channel its own TCP connection (grpc otherwise shares one between channels to one address).
CHANNEL_OPTIONS = [("grpc.use_local_subchannel_pool", 1)]
#: Seconds the streams get to reach their ``sync`` markers.
SYNC_TIMEOUT = 60.0


class Counts:
    """Events read by every stream of this process; zeroed by ``start``."""

    def __init__(self) -> None:
        self.events = 0
        self.conflated = 0
        self.ended = 0


async def _consume(call: Any, counts: Counts) -> None:
    while True:
        try:
            response = await call.read()
        except grpc.aio.AioRpcError:
            response = STREAM_END  # ended with an error status: ended all the same
        if response is STREAM_END:
            counts.ended += 1
            return
        for event in response.events:
            counts.events += 1
            counts.conflated += event.conflated


async def _commands() -> asyncio.StreamReader:
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader(limit=1024)
    await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), sys.stdin)
    return reader


async def listen(spread: list[str], streams: int, first: int) -> int:
    """Open the streams, then count between ``start`` and ``stop``; the exit code."""
    per_address = [0] * len(spread)
    targets = [(first + k) % len(spread) for k in range(streams)]
    for index in targets:
        per_address[index] += 1
    channels = [
        [
            grpc.aio.insecure_channel(address, options=CHANNEL_OPTIONS)
            for _ in range(math.ceil(count / STREAMS_PER_CHANNEL))
        ]
        for address, count in zip(spread, per_address, strict=True)
    ]
    request = pb.ListenRequest(service=SERVICE, property=VALUE_PROPERTY)
    calls = []
    used = [0] * len(spread)
    for index in targets:
        channel = channels[index][used[index] // STREAMS_PER_CHANNEL]
        used[index] += 1
        calls.append(pb_grpc.PropertyServiceStub(channel).Listen(request))
    counts = Counts()
    tasks: list[asyncio.Task[None]] = []
    try:
        try:
            async with asyncio.timeout(SYNC_TIMEOUT):
                await asyncio.gather(*(read_until_sync(call) for call in calls))
        except grpc.aio.AioRpcError as error:
            why = f"{error.code().name}: {error.details()}"
            print(f"error: a Listen stream ended before its sync marker: {why}", file=sys.stderr)
            return 1
        tasks = [asyncio.create_task(_consume(call, counts)) for call in calls]
        commands = await _commands()
        print("ready", flush=True)
        while line := await commands.readline():
            word = line.decode(errors="replace").strip()
            if word == "start":
                counts.events = counts.conflated = 0
            elif word == "stop":
                figures = {"events": counts.events, "conflated": counts.conflated, "ended": counts.ended}
                print(json.dumps(figures), flush=True)
                return 0
        return 1  # end of file before ``stop``: the benchmark went away
    finally:
        for call in calls:
            call.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for group in channels:
            for channel in group:
                await channel.close(None)


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m bench.fanout_listeners --spread A1,A2 --streams N [--first K]``."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.fanout_listeners", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--spread", required=True, help="gateway addresses, comma-separated")
    parser.add_argument("--streams", type=int, required=True, help="Listen streams to open")
    parser.add_argument("--first", type=int, default=0, help="the first stream's turn in the spread")
    parser.add_argument("--time-limit", type=float, default=300.0, help="seconds before giving up")
    args = parser.parse_args(argv)
    spread = [address.strip() for address in args.spread.split(",") if address.strip()]
    if not spread or args.streams < 1 or args.time_limit <= 0:
        parser.error("--spread needs an address, --streams and --time-limit must be positive")

    async def bounded() -> int:
        try:
            async with asyncio.timeout(args.time_limit):
                return await listen(spread, args.streams, args.first)
        except TimeoutError:
            print(f"error: gave up after {args.time_limit:g} s", file=sys.stderr)
            return 1

    with contextlib.suppress(KeyboardInterrupt):
        return asyncio.run(bounded())
    return 1


if __name__ == "__main__":
    raise SystemExit(main())
