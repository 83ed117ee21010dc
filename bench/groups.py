"""Parts (f) and (g), in this process: a group's ``behaviors.moveto`` and the registry's ``find``.

Both run the services in-process, behind the gateway's own
:class:`gateway.engine.router.Router` as their directory (no gRPC), so the figures
are what the group and the registry themselves cost.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import Any

import numpy as np

from gateway.engine.router import Router
from services.apps.group import Group
from services.apps.registry import Registry, RegistryService
from services.apps.simulators import SimRobot, SimSensor
from services.kernel.core import LocalService
from services.kernel.values import parse_names

TARGET = "<marker><location>(0 0)</location></marker>"
#: A member answers a moveto at once; it only starts driving after (no tick until then).
MEMBER_TICK_HZ = 0.1


async def _fill(router: Router, services: list[tuple[str, LocalService]]) -> None:
    for name, backend in services:
        await backend.start()
        router.add(name, backend)


async def _empty(router: Router) -> None:
    for name in router.names():
        await router.remove(name).aclose()


async def measure_group_moveto(n: int, formation: str = "circle") -> dict[str, Any]:
    """Seconds until every one of ``n`` in-process simulated members accepted its moveto target.

    The members are :class:`SimRobot` services in a :class:`Router`; the group
    names them statically. The clock runs from the Set of ``behaviors.moveto``
    on the group to its reply, which lists the members that accepted.
    """
    router = Router()
    names = [f"r{i}" for i in range(n)]
    await _fill(
        router,
        [
            (name, LocalService(SimRobot(start=(i % 100, i // 100), tick_hz=MEMBER_TICK_HZ)))
            for i, name in enumerate(names)
        ],
    )
    group = LocalService(Group(directory=router, members=names))
    await group.start()
    try:
        start = time.perf_counter()
        accepted = await group.set("behaviors.moveto", TARGET, {"formation": formation})
        elapsed = time.perf_counter() - start
    finally:
        await group.aclose()
        await _empty(router)
    count = len(parse_names(accepted))
    return {
        "members": n,
        "formation": formation,
        "accepted": count,
        "seconds": round(elapsed, 5),
        "us_per_member": round(1e6 * elapsed / n, 2),
    }


async def measure_find(n: int, queries: int = 200, seed: int = 1) -> dict[str, Any]:
    """p50 and p99 of ``find`` (mobile robots within a radius of a point) over a registry of ``n`` services.

    Three in four services are :class:`SimRobot` (type ``mobile_robot``), one
    in four :class:`SimSensor` (``sensor``), placed uniformly at random on a
    square of about 9 m² per service. The registry learns their types and
    locations the ordinary way, from the directory and a Listen on each
    ``location``. Each query asks for the mobile robots within 3 m of a random
    point (``type=mobile_robot&near=(x y 0)&radius=3``).
    """
    rng = np.random.default_rng(seed)
    side = float(np.sqrt(n)) * 3  # about one service per 9 m²: a 3 m radius holds two or three robots
    router = Router()
    services: list[tuple[str, LocalService]] = []
    for i, (x, y) in enumerate(rng.uniform(0, side, size=(n, 2))):
        where = (round(float(x), 3), round(float(y), 3))
        if i % 4:
            services.append((f"r{i}", LocalService(SimRobot(start=where, tick_hz=MEMBER_TICK_HZ))))
        else:
            services.append((f"s{i}", LocalService(SimSensor(location=where))))
    await _fill(router, services)
    registry = Registry(directory=router, period=0)
    service = RegistryService(registry)
    await service.start()
    times: list[int] = []
    matches: list[int] = []
    try:
        # Every service located: the first query with ``near`` waits for locations still on the way.
        await service.get("find", {"near": "(0 0 0)", "radius": "1"})
        first = time.perf_counter_ns()
        await service.get("find", {"type": "mobile_robot", "near": "(5 5 0)", "radius": "3"})
        first_ns = time.perf_counter_ns() - first
        for centre in rng.uniform(0, side, size=(queries, 2)):
            params = {"type": "mobile_robot", "near": f"({centre[0]:.2f} {centre[1]:.2f} 0)", "radius": "3"}
            start = time.perf_counter_ns()
            found = await service.get("find", params)
            times.append(time.perf_counter_ns() - start)
            matches.append(len(parse_names(found)))
        indexed = len(registry.names())
    finally:
        await service.aclose()
        await _empty(router)
    us = np.asarray(times, dtype=np.float64) / 1000.0
    p50, p99 = np.percentile(us, [50, 99])
    return {
        "entries": n,
        "indexed": indexed,
        "queries": queries,
        "p50_us": round(float(p50), 1),
        "p99_us": round(float(p99), 1),
        "max_us": round(float(us.max()), 1),
        "first_us": round(first_ns / 1000.0, 1),
        "matches_mean": round(float(np.mean(matches)), 2),
    }


async def run_scaling(
    measure: str, sizes: tuple[int, ...], time_limit: float, **options: Any
) -> dict[str, Any]:
    """Run ``measure_group_moveto`` or ``measure_find`` at each size; stop early past ``time_limit``."""
    measures: dict[str, Callable[..., Awaitable[dict[str, Any]]]] = {
        "group": measure_group_moveto,
        "find": measure_find,
    }
    started = time.monotonic()
    done: list[dict[str, Any]] = []
    skipped: list[int] = []
    for n in sizes:
        if time.monotonic() - started > time_limit:
            skipped.append(n)
            continue
        async with asyncio.timeout(max(time_limit * 2, 60.0)):
            done.append(await measures[measure](n, **options))
    return {"sizes": done, "skipped": skipped, "complete": not skipped}
