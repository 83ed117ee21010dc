"""Part (q): scale-out — Listen fan-out across gateway processes (one core each), and a registry on etcd.

**Cores.** One Python process runs on one core at a time, so one gateway's
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

**Registry.** ``devices`` line-protocol devices (simulated robots multiplexed
on :mod:`bench.device_farm` processes, as in part (h)) across ``gateways``
(4) gateway processes sharing one registry in etcd (Debian's ``etcd``, one
member, in a temporary folder; the part is not run without it). Each device is
registered by a Set on gateway ``k mod 4``, 32 Sets in flight in all: the
registration rate, then the time until every gateway lists every device. Then
``queries`` Gets of the registry's ``find`` (``type=mobile_robot``,
``limit=10``) taking turns over the gateways (p50, p99); ``gets`` Gets of a
device's ``location`` one at a time, on its owner (local) and on another
gateway (forwarded), taking turns (p50 of each and their ratio). Last, the
gateway that owns a quarter of the devices is SIGKILLed: failover is the time
from the kill until each of its devices answers a Get through a surviving
gateway (its lease expired, a survivor owns it and has connected to it);
every registration must still be listed.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import shutil
import signal
import socket
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import grpc

from bench.device_farm import FD_SPARE, device_name, raise_fd_limit
from bench.measure import STREAM_END, read_until_sync
from bench.register import start_farms
from bench.servers import ROOT, ServerError, ServerProcess, end_process
from bench.target import SERVICE, VALUE_PROPERTY
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.values import parse_names

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
    """One :mod:`bench.fanout_listeners` process: ``ready`` once its streams are synced."""

    def __init__(self, process: asyncio.subprocess.Process) -> None:
        self.process = process

    @classmethod
    async def start(
        cls, spread: Sequence[str], streams: int, first: int, time_limit: float
    ) -> ListenerProcess:
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH", "")]))
        argv = [
            "-m", "bench.fanout_listeners", "--spread", ",".join(spread), "--streams", str(streams),
            "--first", str(first), "--time-limit", str(time_limit),
        ]  # fmt: skip
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            *argv,
            cwd=ROOT,
            env=env,
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
        )
        return cls(process)

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


async def _start_gateway(folder: Path, label: str, services: str) -> ServerProcess:
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
    gateways: int, *, streams: int, listeners: int, seconds: float, warmup: float, time_limit: float
) -> dict[str, Any]:
    """``gateways`` gateway processes, the first serving ``bench``, the rest forwarding it: count events."""
    started: list[ServerProcess] = []
    clients: list[ListenerProcess] = []
    stop = asyncio.Event()
    with tempfile.TemporaryDirectory(prefix="bench-cluster-") as name:
        folder = Path(name)
        try:
            origin = await _start_gateway(folder, "gateway-1", ORIGIN_SERVICE)
            started.append(origin)
            forwarded = FORWARDED_SERVICE.format(service=SERVICE, origin=origin.address)
            for number in range(2, gateways + 1):
                started.append(await _start_gateway(folder, f"gateway-{number}", forwarded))
            spread = [gateway.address for gateway in started]
            share, extra = divmod(streams, listeners)
            first = 0
            for number in range(listeners):
                count = share + (number < extra)
                if count:
                    clients.append(await ListenerProcess.start(spread, count, first, time_limit))
                first += count
            await asyncio.gather(*(client.ready() for client in clients))
            async with grpc.aio.insecure_channel(origin.address) as channel:
                stub = pb_grpc.PropertyServiceStub(channel)
                sets = [0, 0]
                setters = [asyncio.create_task(_set_until(stub, stop, sets)) for _ in range(SETS_IN_FLIGHT)]
                try:
                    await asyncio.sleep(warmup)
                    cpu = [gateway.cpu_seconds() for gateway in started]
                    sets_before = sets[0]
                    for client in clients:
                        client.tell("start")
                    begun = time.perf_counter()
                    await asyncio.sleep(seconds)
                    for client in clients:
                        client.tell("stop")
                    wall = time.perf_counter() - begun
                    sets_done = sets[0] - sets_before
                    cores = [(g.cpu_seconds() - c) / wall for g, c in zip(started, cpu, strict=True)]
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
    return {
        "gateways": gateways,
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
        "complete": ended == 0 and events > 0,
    }


async def run_cores(
    gateway_counts: tuple[int, ...],
    *,
    streams: int,
    listeners: int,
    seconds: float,
    warmup: float,
    rounds: int,
    time_limit: float,
) -> dict[str, Any]:
    """Measure fan-out with each number of gateways, taking turns for ``rounds``; the best round counts."""
    machine = free_cores()
    seen: dict[int, list[dict[str, Any]]] = {k: [] for k in gateway_counts}
    for _ in range(rounds):
        for k in gateway_counts:
            seen[k].append(
                await measure_cores(
                    k,
                    streams=streams,
                    listeners=listeners,
                    seconds=seconds,
                    warmup=warmup,
                    time_limit=time_limit,
                )
            )
    best = {k: max(runs, key=lambda figures: float(figures["events_per_s"])) for k, runs in seen.items()}
    one = best[min(gateway_counts)]["events_per_s"]
    sizes = [
        {**best[k], "ratio": round(best[k]["events_per_s"] / one, 3) if one else 0.0,
         "rounds_events_per_s": [r["events_per_s"] for r in seen[k]]}
        for k in gateway_counts
    ]  # fmt: skip
    judged = 4 if machine["free_cores"] >= 4 and 4 in gateway_counts else 2
    return {
        **machine,
        "sizes": sizes,
        "judged_gateways": judged,
        "judged_bound": CORES_BOUNDS[judged],
        "complete": all(size["complete"] for size in sizes),
    }


#: Seconds of each gateway's etcd lease in the registry part: how long a dead gateway's devices wait.
STORE_LEASE = 3.0
#: Registration Sets in flight in all, as in part (h).
REGISTER_IN_FLIGHT = 32
#: Gets in flight while waiting for a dead gateway's devices to answer again.
FAILOVER_IN_FLIGHT = 64
#: Exact selectors one Listen carries (``[limits] max_selectors``, 64 by default).
OWNER_SELECTORS = 64
#: Seconds a Get of a device taken over may take while waiting for it to answer again.
FAILOVER_GET_TIMEOUT = 2.0
#: Seconds between rounds of asking the devices that have not answered yet.
FAILOVER_PAUSE = 0.1
#: What etcd logs once it answers clients (3.4 says the first, later versions the second).
ETCD_READY = (b"serving client traffic", b"ready to serve client requests")
ETCD_MISSING = "etcd is not installed (Debian: apt-get install etcd-server); the registry part needs it"
STORE_CONFIG = """[registry]
store = "etcd://{etcd}"
store_lease = {lease}
gateway_id = "{id}"
max_registrations = {devices}
"""


def etcd_binary() -> str | None:
    """The ``etcd`` command, or None when it is not installed."""
    return shutil.which("etcd")


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


class EtcdProcess:
    """A one-member etcd on loopback ports, its data in ``folder``; ended by its PID."""

    def __init__(self, process: asyncio.subprocess.Process, address: str) -> None:
        self.process = process
        self.address = address
        self._drain: asyncio.Task[None] | None = None

    @classmethod
    async def start(cls, binary: str, folder: Path) -> EtcdProcess:
        client, peer = f"http://127.0.0.1:{_free_port()}", f"http://127.0.0.1:{_free_port()}"
        process = await asyncio.create_subprocess_exec(
            binary,
            "--name=bench",
            f"--data-dir={folder / 'etcd-data'}",
            f"--listen-client-urls={client}",
            f"--advertise-client-urls={client}",
            f"--listen-peer-urls={peer}",
            f"--initial-advertise-peer-urls={peer}",
            f"--initial-cluster=bench={peer}",
            "--logger=zap",
            "--log-outputs=stderr",
            stdin=asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.PIPE,
        )
        etcd = cls(process, client.removeprefix("http://"))
        assert process.stderr is not None
        seen: list[bytes] = []
        try:
            async with asyncio.timeout(READY_TIMEOUT):
                while True:
                    line = await process.stderr.readline()
                    if not line:
                        raise ServerError("etcd exited: " + b"".join(seen[-5:]).decode(errors="replace"))
                    if any(mark in line for mark in ETCD_READY):
                        break
                    seen.append(line)
        except BaseException:
            await end_process(process)
            raise
        etcd._drain = asyncio.create_task(etcd._read_on(process.stderr))
        return etcd

    async def _read_on(self, output: asyncio.StreamReader) -> None:
        while await output.readline():  # a full pipe would stop etcd
            pass

    async def stop(self) -> None:
        await end_process(self.process)
        if self._drain is not None:
            self._drain.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._drain


def _quantile(samples: list[float], q: float) -> float:
    ordered = sorted(samples)
    return ordered[min(len(ordered) - 1, math.floor(q * len(ordered)))] if ordered else math.nan


async def _register_spread(
    stubs: list[pb_grpc.PropertyServiceStub], ports: dict[str, int], deadline: float
) -> tuple[int, list[str]]:
    """Register every device, device k by a Set on gateway k mod len(stubs); successes and first errors."""
    pending = list(enumerate(ports.items()))
    pending.reverse()
    errors: list[str] = []
    ok = 0

    async def worker() -> None:
        nonlocal ok
        while pending and time.monotonic() < deadline:
            number, (name, port) = pending.pop()
            request = pb.SetRequest(
                service="registry", property=f"services.{name}", value=f"tcp://127.0.0.1:{port}"
            )
            try:
                await stubs[number % len(stubs)].Set(request, timeout=CALL_TIMEOUT)
            except grpc.aio.AioRpcError as exc:
                if len(errors) < 10:
                    errors.append(f"{name}: {exc.code().name} {exc.details()}")
                continue
            ok += 1

    await asyncio.gather(*(worker() for _ in range(REGISTER_IN_FLIGHT)))
    return ok, errors


async def _listed(stub: pb_grpc.PropertyServiceStub) -> set[str]:
    reply = await stub.Get(pb.GetRequest(service="registry", property="services"), timeout=CALL_TIMEOUT)
    return set(parse_names(reply.value))


async def _timed_get(stub: pb_grpc.PropertyServiceStub, request: pb.GetRequest) -> float:
    start = time.perf_counter()
    await stub.Get(request, timeout=CALL_TIMEOUT)
    return time.perf_counter() - start


class OwnerWatch:
    """Listens to ``services.NAME.owner`` of every orphan: when each is owned by a gateway not ``killed``.

    Exact selectors, ``OWNER_SELECTORS`` a stream: a wildcard ``services.*.owner`` is expanded from
    the registry's ``properties`` list, which passes the 64 KiB limit of a value past about 250
    services.
    """

    def __init__(self, orphans: list[str], killed: str) -> None:
        self.orphans = orphans
        self.killed = killed
        #: Orphan → seconds from :attr:`killed_at` until it was owned again.
        self.owned: dict[str, float] = {}
        self.killed_at = 0.0
        self.following = asyncio.Event()

    async def follow(self, stub: pb_grpc.PropertyServiceStub) -> None:
        """Listen until cancelled; :attr:`following` is set once every stream has read the current owners."""
        calls = []
        for first in range(0, len(self.orphans), OWNER_SELECTORS):
            paths = [f"services.{name}.owner" for name in self.orphans[first : first + OWNER_SELECTORS]]
            more = [pb.PropertyRef(service="registry", property=path) for path in paths[1:]]
            calls.append(stub.Listen(pb.ListenRequest(service="registry", property=paths[0], more=more)))
        try:
            await asyncio.gather(*(read_until_sync(call) for call in calls))
            self.following.set()
            await asyncio.gather(*(self._read(call) for call in calls))
        finally:
            for call in calls:
                call.cancel()

    async def _read(self, call: Any) -> None:
        while (response := await call.read()) is not STREAM_END:
            now = time.perf_counter()
            for event in response.events:
                name = event.property.removeprefix("services.").removesuffix(".owner")
                if event.value not in ("", self.killed) and name not in self.owned:
                    self.owned[name] = now - self.killed_at


async def _answer_again(
    stub: pb_grpc.PropertyServiceStub, owned: dict[str, float], count: int, killed_at: float, deadline: float
) -> dict[str, float]:
    """Ask each device owned again for its location until it answers; seconds from ``killed_at`` to it."""
    answered: dict[str, float] = {}
    semaphore = asyncio.Semaphore(FAILOVER_IN_FLIGHT)

    async def ask(name: str) -> None:
        async with semaphore:
            try:
                await stub.Get(pb.GetRequest(service=name, property="location"), timeout=FAILOVER_GET_TIMEOUT)
            except grpc.aio.AioRpcError:
                return
            answered[name] = time.perf_counter() - killed_at

    while len(answered) < count and time.monotonic() < deadline:
        await asyncio.gather(*(ask(name) for name in list(owned) if name not in answered))
        await asyncio.sleep(FAILOVER_PAUSE)
    return answered


async def measure_registry(
    devices: int, *, gateways: int, queries: int, gets: int, time_limit: float
) -> dict[str, Any]:
    """The registry part (see the module docstring) on a fresh etcd, fresh farms and fresh gateways."""
    binary = etcd_binary()
    if binary is None:
        raise ServerError(ETCD_MISSING)
    limits = raise_fd_limit(2 * devices + FD_SPARE)
    deadline = time.monotonic() + time_limit
    started: list[ServerProcess] = []
    farms: list[ServerProcess] = []
    etcd: EtcdProcess | None = None
    result: dict[str, Any] = {
        "devices": devices,
        "gateways": gateways,
        "lease_s": STORE_LEASE,
        "fd_limits": limits,
    }
    with tempfile.TemporaryDirectory(prefix="bench-cluster-registry-") as name:
        folder = Path(name)
        try:
            etcd = await EtcdProcess.start(binary, folder)
            farms, ports = await start_farms(devices, folder)
            for number in range(1, gateways + 1):
                store = STORE_CONFIG.format(
                    etcd=etcd.address, lease=STORE_LEASE, id=f"gw{number}", devices=devices
                )
                started.append(await _start_gateway(folder, f"gw{number}", store))
            channels = [grpc.aio.insecure_channel(g.address) for g in started]
            try:
                stubs = [pb_grpc.PropertyServiceStub(channel) for channel in channels]
                result.update(
                    await _registry_figures(
                        stubs, started=started, ports=ports, queries=queries, gets=gets, deadline=deadline
                    )
                )
            finally:
                for channel in channels:
                    await channel.close(None)
            for farm in farms:
                farm.check_alive()
        finally:
            for gateway in reversed(started):
                await gateway.stop()
            for farm in farms:
                await farm.stop()
            if etcd is not None:
                await etcd.stop()
    return result


async def _registry_figures(
    stubs: list[pb_grpc.PropertyServiceStub],
    *,
    started: list[ServerProcess],
    ports: dict[str, int],
    queries: int,
    gets: int,
    deadline: float,
) -> dict[str, Any]:
    devices, count = len(ports), len(stubs)
    begun = time.perf_counter()
    ok, errors = await _register_spread(stubs, ports, deadline)
    registering = time.perf_counter() - begun
    while True:  # every gateway lists every device: the registrations went round the cluster
        listed = [len(await _listed(stub) & set(ports)) for stub in stubs]
        if min(listed) == devices or time.monotonic() > deadline:
            break
        await asyncio.sleep(0.1)
    everywhere = time.perf_counter() - begun

    find = pb.GetRequest(
        service="registry", property="find", parameters={"type": "mobile_robot", "limit": "10"}
    )
    found = [await _timed_get(stubs[k % count], find) for k in range(queries)]

    # Device k was registered on gateway k mod count, which owns it: ask gateway 0's own there and on 1.
    own = [device_name(k) for k in range(0, devices, count)][:10]
    local: list[float] = []
    forwarded: list[float] = []
    for k in range(gets):
        request = pb.GetRequest(service=own[k % len(own)], property="location")
        local.append(await _timed_get(stubs[0], request))
        forwarded.append(await _timed_get(stubs[1], request))

    victim = started[-1]
    orphans = [device_name(k) for k in range(count - 1, devices, count)]
    watch = OwnerWatch(orphans, killed=f"gw{count}")
    following = asyncio.create_task(watch.follow(stubs[0]))
    try:
        async with asyncio.timeout(CALL_TIMEOUT):
            await watch.following.wait()
        watch.killed_at = time.perf_counter()
        os.kill(victim.pid, signal.SIGKILL)
        answered = await _answer_again(stubs[0], watch.owned, len(orphans), watch.killed_at, deadline)
    finally:
        following.cancel()
        await asyncio.gather(following, return_exceptions=True)
    after = len(await _listed(stubs[0]) & set(ports))
    delays = list(answered.values())
    taken = list(watch.owned.values())
    local_p50 = _quantile(local, 0.5)
    return {
        "registered": ok,
        "first_errors": errors,
        "register_s": round(registering, 3),
        "register_per_s": round(ok / registering, 1) if registering else 0.0,
        "listed_by_each": listed,
        "visible_everywhere_s": round(everywhere, 3),
        "find_queries": queries,
        "find_p50_ms": round(1e3 * _quantile(found, 0.5), 2),
        "find_p99_ms": round(1e3 * _quantile(found, 0.99), 2),
        "local_get_p50_us": round(1e6 * local_p50),
        "forwarded_get_p50_us": round(1e6 * _quantile(forwarded, 0.5)),
        "forwarded_ratio": round(_quantile(forwarded, 0.5) / local_p50, 2) if local_p50 else math.nan,
        "killed_gateway_devices": len(orphans),
        "answered_again": len(answered),
        "owned_again": len(taken),
        "owned_again_p50_s": round(_quantile(taken, 0.5), 2),
        "owned_again_s": round(max(taken), 2) if taken else math.nan,
        "failover_p50_s": round(_quantile(delays, 0.5), 2),
        "failover_s": round(max(delays), 2) if delays else math.nan,
        "listed_after_failover": after,
        "complete": ok == devices
        and min(listed) == devices
        and len(answered) == len(taken) == len(orphans)
        and after == devices,
    }
