"""Part (h): members registered over raw TCP, each with a live connection held by the gateway.

Processes: one gateway (``python -m gateway serve`` with an empty config:
only its built-in ``registry``), the devices in one or a few
``python -m bench.device_farm`` processes (at most ``FARM_SIZE`` devices
each, every device on its own port), and this one. With every process up
and settled, the gateway's RSS is read; then every device is registered by
a unary Set of ``registry`` / ``services.<name>`` to ``tcp://127.0.0.1:PORT``,
``concurrency`` Sets in flight. Each Set returns once the gateway has opened
the proxy, had the device's greeting and a Get of ``properties`` answered.
The clock runs from the first Set to the last reply; after a settling pause
the RSS is read again and the registry's ``services`` list is counted. The
gateway's CPU time is read at both ends of the clock (CPU per registration)
and over the settling pause (what the registered devices cost it at rest).
"""

from __future__ import annotations

import asyncio
import json
import math
import tempfile
import time
from pathlib import Path
from typing import Any

import grpc

from bench.device_farm import FD_SPARE, device_name, raise_fd_limit
from bench.servers import ServerProcess
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.kernel.values import parse_names

FARM_SIZE = 500
SETTLE_S = 1.0
CALL_TIMEOUT = 30.0
GATEWAY_CONFIG = '[gateway]\nlisten = "127.0.0.1:0"\nlog_level = "warning"\n'
#: The registry holds at most 256 registrations by default (``[registry] max_registrations``).
REGISTRY_CONFIG = "[registry]\nmax_registrations = {members}\n"


async def _register(
    stub: pb_grpc.PropertyServiceStub, ports: dict[str, int], concurrency: int, time_limit: float
) -> tuple[int, list[str], list[float]]:
    """Register every device, ``concurrency`` Sets in flight; return successes, first errors, latencies."""
    pending = list(ports.items())
    pending.reverse()
    ok = 0
    errors: list[str] = []
    latencies: list[float] = []
    deadline = time.monotonic() + time_limit

    async def worker() -> None:
        nonlocal ok
        while pending and time.monotonic() < deadline:
            name, port = pending.pop()
            request = pb.SetRequest(
                service="registry", property=f"services.{name}", value=f"tcp://127.0.0.1:{port}"
            )
            start = time.perf_counter()
            try:
                await stub.Set(request, timeout=CALL_TIMEOUT)
            except grpc.aio.AioRpcError as exc:
                if len(errors) < 10:
                    errors.append(f"{name}: {exc.code().name} {exc.details()}")
                continue
            latencies.append(time.perf_counter() - start)
            ok += 1

    await asyncio.gather(*(worker() for _ in range(concurrency)))
    return ok, errors, latencies


async def start_farms(members: int, folder: Path) -> tuple[list[ServerProcess], dict[str, int]]:
    """Start the device farms for ``members`` devices (``FARM_SIZE`` a farm); return them and name → port.

    The caller stops the farms; on a failure here the ones started are stopped.
    """
    farms: list[ServerProcess] = []
    ports: dict[str, int] = {}
    try:
        for first in range(0, members, FARM_SIZE):
            count = min(FARM_SIZE, members - first)
            ports_file = folder / f"farm{first}.json"
            argv = [
                "bench.device_farm", "--count", str(count), "--first", str(first),
                "--ports-file", str(ports_file),
            ]  # fmt: skip
            farms.append(await ServerProcess.start(f"device farm {first}", argv))
            ports.update(json.loads(ports_file.read_text()))
    except BaseException:
        for farm in farms:
            await farm.stop()
        raise
    return farms, ports


async def measure_register(
    ports: dict[str, int], folder: Path, *, concurrency: int, time_limit: float
) -> dict[str, Any]:
    """Start a fresh gateway, register the devices of ``ports``, measure time, CPU and gateway memory."""
    members = len(ports)
    gateway: ServerProcess | None = None
    result: dict[str, Any] = {"members": members, "concurrency": concurrency}
    try:
        config = folder / f"gateway{members}.toml"
        config.write_text(GATEWAY_CONFIG + REGISTRY_CONFIG.format(members=members))
        gateway = await ServerProcess.start(
            "gateway", ["gateway", "serve", "--config", str(config), "--log-level", "warning"]
        )
        async with grpc.aio.insecure_channel(gateway.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            await stub.Get(pb.GetRequest(service="registry", property="services"), timeout=CALL_TIMEOUT)
            await asyncio.sleep(SETTLE_S)
            rss_before = gateway.rss_bytes()
            fds_before = gateway.open_files()
            cpu_start = gateway.cpu_seconds()
            start = time.perf_counter()
            ok, errors, latencies = await _register(stub, ports, concurrency, time_limit)
            elapsed = time.perf_counter() - start
            cpu_end = gateway.cpu_seconds()
            await asyncio.sleep(SETTLE_S)
            # What the registered devices cost the gateway while nobody calls (liveness, keep-alives).
            idle_cores = (gateway.cpu_seconds() - cpu_end) / SETTLE_S
            rss_after = gateway.rss_bytes()
            fds_after = gateway.open_files()
            listed = await stub.Get(
                pb.GetRequest(service="registry", property="services"), timeout=CALL_TIMEOUT
            )
            probe = await stub.Get(
                pb.GetRequest(service=device_name(members - 1), property="location"), timeout=CALL_TIMEOUT
            )
        gateway.check_alive()
    finally:
        if gateway is not None:
            await gateway.stop()
    names = set(parse_names(listed.value))
    registered = sum(1 for name in ports if name in names)
    ordered = sorted(latencies)

    def pick(q: float) -> float:
        return (
            round(1e3 * ordered[min(len(ordered) - 1, math.floor(q * len(ordered)))], 2)
            if ordered
            else math.nan
        )

    result.update(
        {
            "farms": math.ceil(members / FARM_SIZE),
            "registered": registered,
            "errors": members - ok,
            "first_errors": errors,
            "complete": registered == members,
            "seconds": round(elapsed, 3),
            "per_s": round(ok / elapsed, 1) if elapsed else 0.0,
            "set_p50_ms": pick(0.50),
            "set_p99_ms": pick(0.99),
            "gateway_cpu_us_per_member": round(1e6 * (cpu_end - cpu_start) / max(ok, 1)),
            "gateway_idle_cores": round(idle_cores, 3),
            "rss_before_mib": round(rss_before / 2**20, 2),
            "rss_after_mib": round(rss_after / 2**20, 2),
            "kib_per_member": round((rss_after - rss_before) / max(registered, 1) / 1024, 1),
            "gateway_fds_before": fds_before,
            "gateway_fds_after": fds_after,
            "last_member_answered": bool(probe.value),
        }
    )
    return result


async def run_register(
    sizes: tuple[int, ...], *, concurrency: int, time_limit: float, rounds: int = 1
) -> dict[str, Any]:
    """Measure registration at each size, a fresh gateway each time, the sizes taking turns for ``rounds``.

    The farms for the largest size are started once and serve every round
    (each gateway registers the first N of their devices); each size keeps
    its fastest round, beside every round's rate.
    """
    limits = raise_fd_limit(2 * max(sizes) + FD_SPARE)
    seen: dict[int, list[dict[str, Any]]] = {n: [] for n in sizes}
    with tempfile.TemporaryDirectory(prefix="bench-register-") as folder:
        farms, ports = await start_farms(max(sizes), Path(folder))
        try:
            for _ in range(rounds):
                for n in sizes:
                    first = {device_name(k): ports[device_name(k)] for k in range(n)}
                    seen[n].append(
                        await measure_register(
                            first, Path(folder), concurrency=concurrency, time_limit=time_limit
                        )
                    )
            for farm in farms:
                farm.check_alive()
        finally:
            for farm in farms:
                await farm.stop()
    done = []
    for n in sizes:
        best = max(seen[n], key=lambda figures: float(figures["per_s"]))
        done.append({**best, "fd_limits": limits, "rounds_per_s": [f["per_s"] for f in seen[n]]})
    return {"sizes": done, "complete": all(d["complete"] for d in done)}
