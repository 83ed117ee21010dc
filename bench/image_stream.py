"""The live image route: frames/s to N browsers through the HTTP front end, and the gateway's CPU.

``python -m bench.image_stream [--readers 10] [--rate 30] [--frame-bytes 50000] [--seconds 10]``

One gateway process serves :class:`FrameBench` (a binary property ``frame``, ``image/jpeg``, a new
value of ``frame_bytes`` bytes ``rate_hz`` times a second: the size of a 640×480 JPEG at quality
75) and its HTTP front end. ``readers`` clients each open
``GET /api/v1/services/bench/properties/frame/stream`` (``multipart/x-mixed-replace``) and read
every part, as that many browser tabs showing the camera would. Over the measured window: the
frames each reader got per second, the frames the service made, the parts that were skipped for a
reader (``X-Conflated``), and the gateway's CPU as a fraction of one core. Frames are rendered
only while someone listens; the bytes are not a real JPEG (the route does not look at them).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import tempfile
import time
from pathlib import Path
from typing import Annotated, Any

import aiohttp

from bench.measure import window
from bench.servers import ServerError, ServerProcess
from services.kernel.core import Prop, Resource

_HTTP = re.compile(r"HTTP front end and console on (https?://\S+/)")
CONFIG = """
[[services]]
name = "bench"
type = "bench.image_stream:FrameBench"
options = {{ rate_hz = {rate}, frame_bytes = {frame_bytes} }}

[http]
max_streams_per_client = {readers}
"""


class FrameBench(Resource):
    """A camera stand-in: ``frame`` renewed ``rate_hz`` times a second (a counter, then filler)."""

    resource_type = "camera"
    frame: Annotated[bytes, Prop(readonly=True, media_type="image/jpeg")] = b""

    def __init__(self, rate_hz: float = 30.0, frame_bytes: int = 50_000) -> None:
        self._rate_hz = rate_hz
        self._filler = os.urandom(max(frame_bytes - 8, 0))
        self._made = 0
        self._task: asyncio.Task[None] | None = None

    @property
    def made(self) -> int:
        """Frames made so far."""
        return self._made

    async def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name="bench frames")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)

    async def _run(self) -> None:
        period = 1.0 / self._rate_hz
        next_at = time.perf_counter()
        while True:
            next_at += period
            await asyncio.sleep(max(0.0, next_at - time.perf_counter()))
            self._made += 1
            self.frame = self._made.to_bytes(8, "big") + self._filler


class _Reader:
    """One stream's parts, counted by their Content-Length (the body is not kept)."""

    def __init__(self) -> None:
        self.parts = 0
        self.conflated = 0
        self.counting = False

    async def read(self, response: aiohttp.ClientResponse) -> None:
        content = response.content
        while True:
            line = await content.readline()
            if not line:
                return
            if not line.startswith(b"--psframe"):
                continue
            if line.startswith(b"--psframe--"):
                return
            length = 0
            conflated = 0
            while (header := await content.readline()) not in (b"\r\n", b""):
                name, _, value = header.decode("latin-1").partition(":")
                if name.lower() == "content-length":
                    length = int(value)
                elif name.lower() == "x-conflated":
                    conflated = int(value)
            await content.readexactly(length + 2)
            if self.counting:
                self.parts += 1
                self.conflated += conflated


async def run(readers: int, rate: float, frame_bytes: int, seconds: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as folder:
        config = Path(folder) / "bench.toml"
        config.write_text(CONFIG.format(rate=rate, frame_bytes=frame_bytes, readers=readers))
        argv = [
            "gateway.cli",
            "serve",
            "--config",
            str(config),
            "--listen",
            "127.0.0.1:0",
            "--http",
            "127.0.0.1:0",
        ]
        server = await ServerProcess.start("gateway", argv)
        try:
            match = _HTTP.search(server.log_tail)
            if match is None:
                raise ServerError(f"no HTTP front end address:\n{server.log_tail}")
            url = match.group(1) + "api/v1/services/bench/properties/frame/stream"
            timeout = aiohttp.ClientTimeout(total=None, sock_read=30)
            async with aiohttp.ClientSession(timeout=timeout) as session:
                responses = [await session.get(url) for _ in range(readers)]
                for response in responses:
                    if response.status != 200:
                        raise ServerError(f"stream refused: {response.status} {await response.text()}")
                counted = [_Reader() for _ in responses]
                tasks = [
                    asyncio.create_task(r.read(resp)) for r, resp in zip(counted, responses, strict=True)
                ]
                await asyncio.sleep(1.0)  # warm up: every stream has its first frames
                made = await _made(session, match.group(1))
                for reader in counted:
                    reader.counting = True
                with window(server) as measured:
                    await asyncio.sleep(seconds)
                for reader in counted:
                    reader.counting = False
                made = await _made(session, match.group(1)) - made
                for task in tasks:
                    task.cancel()
                await asyncio.gather(*tasks, return_exceptions=True)
                for response in responses:
                    response.close()
        finally:
            await server.stop()
    per_reader = [r.parts / measured.wall_s for r in counted]
    return {
        "readers": readers,
        "rate_hz": rate,
        "frame_bytes": frame_bytes,
        "made_per_s": round(made / measured.wall_s, 1),
        "frames_per_s_per_reader": {
            "min": round(min(per_reader), 1),
            "mean": round(sum(per_reader) / len(per_reader), 1),
        },
        "conflated": sum(r.conflated for r in counted),
        "gateway_cpu_of_one_core": round(measured.server_busy, 3),
        "client_cpu_of_one_core": round(measured.client_busy, 3),
        "mbytes_per_s": round(sum(r.parts for r in counted) * frame_bytes / measured.wall_s / 1e6, 1),
    }


async def _made(session: aiohttp.ClientSession, base: str) -> int:
    async with session.get(base + "api/v1/services/bench/properties/made") as response:
        return int((await response.json())["value"])


def main() -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.image_stream", description=__doc__.split("\n")[0])
    parser.add_argument("--readers", type=int, default=10)
    parser.add_argument("--rate", type=float, default=30.0, help="frames/s the service makes")
    parser.add_argument("--frame-bytes", type=int, default=50_000)
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    print(json.dumps(asyncio.run(run(args.readers, args.rate, args.frame_bytes, args.seconds)), indent=2))


if __name__ == "__main__":
    main()
