"""Part (e): Get through the gateway's TCP proxy beside a line-protocol client talking to the device.

Three processes: the device (``python -m services.device --service
sim-robot --tcp 127.0.0.1:0``), a gateway whose config names it as
``url = "tcp://127.0.0.1:PORT"``, and this one, the load generator. The same
Gets of the robot's ``speed`` are made two ways in the same run, taking turns:

* *direct*: one TCP connection to the device speaking the line protocol, each
  request tagged so that several are in flight (the codec of
  :mod:`services.kernel.line_protocol` on both ends);
* *gateway*: unary gRPC Gets of service ``dev`` on one channel; the gateway's
  proxy turns each into a tagged line on its one connection to the device;
* *gateway-session*: the same Gets over one Session stream of the gateway, batched as
  the client library does (:class:`clients.aio.Session`): the requests issued
  in the same event-loop iteration go in one SessionRequest;
* *session-floor*: the same Gets over a Session of the same gateway, of the same
  property of an in-process simulated robot (service ``local``): what a Session
  Get costs with no device behind it, the floor the proxied Session Get is
  judged against (it may cost at most this plus 2 × the direct round trip);
* *bare-session*: the same Gets over a Session of the bare server
  (:mod:`bench.baseline`, a fourth process), of a value in its dict: grpc.aio's
  own cost of a batch of Gets over a bidirectional stream, with no gateway and
  no device. With many in flight a batch of Gets through the proxy crosses
  this hop and the device's in turn (the client sends the next batch when the
  last one is answered), so ``f·d / (f + d)`` of their Gets/s is about the most
  the proxied path can reach (``line-inflight-ceiling``).

Each is measured with 1 and with ``inflight`` calls in flight.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import itertools
import tempfile
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc

from bench.measure import Latencies
from bench.servers import ServerProcess
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.kernel.line_protocol import ErrorReply, Get, Hello, LineReceiver, Ok, encode

#: The device's name in the gateway, and the property every call reads.
DEVICE = "dev"
PROPERTY = "speed"
#: The in-process service of the same type in the same gateway: the Session floor.
LOCAL = "local"
CALL_TIMEOUT = 10.0
GREETING_TIMEOUT = 10.0

#: The ways each Get is made, in the order they take turns.
WAYS = ("direct", "gateway", "gateway-session", "session-floor", "bare-session")
#: The value the bare server holds for the bare-session way (set before it is measured).
BARE_SERVICE, BARE_PROPERTY = "bench", "value"

DEVICE_ARGV = ["services.device", "--service", "sim-robot", "--name", DEVICE, "--tcp", "127.0.0.1:0"]


class SessionClient:
    """One Session stream carrying Gets, batched like the client library does.

    Requests issued in the same event-loop iteration are written as one
    SessionRequest; each reply resolves its request by id.
    """

    def __init__(self, stub: pb_grpc.PropertyServiceStub) -> None:
        self._call = stub.Session()
        self._ids = itertools.count(1)
        self._waiting: dict[int, asyncio.Future[pb.Reply]] = {}
        self._queue: list[pb.Request] = []
        self._wake = asyncio.Event()
        self._tasks = [asyncio.create_task(self._read()), asyncio.create_task(self._write())]

    async def _write(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            batch, self._queue = self._queue, []
            if batch:
                await self._call.write(pb.SessionRequest(requests=batch))

    async def _read(self) -> None:
        try:
            while True:
                response = await self._call.read()
                if response is grpc.aio.EOF:  # type: ignore[attr-defined]
                    break
                for reply in response.replies:
                    future = self._waiting.pop(reply.id, None)
                    if future is not None and not future.done():
                        future.set_result(reply)
        finally:
            for future in self._waiting.values():
                if not future.done():
                    future.set_exception(ConnectionError("the session ended"))
            self._waiting.clear()

    async def get(self, service: str, path: str) -> str:
        """GET ``service``/``path`` over the session."""
        rid = next(self._ids)
        future: asyncio.Future[pb.Reply] = asyncio.get_running_loop().create_future()
        self._waiting[rid] = future
        self._queue.append(pb.Request(id=rid, get=pb.GetRequest(service=service, property=path)))
        self._wake.set()
        try:
            async with asyncio.timeout(CALL_TIMEOUT):
                reply = await future
        finally:
            self._waiting.pop(rid, None)
        if reply.status.code:
            raise RuntimeError(f"status {reply.status.code} {reply.status.message}")
        return str(reply.get.value)

    async def aclose(self) -> None:
        """End the stream and its tasks."""
        self._call.cancel()
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)


class LineClient:
    """One line-protocol connection that pipelines tagged GETs (what a program on a PC would do)."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader = reader
        self.writer = writer
        self.greeting: Hello | None = None
        self._greeted = asyncio.Event()
        self._receiver = LineReceiver()
        self._waiting: dict[str, asyncio.Future[str]] = {}
        self._tags = itertools.count(1)
        self._pump = asyncio.create_task(self._read())

    @classmethod
    async def connect(cls, host: str, port: int) -> LineClient:
        """Connect and wait for the device's greeting."""
        reader, writer = await asyncio.open_connection(host, port, limit=65536)
        client = cls(reader, writer)
        try:
            async with asyncio.timeout(GREETING_TIMEOUT):
                await client._greeted.wait()
        except BaseException:
            await client.aclose()
            raise
        return client

    async def _read(self) -> None:
        try:
            while data := await self.reader.read(65536):
                for frame in self._receiver.receive_data(data):
                    if isinstance(frame, Hello) and frame.tag is None:
                        self.greeting = frame
                        self._greeted.set()
                    elif isinstance(frame, Ok | ErrorReply) and frame.tag is not None:
                        future = self._waiting.pop(frame.tag, None)
                        if future is None or future.done():
                            continue
                        if isinstance(frame, Ok):
                            future.set_result(frame.value)
                        else:
                            future.set_exception(RuntimeError(f"ERR {frame.code} {frame.message}"))
        finally:
            for future in self._waiting.values():
                if not future.done():
                    future.set_exception(ConnectionError("the device closed the connection"))
            self._waiting.clear()

    async def get(self, path: str) -> str:
        """GET ``path`` with a fresh tag; the reply may overtake or be overtaken by others."""
        tag = format(next(self._tags), "x")
        future: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        self._waiting[tag] = future
        self.writer.write(encode(Get(path, tag=tag)))
        try:
            async with asyncio.timeout(CALL_TIMEOUT):
                return await future
        finally:
            self._waiting.pop(tag, None)

    async def aclose(self) -> None:
        """Close the connection and stop reading."""
        self.writer.close()
        with contextlib.suppress(Exception):
            await self.writer.wait_closed()
        self._pump.cancel()
        await asyncio.gather(self._pump, return_exceptions=True)


@dataclass
class PathResult:
    """One way (direct or through the gateway) at one number of calls in flight."""

    inflight: int
    calls: int
    done: int = 0
    errors: int = 0
    complete: bool = True
    wall_s: float = 0.0
    client_cpu_s: float = 0.0
    device_cpu_s: float = 0.0
    gateway_cpu_s: float = 0.0
    latency: Latencies = field(default_factory=Latencies)

    @property
    def throughput(self) -> float:
        return (self.done - self.errors) / self.wall_s if self.wall_s else 0.0

    def as_dict(self) -> dict[str, Any]:
        calls = max(self.done, 1)
        return {
            "inflight": self.inflight,
            "calls": self.calls,
            "done": self.done,
            "errors": self.errors,
            "complete": self.complete,
            "throughput_per_s": round(self.throughput, 1),
            "latency": self.latency.as_dict(),
            "wall_s": round(self.wall_s, 4),
            "client_busy": round(self.client_cpu_s / self.wall_s, 3) if self.wall_s else 0.0,
            "device_cpu_us_per_call": round(1e6 * self.device_cpu_s / calls, 1),
            "gateway_cpu_us_per_call": round(1e6 * self.gateway_cpu_s / calls, 1),
        }


async def drive(
    call: Callable[[], Awaitable[Any]], calls: int, inflight: int, time_limit: float
) -> PathResult:
    """Make ``calls`` calls, ``inflight`` at a time, for at most ``time_limit`` seconds."""
    result = PathResult(inflight=inflight, calls=calls)
    deadline = time.monotonic() + time_limit
    remaining = calls
    samples: list[int] = []

    async def worker() -> None:
        nonlocal remaining
        while remaining > 0 and time.monotonic() < deadline:
            remaining -= 1
            start = time.perf_counter_ns()
            try:
                await call()
            except (grpc.aio.AioRpcError, RuntimeError, ConnectionError, TimeoutError):
                result.errors += 1
                continue
            samples.append(time.perf_counter_ns() - start)

    cpu = time.process_time()
    start = time.perf_counter()
    await asyncio.gather(*(worker() for _ in range(inflight)))
    result.wall_s = time.perf_counter() - start
    result.client_cpu_s = time.process_time() - cpu
    result.done = len(samples) + result.errors
    result.complete = remaining == 0
    result.latency = Latencies.of(samples)
    return result


def gateway_config(device_address: str) -> str:
    """A gateway config that serves the device at ``device_address`` as service ``dev``,
    and the same simulated robot in-process as service ``local``."""
    return (
        '[gateway]\nlisten = "127.0.0.1:0"\nlog_level = "warning"\n\n'
        f'[[services]]\nname = "{DEVICE}"\nurl = "tcp://{device_address}"\n\n'
        f'[[services]]\nname = "{LOCAL}"\ntype = "sim-robot"\n'
    )


async def _measured(
    call: Callable[[], Awaitable[Any]],
    *,
    calls: int,
    inflight: int,
    time_limit: float,
    device: ServerProcess,
    gateway: ServerProcess,
) -> PathResult:
    device_cpu, gateway_cpu = device.cpu_seconds(), gateway.cpu_seconds()
    result = await drive(call, calls, inflight, time_limit)
    result.device_cpu_s = device.cpu_seconds() - device_cpu
    result.gateway_cpu_s = gateway.cpu_seconds() - gateway_cpu
    return result


async def run_line(
    *, calls: int, inflights: tuple[int, ...], warmup: int, rounds: int, time_limit: float
) -> dict[str, dict[str, Any]]:
    """Start the device and the gateway, then measure each of :data:`WAYS`; return ``{way: figures}``.

    Each way's figures are kept per number in flight (``"1"``, ``"8"``); with
    several rounds the ways take turns and the best round (by Gets/s) counts.
    """
    best: dict[str, dict[int, PathResult]] = {name: {} for name in WAYS}
    rounds_seen: dict[str, dict[int, list[float]]] = {name: {} for name in WAYS}
    device = await ServerProcess.start("device", DEVICE_ARGV, address_on="stdout")
    gateway: ServerProcess | None = None
    bare: ServerProcess | None = None
    try:
        bare = await ServerProcess.start("bare", ["bench.baseline", "--listen", "127.0.0.1:0"])
        with tempfile.TemporaryDirectory(prefix="bench-line-") as folder:
            config = Path(folder) / "gateway.toml"
            config.write_text(gateway_config(device.address))
            gateway = await ServerProcess.start(
                "gateway", ["gateway", "serve", "--config", str(config), "--log-level", "warning"]
            )
        host, _, port = device.address.rpartition(":")
        direct = await LineClient.connect(host, int(port))
        channel = grpc.aio.insecure_channel(gateway.address)
        session_channel = grpc.aio.insecure_channel(gateway.address)
        bare_channel = grpc.aio.insecure_channel(bare.address)
        session: SessionClient | None = None
        bare_session: SessionClient | None = None
        try:
            stub = pb_grpc.PropertyServiceStub(channel)
            request = pb.GetRequest(service=DEVICE, property=PROPERTY)

            async def through_gateway() -> Any:
                return await stub.Get(request, timeout=CALL_TIMEOUT)

            async def straight() -> str:
                return await direct.get(PROPERTY)

            session = SessionClient(pb_grpc.PropertyServiceStub(session_channel))
            over_session = functools.partial(session.get, DEVICE, PROPERTY)
            bare_stub = pb_grpc.PropertyServiceStub(bare_channel)
            await bare_stub.Set(
                pb.SetRequest(service=BARE_SERVICE, property=BARE_PROPERTY, value="0.0"), timeout=CALL_TIMEOUT
            )
            bare_session = SessionClient(bare_stub)
            ways: dict[str, Callable[[], Awaitable[Any]]] = {
                "direct": straight,
                "gateway": through_gateway,
                "gateway-session": over_session,
                "session-floor": functools.partial(session.get, LOCAL, PROPERTY),
                "bare-session": functools.partial(bare_session.get, BARE_SERVICE, BARE_PROPERTY),
            }
            for way in ways.values():  # the proxy may still be connecting: the warm-up waits for it
                await _wait_answering(way)
                await drive(way, warmup, max(inflights), time_limit)
            for _ in range(rounds):
                for inflight in inflights:
                    for name, way in ways.items():
                        got = await _measured(
                            way,
                            calls=calls,
                            inflight=inflight,
                            time_limit=time_limit,
                            device=device,
                            # The bare way's server CPU is the bare server's.
                            gateway=bare if name == "bare-session" else gateway,
                        )
                        rounds_seen[name].setdefault(inflight, []).append(round(got.throughput, 1))
                        kept = best[name].get(inflight)
                        if kept is None or got.throughput > kept.throughput:
                            best[name][inflight] = got
            device.check_alive()
            gateway.check_alive()
            bare.check_alive()
        finally:
            if session is not None:
                await session.aclose()
            if bare_session is not None:
                await bare_session.aclose()
            await bare_channel.close(None)
            await session_channel.close(None)
            await channel.close(None)
            await direct.aclose()
    finally:
        if gateway is not None:
            await gateway.stop()
        if bare is not None:
            await bare.stop()
        await device.stop()
    return {
        name: {
            "property": f"{DEVICE}/{PROPERTY}",
            "rounds": rounds,
            "inflight": {
                str(n): {**result.as_dict(), "rounds": rounds_seen[name][n]}
                for n, result in sorted(ways.items())
            },
        }
        for name, ways in best.items()
    }


async def _wait_answering(call: Callable[[], Awaitable[Any]]) -> None:
    deadline = time.monotonic() + GREETING_TIMEOUT
    while True:
        try:
            await call()
            return
        except (grpc.aio.AioRpcError, RuntimeError, ConnectionError, TimeoutError):
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.05)
