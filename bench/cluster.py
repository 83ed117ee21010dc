"""Part (t), scale-out: Listen fan-out across gateway processes (one core each).

One Python process runs on one core at a time, so one gateway's
fan-out is bounded by that core. The part serves service ``bench``
(:class:`bench.gateway_server.BenchTarget`) on one gateway process and, in turn
for K in ``gateways`` (1, 2, 4), starts K−1 more gateway processes that forward
it from the first over ``grpc://`` (each holds one upstream Listen, shared by
its listeners). ``streams`` Listen streams on ``bench`` / ``value`` are spread
over the K gateways (stream k to gateway k mod K), opened by ``listener``
processes of :mod:`bench.fanout_listeners` — as many for every K, so the
client side costs the same. One client in this process Sets ``value`` on the
first gateway, ``SETS_IN_FLIGHT`` at a time, as fast as it answers; after
``warmup`` seconds the listeners count the events they read for ``seconds``.
The figure is delivered events per second (conflated values are counted
apart, never as delivered), and the ratio of K gateways to one, printed
beside the machine's cores and how many of them were free (usable cores less
the load average when the part started).

The registry on etcd, the other half of the scale-out part, is :mod:`bench.cluster_registry`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import grpc

from bench.cluster_listeners import ListenerProgram, listener_programs
from bench.servers import ROOT, ServerError, ServerProcess, end_process
from bench.target import SERVICE, VALUE_PROPERTY
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

CALL_TIMEOUT = 10.0
#: Sets the setter keeps in flight on the first gateway.
SETS_IN_FLIGHT = 4
#: Seconds a listener process may take to open its streams and say ``ready``.
READY_TIMEOUT = 60.0
GATEWAY_CONFIG = '[gateway]\nlisten = "127.0.0.1:0"\nlog_level = "warning"\n'
ORIGIN_SERVICE = f'[[services]]\nname = "{SERVICE}"\ntype = "bench.gateway_server:BenchTarget"\n'
FORWARDED_SERVICE = '[[services]]\nname = "{service}"\nurl = "grpc://{origin}/{service}"\n'
#: The ratio each number of gateways is judged by: K=4 on a machine with 4 free cores, else K=2.
CORES_BOUNDS = {2: 1.6, 4: 3.0}


def free_cores() -> dict[str, Any]:
    """The machine's cores: logical, usable by this process, and free (usable less the load average)."""
    usable = len(os.sched_getaffinity(0))
    load = os.getloadavg()[0]
    return {
        "cpu_count": os.cpu_count(),
        "usable_cores": usable,
        "load_average": round(load, 2),
        "free_cores": round(max(0.0, usable - load), 1),
    }


class ListenerProcess:
    """One listener process (:mod:`bench.cluster_listeners`): ``ready`` once its streams are synced."""

    def __init__(self, process: asyncio.subprocess.Process) -> None:
        self.process = process
        # Imported here, not at the top: `python -m bench --help` needs only the runtime packages.
        import psutil  # type: ignore[import-untyped,unused-ignore]

        self._ps = psutil.Process(process.pid)

    @classmethod
    async def start(
        cls, program: ListenerProgram, spread: Sequence[str], streams: int, first: int, time_limit: float
    ) -> ListenerProcess:
        options = [
            "--spread", ",".join(spread), "--streams", str(streams), "--first", str(first),
            "--time-limit", str(time_limit),
        ]  # fmt: skip
        process = await asyncio.create_subprocess_exec(
            *program.command,
            *options,
            cwd=ROOT,
            env=program.environment(),
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
        )
        return cls(process)

    def cpu_seconds(self) -> float:
        """User plus system CPU time the process has used so far (all its threads), as a gateway's."""
        times = self._ps.cpu_times()
        return float(times.user + times.system)

    async def ready(self) -> None:
        """Wait for ``ready``; ServerError with the process's stderr when it does not come."""
        line = b""
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(READY_TIMEOUT):
                line = await self._stdout().readline()
        if line.strip() != b"ready":
            raise ServerError(f"a listener process did not get ready: {await self._failure()}")

    def tell(self, word: str) -> None:
        assert self.process.stdin is not None
        self.process.stdin.write(f"{word}\n".encode())

    async def figures(self) -> dict[str, int]:
        """The JSON line it prints after ``stop``."""
        async with asyncio.timeout(CALL_TIMEOUT):
            line = await self._stdout().readline()
        try:
            figures: dict[str, int] = json.loads(line)
        except ValueError:
            raise ServerError(f"a listener process gave no counts: {await self._failure()}") from None
        return figures

    async def stop(self) -> None:
        await end_process(self.process)

    def _stdout(self) -> asyncio.StreamReader:
        assert self.process.stdout is not None
        return self.process.stdout

    async def _failure(self) -> str:
        await end_process(self.process)
        assert self.process.stderr is not None
        tail = (await self.process.stderr.read())[-2000:].decode(errors="replace")
        return f"exit {self.process.returncode}: {tail.strip() or '(nothing on stderr)'}"


async def start_gateway(folder: Path, label: str, services: str) -> ServerProcess:
    """``python -m gateway serve`` with its own config in ``folder``: the gateway section and ``services``."""
    config = folder / f"{label}.toml"
    config.write_text(GATEWAY_CONFIG + services)
    return await ServerProcess.start(
        label, ["gateway", "serve", "--config", str(config), "--log-level", "warning"]
    )


async def _set_until(stub: pb_grpc.PropertyServiceStub, stop: asyncio.Event, counts: list[int]) -> None:
    """Set ``value`` again and again until ``stop``; ``counts`` is [done, failed]."""
    while not stop.is_set():
        request = pb.SetRequest(service=SERVICE, property=VALUE_PROPERTY, value=str(counts[0]))
        try:
            await stub.Set(request, timeout=CALL_TIMEOUT)
        except grpc.aio.AioRpcError:
            counts[1] += 1
        counts[0] += 1


async def measure_cores(
    gateways: int,
    *,
    program: ListenerProgram,
    streams: int,
    listeners: int,
    seconds: float,
    warmup: float,
    time_limit: float,
) -> dict[str, Any]:
    """``gateways`` gateway processes, the first serving ``bench``, the rest forwarding it: count events."""
    started: list[ServerProcess] = []
    clients: list[ListenerProcess] = []
    stop = asyncio.Event()
    with tempfile.TemporaryDirectory(prefix="bench-cluster-") as name:
        folder = Path(name)
        try:
            origin = await start_gateway(folder, "gateway-1", ORIGIN_SERVICE)
            started.append(origin)
            forwarded = FORWARDED_SERVICE.format(service=SERVICE, origin=origin.address)
            for number in range(2, gateways + 1):
                started.append(await start_gateway(folder, f"gateway-{number}", forwarded))
            spread = [gateway.address for gateway in started]
            share, extra = divmod(streams, listeners)
            first = 0
            for number in range(listeners):
                count = share + (number < extra)
                if count:
                    clients.append(await ListenerProcess.start(program, spread, count, first, time_limit))
                first += count
            await asyncio.gather(*(client.ready() for client in clients))
            async with grpc.aio.insecure_channel(origin.address) as channel:
                stub = pb_grpc.PropertyServiceStub(channel)
                sets = [0, 0]
                setters = [asyncio.create_task(_set_until(stub, stop, sets)) for _ in range(SETS_IN_FLIGHT)]
                try:
                    await asyncio.sleep(warmup)
                    cpu = [gateway.cpu_seconds() for gateway in started]
                    listener_cpu = [client.cpu_seconds() for client in clients]
                    setter_cpu = time.process_time()
                    sets_before = sets[0]
                    for client in clients:
                        client.tell("start")
                    begun = time.perf_counter()
                    await asyncio.sleep(seconds)
                    # Read before ``stop``: a listener exits once it has printed its counts.
                    listener_used = sum(
                        c.cpu_seconds() - before for c, before in zip(clients, listener_cpu, strict=True)
                    )
                    for client in clients:
                        client.tell("stop")
                    wall = time.perf_counter() - begun
                    sets_done = sets[0] - sets_before
                    cores = [(g.cpu_seconds() - c) / wall for g, c in zip(started, cpu, strict=True)]
                    listener_cores = listener_used / wall
                    setter_cores = (time.process_time() - setter_cpu) / wall
                    counted = await asyncio.gather(*(client.figures() for client in clients))
                finally:
                    stop.set()
                    await asyncio.gather(*setters, return_exceptions=True)
            for gateway in started:
                gateway.check_alive()
        finally:
            for client in clients:
                await client.stop()
            for gateway in reversed(started):
                await gateway.stop()
    events = sum(c["events"] for c in counted)
    ended = sum(c["ended"] for c in counted)

    def per_event(busy_cores: float) -> float:
        return round(1e6 * busy_cores * wall / events, 1) if events else 0.0

    return {
        "gateways": gateways,
        "listener": program.kind,
        "streams": streams,
        "listener_processes": len(clients),
        "seconds": round(wall, 3),
        "events": events,
        "conflated": sum(c["conflated"] for c in counted),
        "events_per_s": round(events / wall, 1),
        "sets_per_s": round(sets_done / wall, 1),
        "set_errors": sets[1],
        "streams_ended": ended,
        "gateway_cores": [round(c, 2) for c in cores],
        "gateway_cpu_us_per_event": per_event(sum(cores)),
        "listener_cores": round(listener_cores, 2),
        "listener_cpu_us_per_event": per_event(listener_cores),
        # This process: the setter, and the asyncio loop that drives the listeners' pipes.
        "setter_cores": round(setter_cores, 2),
        "complete": ended == 0 and events > 0,
    }


def _best_of(gateway_counts: tuple[int, ...], seen: dict[int, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Each number of gateways' best round, with its ratio to the fewest gateways' and every round's rate."""
    best = {k: max(runs, key=lambda figures: float(figures["events_per_s"])) for k, runs in seen.items()}
    one = best[min(gateway_counts)]["events_per_s"]
    return [
        {**best[k], "ratio": round(best[k]["events_per_s"] / one, 3) if one else 0.0,
         "rounds_events_per_s": [r["events_per_s"] for r in seen[k]]}
        for k in gateway_counts
    ]  # fmt: skip


async def run_cores(
    gateway_counts: tuple[int, ...],
    *,
    listener_kinds: Sequence[str] = ("auto",),
    streams: int,
    listeners: int,
    seconds: float,
    warmup: float,
    rounds: int,
    time_limit: float,
) -> dict[str, Any]:
    """Measure fan-out with each number of gateways, taking turns for ``rounds``; the best round counts.

    Each kind of listener program in ``listener_kinds`` (:mod:`bench.cluster_listeners`) takes its turn
    after each number of gateways; the first is the one the target judges (``sizes``), the others are
    kept in ``other_listeners``, measured in the same rounds.
    """
    machine = free_cores()
    programs, notes = await listener_programs(listener_kinds)
    for note in notes:
        print(f"  cluster cores: {note}", file=sys.stderr)
    seen: dict[str, dict[int, list[dict[str, Any]]]] = {
        program.kind: {k: [] for k in gateway_counts} for program in programs
    }
    for _ in range(rounds):
        for k in gateway_counts:
            for program in programs:
                seen[program.kind][k].append(
                    await measure_cores(
                        k,
                        program=program,
                        streams=streams,
                        listeners=listeners,
                        seconds=seconds,
                        warmup=warmup,
                        time_limit=time_limit,
                    )
                )
    by_kind = {kind: _best_of(gateway_counts, runs) for kind, runs in seen.items()}
    judged_kind = programs[0].kind
    sizes = by_kind.pop(judged_kind)
    judged = 4 if machine["free_cores"] >= 4 and 4 in gateway_counts else 2
    return {
        **machine,
        "listener": judged_kind,
        "listener_notes": notes,
        "sizes": sizes,
        "other_listeners": by_kind,
        "judged_gateways": judged,
        "judged_bound": CORES_BOUNDS[judged],
        "complete": all(size["complete"] for runs in (sizes, *by_kind.values()) for size in runs),
    }
