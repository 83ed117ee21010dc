"""Part (m), in this process: the registry scheduler's decision time beside a plain ``find``.

A registry of ``n`` entries (three in four ``mobile_robot`` with the feature ``survey``, one in
four ``sensor``), each at a random place on a square of about 9 m² per entry, as
:func:`bench.groups.measure_find` lays them out. One round is a ``request`` for ``(survey)`` near
a random point (the decision: rules, cost, QoS, cover; then one licence granted) and the
``release`` of its allocation with an assessment. The baseline, in the same run and over the same
registry, is the plain ``find`` of the mobile robots near the same points (``type`` and ``near``):
what the registry costs before any scheduling.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from services.apps.registry import Registry, RegistryService
from services.kernel.backend import BackendInfo
from services.kernel.values import parse_list


async def measure_scheduler(n: int, rounds: int = 200, seed: int = 1) -> dict[str, Any]:
    """p50 and p99 of a scheduler ``request`` and of a ``find`` over ``n`` registry entries, and the
    first request after the table changed (it indexes every entry's capabilities anew)."""
    rng = np.random.default_rng(seed)
    side = float(np.sqrt(n)) * 3
    features = {}
    registry_names = []
    for i, (x, y) in enumerate(rng.uniform(0, side, size=(n, 2))):
        name, kind = (f"r{i}", "mobile_robot") if i % 4 else (f"s{i}", "sensor")
        registry_names.append((name, kind, np.array([x, y, 0.0])))
        if kind == "mobile_robot":
            features[name] = ("survey",)
    registry = Registry(period=0, features=features)
    service = RegistryService(registry)
    await service.start()
    for name, kind, where in registry_names:
        registry.add(name, BackendInfo(type=kind, url="local"))
        registry.set_location(name, where)
    request_ns: list[int] = []
    find_ns: list[int] = []
    try:
        # The first request after the table changed reads every entry's capabilities once.
        start = time.perf_counter_ns()
        answer = await service.set("request", "(survey)", {"consumer": "first", "wait": "0"})
        first_ns = time.perf_counter_ns() - start
        await service.set("release", "", {"allocation": parse_list(answer)[0]})
        for i, centre in enumerate(rng.uniform(0, side, size=(rounds, 2))):
            near = f"({centre[0]:.2f} {centre[1]:.2f})"
            start = time.perf_counter_ns()
            await service.get("find", {"type": "mobile_robot", "near": near, "limit": "1"})
            find_ns.append(time.perf_counter_ns() - start)
            start = time.perf_counter_ns()
            answer = await service.set(
                "request", "(survey)", {"consumer": f"c{i}", "location": near, "wait": "0"}
            )
            request_ns.append(time.perf_counter_ns() - start)
            allocation_id, status, chosen = parse_list(answer)
            assert status == "granted" and len(chosen) == 1, answer
            await service.set("release", "", {"allocation": allocation_id, "qos": f"(({chosen[0][0]} 0.9))"})
    finally:
        await service.aclose()
    req = np.asarray(request_ns, dtype=np.float64) / 1000.0
    base = np.asarray(find_ns, dtype=np.float64) / 1000.0
    req50, req99 = np.percentile(req, [50, 99])
    find50, find99 = np.percentile(base, [50, 99])
    return {
        "entries": n,
        "rounds": rounds,
        "request_p50_us": round(float(req50), 1),
        "request_p99_us": round(float(req99), 1),
        "find_p50_us": round(float(find50), 1),
        "find_p99_us": round(float(find99), 1),
        "ratio_p50": round(float(req50 / find50), 2),
        "first_request_us": round(first_ns / 1000.0, 1),
    }


async def run_scheduler(sizes: tuple[int, ...], rounds: int, time_limit: float) -> dict[str, Any]:
    """:func:`measure_scheduler` at each size; sizes past ``time_limit`` are skipped."""
    started = time.monotonic()
    done: list[dict[str, Any]] = []
    skipped: list[int] = []
    for n in sizes:
        if time.monotonic() - started > time_limit:
            skipped.append(n)
            continue
        done.append(await measure_scheduler(n, rounds))
    return {"sizes": done, "skipped": skipped, "complete": not skipped}
