"""Part (t), scale-out: a registry on etcd shared by gateway processes.

``devices`` line-protocol devices (simulated robots multiplexed on
:mod:`bench.device_farm` processes, as in part (h)) across ``gateways`` (4)
gateway processes sharing one registry in etcd (Debian's ``etcd``, one member,
in a temporary folder; the part is not run without it). Each device is
registered by a Set on gateway ``k mod 4``, 32 Sets in flight in all: the
registration rate, then the time until every gateway lists every device. Then
``queries`` Gets of the registry's ``find`` (``type=mobile_robot``,
``limit=10``) taking turns over the gateways (p50, p99); ``gets`` Gets of a
device's ``location`` one at a time, on its owner (local) and on another
gateway (forwarded), taking turns (p50 of each and their ratio). Before those,
once every gateway reads every device ``up`` and typed (its forwarding set up
and its type learnt), the cluster is left alone for ``rest`` seconds
(``REST_SECONDS``, 5): each
gateway's CPU over that rest, then its RSS and open files, compared with what
it held before the first registration (per service it serves: every device of
the cluster), and its established TCP connections to the other gateways' gRPC
ports (how many channels it forwards over). Last, the
gateway that owns a quarter of the devices is SIGKILLed. Exact Listens on each
of its devices' ``services.NAME.owner`` tell when it is owned again, Gets of
its ``location`` through a survivor when it answers again (the new owner has
connected to it); every registration must still be listed. The first and the
last of each are kept: the first is the lease running out, the spread between
them is the survivors taking the orphans over.

Run alone, at any size (``python -m bench.cluster_registry --devices 4000
--gateways 2``); ``--profile FOLDER`` records each survivor with py-spy from the
kill until every orphan answers again (collapsed stacks, one file a gateway).
"""

from __future__ import annotations

import argparse
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
from pathlib import Path
from typing import Any

import grpc

from bench.cluster import CALL_TIMEOUT, READY_TIMEOUT, start_gateway
from bench.device_farm import FD_SPARE, device_name, raise_fd_limit
from bench.measure import STREAM_END
from bench.register import start_farms
from bench.servers import ServerError, ServerProcess, end_process
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.kernel.values import parse_names

#: Seconds of each gateway's etcd lease in the registry part: how long a dead gateway's devices wait.
STORE_LEASE = 5.0
#: Registration Sets in flight in all, as in part (h).
REGISTER_IN_FLIGHT = 32
#: Gets in flight while waiting for a dead gateway's devices to answer again.
FAILOVER_IN_FLIGHT = 64
#: Characters of each gateway's log kept in the results of a run that did not complete.
LOG_TAIL_CHARS = 2000
#: Exact selectors one Listen carries (``[limits] max_selectors``, 64 by default).
OWNER_SELECTORS = 64
#: Seconds a Get of a device taken over may take while waiting for it to answer again.
FAILOVER_GET_TIMEOUT = 2.0
#: Seconds between rounds of asking the devices that have not answered yet.
FAILOVER_PAUSE = 0.1
#: Seconds the settled cluster is left alone while each gateway's CPU time is read (its CPU at rest).
REST_SECONDS = 5.0
#: Devices whose state and type one Get reads while waiting for the cluster to settle: two paths
#: each, within a gateway's default ``[limits] max_get_paths`` (1,000).
SETTLE_CHUNK = 400
#: Seconds between looks at whether the cluster has settled.
SETTLE_PAUSE = 0.5
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


async def _unsettled(stub: pb_grpc.PropertyServiceStub, names: list[str]) -> int:
    """How many of ``names`` the gateway of ``stub`` does not read ``up`` with a known type yet."""
    waiting = 0
    for first in range(0, len(names), SETTLE_CHUNK):
        chunk = names[first : first + SETTLE_CHUNK]
        paths = [f"services.{name}.{what}" for name in chunk for what in ("state", "type")]
        more = [pb.PropertyRef(property=path) for path in paths[1:]]
        reply = await stub.Get(
            pb.GetRequest(service="registry", property=paths[0], more=more), timeout=CALL_TIMEOUT
        )
        values = [reply.value, *(item.value for item in reply.more)]
        waiting += sum(
            1
            for state, kind in zip(values[::2], values[1::2], strict=True)
            if state != "up" or kind in ("", "unknown")
        )
    return waiting


def _footprint(started: list[ServerProcess]) -> dict[str, list[int]]:
    return {"rss": [g.rss_bytes() for g in started], "fds": [g.open_files() for g in started]}


async def _at_rest(
    stubs: list[pb_grpc.PropertyServiceStub],
    started: list[ServerProcess],
    names: list[str],
    before: dict[str, list[int]],
    *,
    deadline: float,
    rest: float,
) -> dict[str, Any]:
    """Wait until every gateway reads every device up and typed, leave the cluster alone for
    ``rest`` seconds, and read what each gateway holds then (see the module docstring)."""
    begun = time.perf_counter()
    waiting = [len(names)] * len(stubs)
    while max(waiting) and time.monotonic() < deadline:
        waiting = [await _unsettled(stub, names) for stub in stubs]
        if max(waiting):
            await asyncio.sleep(SETTLE_PAUSE)
    settled = time.perf_counter() - begun
    cpu = [g.cpu_seconds() for g in started]
    rest_begun = time.perf_counter()
    await asyncio.sleep(rest)
    rested = time.perf_counter() - rest_begun
    cpu = [g.cpu_seconds() - c for g, c in zip(started, cpu, strict=True)]
    after = _footprint(started)
    ports = [int(g.address.rsplit(":", 1)[1]) for g in started]
    served = max(1, len(names))
    return {
        "settled_s": round(settled, 2),
        "unsettled_by_each": waiting,
        "rest_s": round(rested, 2),
        "rest_cpu_percent": [round(100 * c / rested, 2) for c in cpu],
        "rss_mib": [round(rss / 2**20, 1) for rss in after["rss"]],
        "rss_kib_per_service": [
            round((a - b) / 1024 / served, 2) for a, b in zip(after["rss"], before["rss"], strict=True)
        ],
        "fds": after["fds"],
        "fds_added": [a - b for a, b in zip(after["fds"], before["fds"], strict=True)],
        "connections_to_other_gateways": [
            g.connections_to(set(ports) - {own}) for g, own in zip(started, ports, strict=True)
        ],
    }


async def _timed_get(stub: pb_grpc.PropertyServiceStub, request: pb.GetRequest) -> float:
    start = time.perf_counter()
    await stub.Get(request, timeout=CALL_TIMEOUT)
    return time.perf_counter() - start


class OwnerWatch:
    """Listens to ``services.NAME.owner`` of every orphan: when each is owned by a gateway not ``killed``.

    Exact selectors, ``OWNER_SELECTORS`` a stream: only the orphans are followed (a wildcard
    ``services.*.owner`` would follow every registration of the cluster). A stream that ends is
    opened again, and the current owners it reads then count as heard at that moment (a change
    made meanwhile is not lost, only heard late); how many ended, and the first reason, are kept.
    """

    def __init__(self, orphans: list[str], killed: str) -> None:
        self.orphans = orphans
        self.killed = killed
        #: Orphan → seconds from :attr:`killed_at` until it was owned again.
        self.owned: dict[str, float] = {}
        self.killed_at = 0.0
        self.following = asyncio.Event()
        self.ended = 0
        self.first_end = ""

    async def follow(self, stub: pb_grpc.PropertyServiceStub) -> None:
        """Listen until cancelled; :attr:`following` is set once every stream has read the current owners."""
        chunks = [self.orphans[k : k + OWNER_SELECTORS] for k in range(0, len(self.orphans), OWNER_SELECTORS)]
        synced = [asyncio.Event() for _ in chunks]
        watches = [asyncio.create_task(self._watch(stub, c, e)) for c, e in zip(chunks, synced, strict=True)]
        try:
            await asyncio.gather(*(event.wait() for event in synced))
            self.following.set()
            await asyncio.gather(*watches)
        finally:
            for watch in watches:
                watch.cancel()
            await asyncio.gather(*watches, return_exceptions=True)

    async def _watch(
        self, stub: pb_grpc.PropertyServiceStub, names: list[str], synced: asyncio.Event
    ) -> None:
        paths = [f"services.{name}.owner" for name in names]
        more = [pb.PropertyRef(service="registry", property=path) for path in paths[1:]]
        request = pb.ListenRequest(service="registry", property=paths[0], more=more)
        while True:
            call = stub.Listen(request)
            try:
                while (response := await call.read()) is not STREAM_END:
                    if response.sync:
                        synced.set()
                    else:
                        self._heard(response.events)
                reason = f"{await call.code()}: {await call.details()}"
            except grpc.aio.AioRpcError as exc:
                reason = f"{exc.code().name}: {exc.details()}"
            finally:
                call.cancel()
            self.ended += 1
            self.first_end = self.first_end or reason
            await asyncio.sleep(FAILOVER_PAUSE)

    def _heard(self, events: Any) -> None:
        if not self.following.is_set():
            return  # the owners before the kill
        now = time.perf_counter()
        for event in events:
            name = event.property.removeprefix("services.").removesuffix(".owner")
            if event.value not in ("", self.killed) and name not in self.owned:
                self.owned[name] = now - self.killed_at


async def _answer_again(
    stub: pb_grpc.PropertyServiceStub, orphans: list[str], killed_at: float, deadline: float
) -> dict[str, float]:
    """Ask each orphan for its location until it answers; seconds from ``killed_at`` to its answer.

    Until a survivor owns it a Get fails at once (no owner) or within ``FAILOVER_GET_TIMEOUT``.
    """
    answered: dict[str, float] = {}
    semaphore = asyncio.Semaphore(FAILOVER_IN_FLIGHT)

    async def ask(name: str) -> None:
        async with semaphore:
            try:
                await stub.Get(pb.GetRequest(service=name, property="location"), timeout=FAILOVER_GET_TIMEOUT)
            except grpc.aio.AioRpcError:
                return
            answered[name] = time.perf_counter() - killed_at

    while len(answered) < len(orphans) and time.monotonic() < deadline:
        await asyncio.gather(*(ask(name) for name in orphans if name not in answered))
        await asyncio.sleep(FAILOVER_PAUSE)
    return answered


async def measure_registry(
    devices: int,
    *,
    gateways: int,
    queries: int,
    gets: int,
    time_limit: float,
    profile: Path | None = None,
    rest: float = REST_SECONDS,
) -> dict[str, Any]:
    """The registry part (see the module docstring) on a fresh etcd, fresh farms and fresh gateways;
    ``profile``: a folder where py-spy's record of each survivor's failover is written."""
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
                started.append(await start_gateway(folder, f"gw{number}", store))
            channels = [grpc.aio.insecure_channel(g.address) for g in started]
            try:
                stubs = [pb_grpc.PropertyServiceStub(channel) for channel in channels]
                try:
                    await _registry_figures(
                        result,
                        stubs,
                        started=started,
                        ports=ports,
                        queries=queries,
                        gets=gets,
                        deadline=deadline,
                        profile=profile,
                        rest=rest,
                    )
                except (grpc.aio.AioRpcError, TimeoutError) as exc:
                    # What was measured before stays in the results (the cluster at rest, say).
                    result["error"] = f"{type(exc).__name__}: {exc}"[:LOG_TAIL_CHARS]
                    result["complete"] = False
            finally:
                for channel in channels:
                    await channel.close(None)
            if not result["complete"]:  # what the gateways said: the end of each one's log
                result["gateway_logs"] = {g.kind: g.log_tail[-LOG_TAIL_CHARS:] for g in started}
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
    result: dict[str, Any],
    stubs: list[pb_grpc.PropertyServiceStub],
    *,
    started: list[ServerProcess],
    ports: dict[str, int],
    queries: int,
    gets: int,
    deadline: float,
    profile: Path | None,
    rest: float,
) -> None:
    """Measure the cluster into ``result``, each figure as soon as it is known."""
    devices, count = len(ports), len(stubs)
    before = _footprint(started)
    begun = time.perf_counter()
    ok, errors = await _register_spread(stubs, ports, deadline)
    registering = time.perf_counter() - begun
    while True:  # every gateway lists every device: the registrations went round the cluster
        listed = [len(await _listed(stub) & set(ports)) for stub in stubs]
        if min(listed) == devices or time.monotonic() > deadline:
            break
        await asyncio.sleep(0.1)
    everywhere = time.perf_counter() - begun
    result.update(
        registered=ok,
        first_errors=errors,
        register_s=round(registering, 3),
        register_per_s=round(ok / registering, 1) if registering else 0.0,
        listed_by_each=listed,
        visible_everywhere_s=round(everywhere, 3),
    )
    at_rest = result["at_rest"] = await _at_rest(
        stubs, started, list(ports), before, deadline=deadline, rest=rest
    )

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
        recorders = await _start_profiles(profile, started[:-1])
        watch.killed_at = time.perf_counter()
        os.kill(victim.pid, signal.SIGKILL)
        try:
            answered = await _answer_again(stubs[0], orphans, watch.killed_at, deadline)
        finally:
            await _stop_profiles(recorders)
    finally:
        following.cancel()
        await asyncio.gather(following, return_exceptions=True)
    after = len(await _listed(stubs[0]) & set(ports))
    delays = list(answered.values())
    taken = list(watch.owned.values())
    local_p50 = _quantile(local, 0.5)
    result.update(
        {
            "find_queries": queries,
            "find_p50_ms": round(1e3 * _quantile(found, 0.5), 2),
            "find_p99_ms": round(1e3 * _quantile(found, 0.99), 2),
            "local_get_p50_us": round(1e6 * local_p50),
            "forwarded_get_p50_us": round(1e6 * _quantile(forwarded, 0.5)),
            "forwarded_ratio": round(_quantile(forwarded, 0.5) / local_p50, 2) if local_p50 else math.nan,
            "killed_gateway_devices": len(orphans),
            "answered_again": len(answered),
            "owned_again": len(taken),
            "owner_streams_ended": watch.ended,
            "owner_streams_first_end": watch.first_end,
            "owned_again_first_s": round(min(taken), 2) if taken else math.nan,
            "owned_again_p50_s": round(_quantile(taken, 0.5), 2),
            "owned_again_s": round(max(taken), 2) if taken else math.nan,
            "failover_first_s": round(min(delays), 2) if delays else math.nan,
            "failover_p50_s": round(_quantile(delays, 0.5), 2),
            "failover_s": round(max(delays), 2) if delays else math.nan,
            "listed_after_failover": after,
            "complete": ok == devices
            and min(listed) == devices
            and len(answered) == len(taken) == len(orphans)
            and after == devices
            and not max(at_rest["unsettled_by_each"]),
        }
    )


async def _start_profiles(
    folder: Path | None, gateways: list[ServerProcess]
) -> list[asyncio.subprocess.Process]:
    """py-spy recording each of ``gateways`` into ``folder`` (none without a folder)."""
    if folder is None:
        return []
    binary = shutil.which("py-spy")
    if binary is None:
        raise ServerError("--profile needs py-spy (pip install py-spy)")
    await asyncio.to_thread(folder.mkdir, parents=True, exist_ok=True)
    recorders = []
    for gateway in gateways:
        argv = [binary, "record", "--pid", str(gateway.pid), "--rate", "100", "--format", "raw"]
        argv += ["--output", str(folder / f"{gateway.kind}.txt")]
        recorders.append(
            await asyncio.create_subprocess_exec(
                *argv, stdin=asyncio.subprocess.DEVNULL, stdout=asyncio.subprocess.DEVNULL
            )
        )
    await asyncio.sleep(1.0)  # py-spy attaches to the process before the kill
    return recorders


async def _stop_profiles(recorders: list[asyncio.subprocess.Process]) -> None:
    """Stop each recorder as Ctrl-C does: py-spy writes its file, then exits."""
    for recorder in recorders:
        with contextlib.suppress(ProcessLookupError):
            recorder.send_signal(signal.SIGINT)
    for recorder in recorders:
        try:
            async with asyncio.timeout(30):
                await recorder.wait()
        except TimeoutError:
            await end_process(recorder)


def main(argv: list[str] | None = None) -> None:
    """Run the registry part alone and print its figures as JSON."""
    parser = argparse.ArgumentParser(
        prog="python -m bench.cluster_registry", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--devices", type=int, default=4_000, help="devices registered (default 4000)")
    parser.add_argument("--gateways", type=int, default=4, help="gateway processes, 2 to 16 (default 4)")
    parser.add_argument("--queries", type=int, default=200, help="finds and Gets each way (default 200)")
    parser.add_argument("--time-limit", type=float, default=600.0, help="seconds the run may take")
    parser.add_argument(
        "--profile", type=Path, help="a folder for py-spy's record of each survivor's failover"
    )
    parser.add_argument(
        "--rest", type=float, default=REST_SECONDS, help=f"seconds of rest (default {REST_SECONDS:g})"
    )
    args = parser.parse_args(argv)
    if not 2 <= args.gateways <= 16 or args.devices < args.gateways or args.queries < 1:
        parser.error("expected 2 to 16 gateways, at least as many devices, and at least one query")
    result = asyncio.run(
        measure_registry(
            args.devices,
            gateways=args.gateways,
            queries=args.queries,
            gets=args.queries,
            time_limit=args.time_limit,
            profile=args.profile,
            rest=args.rest,
        )
    )
    json.dump(result, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
