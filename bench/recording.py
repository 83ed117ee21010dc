"""Part (v): the gateway's CPU while the recorder writes 100 properties changing 100 times a second.

One gateway process (``psgateway serve``) serves :class:`ChangingSource` as ``source`` (100 number
properties, each given a new value :data:`RATE_HZ` times a second by its own ticker: 10,000
changes a second in all) and a recorder writing into a temporary folder. The gateway process's CPU
time (user + system, every thread; psutil) is measured over equal windows taking turns, in the same
run and the same process, and beside it the CPU time of the recorder's writer process (a child of
the gateway: the MCAP encoding, compression and file I/O):

* ``idle``: the source changing, nobody listening, nothing recorded;
* ``recording``: the recorder recording ``source/*`` (started by a Set of ``recorder start``,
  stopped before the next window);
* ``listen``: one gRPC Listen client of ``source/*`` instead, for scale (what a recording costs
  beside the cheapest other reader of the same changes).

The figure is ``recording / idle`` (target ≤ 1.10, docs/performance.md): the gateway process's
cores, the best window of each kind over the rounds; beside it ``recording / listen``, the writer
process's own cores while recording (``writer``, in the same windows), the events recorded and
how many were dropped.
"""

from __future__ import annotations

import asyncio
import json
import tempfile
import time
from pathlib import Path
from typing import Annotated, Any

import grpc

from bench.servers import ServerProcess
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.kernel.core import Prop, Resource

PROPERTIES = 100
RATE_HZ = 100.0
CALL_TIMEOUT = 15.0
#: Seconds after a recording starts (or a Listen opens) before its window: the first file and
#: chunk are made, the snapshot is written.
SETTLE_S = 1.0
TARGET = 1.10
NAMES = tuple(f"p{i:03d}" for i in range(PROPERTIES))


def _source_class() -> type[Resource]:
    """A Resource with :data:`PROPERTIES` read-only numbers (a class body cannot spell 100 of them)."""

    async def start(self: Any) -> None:
        self._ps_spawn(self._change(), "change the values")

    async def change(self: Any) -> None:
        period = 1.0 / RATE_HZ
        next_at = time.monotonic()
        tick = 0
        while True:
            tick += 1
            for name in NAMES:
                setattr(self, name, float(tick))
            next_at += period
            delay = next_at - time.monotonic()
            if delay < -1.0:  # fell a second behind: start again from now
                next_at = time.monotonic()
            await asyncio.sleep(max(0.0, delay))

    namespace: dict[str, Any] = {
        "__doc__": f"{PROPERTIES} numbers, each changed {RATE_HZ:g} times a second.",
        "__module__": __name__,
        "__annotations__": {
            name: Annotated[float, Prop(readonly=True, doc="a changing number")] for name in NAMES
        },
        "resource_type": "bench_source",
        "start": start,
        "_change": change,
        **dict.fromkeys(NAMES, 0.0),
    }
    return type("ChangingSource", (Resource,), namespace)


#: Served by the benchmark's gateway as ``type = "bench.recording:ChangingSource"``.
ChangingSource = _source_class()


def _config(folder: Path) -> str:
    return f"""
[[services]]
name = "source"
type = "bench.recording:ChangingSource"

[[services]]
name = "recorder"
type = "recorder"
options = {{ folder = "{folder}", max_total_bytes = {4 * 1024**3} }}
"""


async def _listen(address: str, opened: asyncio.Event) -> int:
    events = 0
    async with grpc.aio.insecure_channel(address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        call = stub.Listen(pb.ListenRequest(service="source", property="*"))
        async for response in call:
            opened.set()
            events += len(response.events)
    return events


async def run_recording(*, seconds: float, rounds: int, time_limit: float) -> dict[str, Any]:
    """CPU of the gateway idle, recording, and with one Listen, in turns; see the module docstring."""
    window = max(1.0, min(seconds, (time_limit - 5.0) / (3 * rounds) - SETTLE_S))
    cores: dict[str, list[float]] = {"idle": [], "recording": [], "listen": []}
    #: The writer process's cores in each recording window (the gateway's children).
    writer_cores: list[float] = []
    recorded: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="bench-recording-") as tmp:
        config = Path(tmp) / "recording.toml"
        config.write_text(_config(Path(tmp) / "recordings"))
        server = await ServerProcess.start(
            "gateway recording",
            ["gateway.cli", "serve", "--config", str(config), "--listen", "127.0.0.1:0"],
            address_on="stdout",
        )
        try:
            async with grpc.aio.insecure_channel(server.address) as channel:
                stub = pb_grpc.PropertyServiceStub(channel)

                async def measure(kind: str) -> None:
                    await asyncio.sleep(SETTLE_S)
                    server.check_alive()
                    children0 = _children_cpu(server.pid)
                    cpu0, t0 = server.cpu_seconds(), time.perf_counter()
                    await asyncio.sleep(window)
                    cpu1, t1 = server.cpu_seconds(), time.perf_counter()
                    children1 = _children_cpu(server.pid)
                    cores[kind].append((cpu1 - cpu0) / (t1 - t0))
                    if kind == "recording":
                        spent = sum(cpu - children0.get(pid, 0.0) for pid, cpu in children1.items())
                        writer_cores.append(spent / (t1 - t0))

                async def set_(prop: str, value: str, **params: str) -> str:
                    reply = await stub.Set(
                        pb.SetRequest(service="recorder", property=prop, value=value, parameters=params),
                        timeout=CALL_TIMEOUT,
                    )
                    return str(reply.value)

                for n in range(rounds):
                    await measure("idle")
                    name = await set_("start", "source/*", name=f"bench{n}")
                    await measure("recording")
                    await set_("stop", name)
                    reply = await stub.Get(
                        pb.GetRequest(service="recorder", property="recordings"), timeout=CALL_TIMEOUT
                    )
                    recorded.append(next(r for r in json.loads(reply.value) if r["name"] == name))
                    opened = asyncio.Event()
                    listening = asyncio.create_task(_listen(server.address, opened))
                    async with asyncio.timeout(CALL_TIMEOUT):
                        await opened.wait()
                    await measure("listen")
                    listening.cancel()
                    await asyncio.gather(listening, return_exceptions=True)
        finally:
            await server.stop()
    best = {kind: min(values) for kind, values in cores.items()}
    ratio = best["recording"] / best["idle"] if best["idle"] else None
    return {
        "properties": PROPERTIES,
        "rate_hz": RATE_HZ,
        "window_s": round(window, 2),
        "rounds": rounds,
        "cores": {kind: round(value, 3) for kind, value in best.items()},
        "writer_cores": round(min(writer_cores), 3) if writer_cores else None,
        "writer_cores_windows": [round(c, 3) for c in writer_cores],
        "cores_windows": {kind: [round(c, 3) for c in values] for kind, values in cores.items()},
        "ratio": round(ratio, 3) if ratio is not None else None,
        "target": TARGET,
        "recording_over_listen": round(best["recording"] / best["listen"], 3) if best["listen"] else None,
        "events_per_s": round(_mean([r["events"] / r["duration"] for r in recorded if r["duration"]]), 1),
        "dropped": sum(r["dropped"] for r in recorded),
        "conflated": sum(r["conflated"] for r in recorded),
        "mib_per_s": round(_mean([r["size"] / r["duration"] / 2**20 for r in recorded if r["duration"]]), 2),
        "states": sorted({r["state"] for r in recorded}),
    }


def _children_cpu(pid: int) -> dict[int, float]:
    """User plus system CPU seconds of each living child of ``pid`` (the recorder's writer process)."""
    import psutil  # only when measuring: `python -m bench --help` runs without the test extra

    spent = {}
    try:
        children = psutil.Process(pid).children(recursive=True)
    except psutil.Error:
        return {}
    for child in children:
        try:
            times = child.cpu_times()
        except psutil.Error:
            continue
        spent[child.pid] = float(times.user + times.system)
    return spent


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else 0.0
