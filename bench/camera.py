"""Part (o): camera frames — a 640x480 camera at 30 Hz to 10 gRPC Listeners through one gateway.

A gateway process serves one ``camera`` (three objects in view); ten gRPC
channels of this process each Listen on its ``frame`` (one HTTP/2 connection
each, as ten viewers would have). After a second of warm-up, for a fixed
window, each listener counts the frames it receives and their bytes, and the
gateway's CPU time (psutil ``cpu_times``, every thread: the render thread,
gRPC's and the loop's) is read at both ends of the window: its rise over the
window's length is the gateway's load in cores. The targets: each listener
gets at least 30 frames/s less the slack of the window's edges, and the
gateway stays under one core.

The baseline, in the same run and this process: the camera's own
render-and-encode of the same view, one frame after another, as fast as it
goes (what one core could render, with nothing sent anywhere).
"""

from __future__ import annotations

import asyncio
import io
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import grpc

from bench.servers import ServerProcess
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

SERVICE = "cam"
LISTENERS = 10
RATE_HZ = 30
WIDTH, HEIGHT = 640, 480
QUALITY = 75
WARMUP_S = 1.0
#: Frames per second a listener must get: the camera's 30, less what the window's edges can cut
#: (a frame due just outside it), i.e. one frame per second of a short window.
FPS_TARGET = 30.0
CORES_TARGET = 1.0
CALL_TIMEOUT = 30.0

OBJECTS: list[dict[str, Any]] = [
    {"id": "crate", "class": "box", "location": [3.0, 0.5], "colour": "red", "size": 0.6},
    {"id": "barrel", "class": "barrel", "location": [5.0, -1.0], "colour": "blue", "size": 0.8},
    {"id": "ball", "class": "ball", "location": [2.0, -0.6], "colour": "green", "size": 0.3},
]
OPTIONS: dict[str, Any] = {
    "location": [0.0, 0.0, 1.2],
    "resolution": [WIDTH, HEIGHT],
    "rate_hz": RATE_HZ,
    "quality": QUALITY,
}


def _toml(value: Any) -> str:
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + " }"
    return str(value)


def _config() -> str:
    return (
        '[gateway]\nlog_level = "warning"\n'
        f'[[services]]\nname = "{SERVICE}"\ntype = "camera"\n'
        "[services.options]\n"
        + "".join(f"{key} = {_toml(value)}\n" for key, value in OPTIONS.items())
        + f"objects = {_toml(OBJECTS)}\n"
    )


class _Counter:
    def __init__(self) -> None:
        self.counting = False
        self.frames = 0
        self.bytes = 0
        self.first: float | None = None
        self.last: float | None = None


async def _listen(address: str, counter: _Counter, ready: asyncio.Event, stop: asyncio.Event) -> None:
    async with grpc.aio.insecure_channel(address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        call = stub.Listen(pb.ListenRequest(service=SERVICE, property="frame"))
        try:
            async for message in call:
                if message.sync:
                    ready.set()
                for event in message.events:
                    if not event.HasField("data"):
                        raise RuntimeError(f"a frame event carried no bytes: {event}")
                    if counter.counting:
                        counter.frames += 1
                        counter.bytes += len(event.data)
                if stop.is_set():
                    break
        finally:
            call.cancel()


def _baseline(seconds: float) -> dict[str, Any]:
    """The camera's render and encode of the same view in this process, one frame after another."""
    from services.apps.vision.camera import Camera

    camera = Camera(**OPTIONS, objects=OBJECTS)
    frames = 0
    size = 0
    started = time.perf_counter()
    cpu0 = time.process_time()
    while time.perf_counter() - started < seconds:
        size = len(camera.render_once())
        frames += 1
    wall = time.perf_counter() - started
    cpu = time.process_time() - cpu0
    return {
        "frames": frames,
        "frames_per_s": round(frames / wall, 1),
        "ms_per_frame": round(cpu / frames * 1000, 2),
        "frame_bytes": size,
        "seen": len(camera.sightings()),
    }


async def run_camera(*, seconds: float, time_limit: float) -> dict[str, Any]:
    """Frames/s per listener, frame size and gateway CPU over a fixed window; the in-process baseline."""
    seconds = min(seconds, max(1.0, time_limit - WARMUP_S - 5.0))
    with tempfile.TemporaryDirectory(prefix="bench-camera-") as tmp:
        config = Path(tmp) / "camera.toml"
        config.write_text(_config())
        server = await ServerProcess.start(
            "gateway camera",
            ["gateway.cli", "serve", "--config", str(config), "--listen", "127.0.0.1:0"],
            address_on="stdout",
        )
        counters = [_Counter() for _ in range(LISTENERS)]
        readies = [asyncio.Event() for _ in range(LISTENERS)]
        stop = asyncio.Event()
        tasks = [
            asyncio.create_task(_listen(server.address, c, r, stop))
            for c, r in zip(counters, readies, strict=True)
        ]
        try:
            async with asyncio.timeout(CALL_TIMEOUT):
                await asyncio.gather(*(r.wait() for r in readies))
            await asyncio.sleep(WARMUP_S)
            server.check_alive()
            cpu0, t0 = server.cpu_seconds(), time.perf_counter()
            for c in counters:
                c.counting = True
            await asyncio.sleep(seconds)
            for c in counters:
                c.counting = False
            cpu1, t1 = server.cpu_seconds(), time.perf_counter()
            server.check_alive()
            async with grpc.aio.insecure_channel(server.address) as channel:
                reply = await pb_grpc.PropertyServiceStub(channel).Get(
                    pb.GetRequest(service=SERVICE, property="frame"), timeout=CALL_TIMEOUT
                )
            from PIL import Image

            decoded = Image.open(io.BytesIO(reply.data)).size
        finally:
            stop.set()
            for task in tasks:
                task.cancel()
            errors = [
                r for r in await asyncio.gather(*tasks, return_exceptions=True) if isinstance(r, Exception)
            ]
            await server.stop()
        failed = [e for e in errors if not isinstance(e, asyncio.CancelledError | grpc.aio.AioRpcError)]
        if failed:
            raise failed[0]
    window = t1 - t0
    fps = [c.frames / window for c in counters]
    frames = sum(c.frames for c in counters)
    return {
        "listeners": LISTENERS,
        "rate_hz": RATE_HZ,
        "resolution": [WIDTH, HEIGHT],
        "quality": QUALITY,
        "window_s": round(window, 2),
        "fps_min": round(min(fps), 2),
        "fps_mean": round(statistics.fmean(fps), 2),
        "frames": frames,
        "frame_bytes_mean": round(sum(c.bytes for c in counters) / frames) if frames else 0,
        "mib_per_s": round(sum(c.bytes for c in counters) / window / 2**20, 2),
        "gateway_cores": round((cpu1 - cpu0) / window, 3),
        "gateway_cpu_ms_per_frame": round((cpu1 - cpu0) / (frames / LISTENERS) * 1000, 2) if frames else None,
        "decoded": list(decoded),
        "baseline": _baseline(min(2.0, seconds)),
        "complete": frames > 0 and list(decoded) == [WIDTH, HEIGHT],
    }
