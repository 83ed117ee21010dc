"""The listen hub's own work per event of a batched fan-out, in one process and without gRPC.

Run ``python -m bench.hub_fanout`` (``--bursts N``, ``--profile``). 100 streams of the listen hub
follow the ten properties of part (c)'s batched mode each, on :class:`bench.gateway_server.BenchTarget`
served by ``LocalService`` as the benchmark's gateway serves it. A burst sets each property
once (ten changes); then every stream is drained as the gRPC front drains it
(``gateway.fronts.grpc_v1.listen_encoding.take_wire``: one message of ten events). The figure,
the best of five runs, is the time per event and per message: what the gateway's Python pays
beside grpc.aio's own cost of writing the message, which the floor of ``python -m bench.fanout``
pays too. ``--profile`` prints where it goes (cProfile).

``--instructions`` counts instead of timing: the same process under ``valgrind --tool=callgrind``,
its counters zeroed and dumped (``callgrind_control``) around each of three runs, after a garbage
collection each (a collection that falls into one run and not the next would swing its count by
3-5 %), less the count of an empty run (the ``callgrind_control`` calls). The gateway's figures
of ``python -m bench.instructions`` swing 2-5 % from round to round; these repeat within 0.2 %:
what settles a change of a hundred instructions per event in the engine's fan-out
(``services.kernel.backend.tell_each``, ``ListenStream.topic_changed``).
"""

from __future__ import annotations

import argparse
import asyncio
import cProfile
import gc
import glob
import os
import pstats
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.gateway_server import BenchTarget
from bench.servers import ROOT
from bench.target import BATCH_PROPERTIES, SERVICE
from gateway.config import Limits
from gateway.engine.listen import ListenHub, ListenStream, Selector, StreamOptions
from gateway.engine.router import Router
from gateway.fronts.grpc_v1.listen_encoding import take_wire
from services.kernel.core import LocalService

STREAMS = 100
#: Bursts before the measured ones: the first changes of a stream take its start-up paths.
WARM_UP = 50


class _Hub:
    """The hub with its streams open and synced, and the streams each burst woke."""

    def __init__(self) -> None:
        self.target = BenchTarget()
        router = Router()
        router.add(SERVICE, LocalService(self.target))
        self.hub = ListenHub(router, Limits(), call_timeout=5.0)
        self.woken: list[ListenStream] = []
        self.streams: list[ListenStream] = []
        self.events = 0

    async def open(self) -> None:
        selectors = [Selector(SERVICE, prop) for prop in BATCH_PROPERTIES]
        for _ in range(STREAMS):
            holder: list[ListenStream] = []
            stream = self.hub.open(selectors, StreamOptions(), lambda held=holder: self.woken.append(held[0]))
            holder.append(stream)
            self.streams.append(stream)
        for stream in self.streams:
            await stream.start()
        self.bursts(WARM_UP)

    def bursts(self, count: int) -> None:
        """``count`` bursts of one change to each property, each drained by every stream it woke."""
        for _ in range(count):
            value = str(time.perf_counter_ns())
            for prop in BATCH_PROPERTIES:
                setattr(self.target, prop, value)
            woken, self.woken = self.woken, []
            for stream in woken:
                while take_wire(stream) is not None:
                    pass

    def sent(self) -> int:
        return sum(stream.events_sent for stream in self.streams)


async def measure(bursts: int, profile: bool) -> None:
    """Print the hub's time per event and per message, or with ``profile`` where it goes."""
    hub = _Hub()
    await hub.open()
    if profile:
        profiler = cProfile.Profile()
        profiler.enable()
        hub.bursts(bursts)
        profiler.disable()
        pstats.Stats(profiler).sort_stats("tottime").print_stats(20)
        return
    best = float("inf")
    for _ in range(5):
        before = hub.sent()
        started = time.perf_counter()
        hub.bursts(bursts)
        elapsed = time.perf_counter() - started
        events = hub.sent() - before
        if events != bursts * STREAMS * len(BATCH_PROPERTIES):
            raise RuntimeError(f"expected {bursts * STREAMS * len(BATCH_PROPERTIES)} events, sent {events}")
        best = min(best, elapsed / events)
    per_message = best * len(BATCH_PROPERTIES)
    print(
        f"{STREAMS} streams, {len(BATCH_PROPERTIES)} events a message: "
        f"{1e6 * best:.3f} µs per event, {1e6 * per_message:.2f} µs per message (best of 5 runs)"
    )


#: Runs counted by ``--instructions``.
COUNTED_RUNS = 3


def _control(option: str) -> None:
    """``callgrind_control option`` on this process (it runs under callgrind)."""
    subprocess.run(["callgrind_control", option, str(os.getpid())], check=True, capture_output=True)


async def counted_runs(bursts: int) -> None:
    """Under callgrind: dump the counts of an empty run, then of :data:`COUNTED_RUNS` runs."""
    hub = _Hub()
    await hub.open()
    for count in (0, *[bursts] * COUNTED_RUNS):
        gc.collect()
        _control("-z")
        hub.bursts(count)
        _control("-d")


def _dump_total(dump: str) -> int:
    for line in Path(dump).read_text(errors="replace").splitlines():
        if line.startswith(("summary:", "totals:")):
            return int(line.split()[1])
    raise RuntimeError(f"no count in {dump}")


def count_instructions(bursts: int) -> None:
    """Print the instructions per event of :data:`COUNTED_RUNS` runs of ``bursts`` bursts each."""
    with tempfile.TemporaryDirectory(prefix="callgrind-") as folder:
        run = subprocess.run(
            [
                "valgrind",
                "--tool=callgrind",
                f"--callgrind-out-file={folder}/callgrind.out",
                sys.executable,
                "-m",
                "bench.hub_fanout",
                "--bursts",
                str(bursts),
                "--counted",
            ],
            check=False,
            cwd=ROOT,
            env={**os.environ, "PYTHONHASHSEED": "0"},  # the runs hash alike
            capture_output=True,
            text=True,
        )
        if run.returncode:
            raise RuntimeError(f"the counted process failed:\n{run.stderr[-2000:]}")
        # callgrind.out.1, .2, ...: one a dump, in order; callgrind.out itself is the exit's.
        dumps = sorted(glob.glob(f"{folder}/callgrind.out.*"), key=lambda name: int(name.rsplit(".", 1)[1]))
        empty, *runs = [_dump_total(dump) for dump in dumps]
    events = bursts * STREAMS * len(BATCH_PROPERTIES)
    shown = ", ".join(f"{(total - empty) / events:,.0f}" for total in runs)
    print(f"{STREAMS} streams, {len(BATCH_PROPERTIES)} events a message: instructions per event {shown}")


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m bench.hub_fanout``."""
    parser = argparse.ArgumentParser(prog="python -m bench.hub_fanout", description=__doc__.splitlines()[0])
    parser.add_argument("--bursts", type=int, default=200, help="bursts a run (default 200)")
    parser.add_argument("--profile", action="store_true", help="print a cProfile of one run instead")
    parser.add_argument(
        "--instructions",
        action="store_true",
        help=f"count instructions per event under callgrind instead ({COUNTED_RUNS} runs; about a minute)",
    )
    parser.add_argument("--counted", action="store_true", help=argparse.SUPPRESS)  # the process counted
    args = parser.parse_args(argv)
    if args.bursts < 1:
        parser.error("--bursts must be at least 1")
    if args.counted:
        asyncio.run(counted_runs(args.bursts))
    elif args.instructions:
        missing = [tool for tool in ("valgrind", "callgrind_control") if shutil.which(tool) is None]
        if missing:
            print(f"needs {' and '.join(missing)} (apt-get install valgrind)", file=sys.stderr)
            return 2
        count_instructions(args.bursts)
    else:
        asyncio.run(measure(args.bursts, args.profile))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
