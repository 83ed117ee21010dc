"""Part (j): the storage service — Get and Set of a file through the gateway, beside plain file I/O.

A gateway process serves a ``storage`` service on a folder of a temporary
directory; this process Gets and Sets one file of 1 KiB and one of 1 MiB
(text) through it, one call at a time with unary calls, and does the same
with plain Python file I/O on the same filesystem in the same run: a read is
``open().read()`` and a decode, a write is what an application that must not
lose or tear a file does (a temporary file, written, ``fsync``-ed, renamed,
and the directory ``fsync``-ed), which is what the storage service does too.
The two take turns call by call, so that load from elsewhere on the machine
falls on both alike. The ratios (p50 over p50) say what the gateway adds to
the disk's own cost.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import grpc

from bench.servers import ServerProcess
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

#: File sizes measured, by the name used in the results.
SIZES = {"1k": 1024, "1m": 1024 * 1024}
SERVICE = "store"
CALL_TIMEOUT = 30.0


def _text(size: int, turn: int) -> str:
    return (chr(ord("a") + turn % 26)) * size


def _plain_write(folder: Path, name: str, data: bytes) -> None:
    temp = folder / f".{name}.tmp"
    fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(temp, folder / name)
    dir_fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def _plain_read(path: Path) -> str:
    with open(path, "rb") as f:
        return f.read().decode("utf-8")


def _figures(latencies: list[float], calls: int, wall: float) -> dict[str, Any]:
    if not latencies:
        raise RuntimeError("no call finished within the time limit")
    ordered = sorted(latencies)
    return {
        "done": len(latencies),
        "complete": len(latencies) == calls,
        "p50_us": round(statistics.median(ordered) * 1e6, 1),
        "p99_us": round(ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))] * 1e6, 1),
        "per_s": round(len(latencies) / wall, 1) if wall else 0.0,
    }


async def _side_by_side(
    calls: int,
    deadline: float,
    gateway: Callable[[int], Awaitable[None]],
    plain: Callable[[int], Awaitable[None]],
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Each turn one gateway call, then one plain call: load from elsewhere falls on both alike."""
    times: tuple[list[float], list[float]] = ([], [])
    walls = [0.0, 0.0]
    for turn in range(calls):
        if time.perf_counter() > deadline:
            break
        for side, one in enumerate((gateway, plain)):
            t0 = time.perf_counter()
            await one(turn)
            spent = time.perf_counter() - t0
            times[side].append(spent)
            walls[side] += spent
    return _figures(times[0], calls, walls[0]), _figures(times[1], calls, walls[1])


async def _one_size(
    stub: pb_grpc.PropertyServiceStub, plain: Path, label: str, *, size: int, calls: int, deadline: float
) -> dict[str, Any]:
    """Sets, then Gets, of one file through the gateway; then the same with plain file I/O."""
    name = f"file-{label}.txt"
    params = {"name": name}
    texts = [_text(size, turn) for turn in range(2)]

    async def gateway_set(turn: int) -> None:
        request = pb.SetRequest(service=SERVICE, property="file", parameters=params, value=texts[turn % 2])
        await stub.Set(request, timeout=CALL_TIMEOUT)

    async def gateway_get(turn: int) -> None:
        request = pb.GetRequest(service=SERVICE, property="file", parameters=params)
        reply = await stub.Get(request, timeout=CALL_TIMEOUT)
        if len(reply.value) != size:
            raise RuntimeError(f"a Get of {name} answered {len(reply.value)} characters")

    async def plain_set(turn: int) -> None:
        _plain_write(plain, name, texts[turn % 2].encode("utf-8"))

    async def plain_get(turn: int) -> None:
        if len(_plain_read(plain / name)) != size:
            raise RuntimeError(f"a read of {name} came back short")

    figures: dict[str, Any] = {}
    figures["gateway_set"], figures["plain_set"] = await _side_by_side(
        calls, deadline, gateway_set, plain_set
    )
    figures["gateway_get"], figures["plain_get"] = await _side_by_side(
        calls, deadline, gateway_get, plain_get
    )
    for op in ("get", "set"):
        figures[f"{op}_ratio"] = round(
            figures[f"gateway_{op}"]["p50_us"] / figures[f"plain_{op}"]["p50_us"], 2
        )
    figures["bytes"] = size
    return figures


async def run_storage(*, calls: int, time_limit: float) -> dict[str, Any]:
    """Get and Set p50 of each size through the gateway and with plain file I/O, and their ratios."""
    results: dict[str, Any] = {"sizes": {}}
    with tempfile.TemporaryDirectory(prefix="bench-storage-") as tmp:
        root = Path(tmp)
        plain = root / "plain"
        plain.mkdir()
        config = root / "storage.toml"
        config.write_text(
            f'[gateway]\nlog_level = "warning"\n[[services]]\nname = "{SERVICE}"\ntype = "storage"\n'
            'options = { directory = "served" }\n'
        )
        server = await ServerProcess.start(
            "gateway storage",
            ["gateway.cli", "serve", "--config", str(config), "--listen", "127.0.0.1:0"],
            address_on="stdout",
        )
        try:
            async with grpc.aio.insecure_channel(server.address) as channel:
                stub = pb_grpc.PropertyServiceStub(channel)
                for label, size in SIZES.items():
                    # Fewer calls of the big file: each moves a MiB through a socket and a disk.
                    n = calls if size <= 64 * 1024 else max(calls // 10, 20)
                    deadline = time.perf_counter() + time_limit
                    results["sizes"][label] = await _one_size(
                        stub, plain, label, size=size, calls=n, deadline=deadline
                    )
        finally:
            await server.stop()
    results["complete"] = all(
        d[k]["complete"]
        for d in results["sizes"].values()
        for k in ("gateway_set", "gateway_get", "plain_set", "plain_get")
    )
    return results
