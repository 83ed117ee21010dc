"""Instructions a server executes per unary Get or per Listen event, counted by callgrind.

Run ``python -m bench.instructions`` (``--rounds N``, ``--servers bare,gateway,floor``,
``--parts unary,fanout``). Each server runs under ``valgrind --tool=callgrind`` (about fifty
times slower, so the counts come from a few hundred calls); the load comes from this process
with the same client code as ``python -m bench``. Around each measured batch the counters are
zeroed and dumped (``callgrind_control``), so start-up, warm-up and the parts measured before on
the same server are not counted: each server starts once and serves every part asked of it, one
after the other (``proxied`` on a start of its own, with the device in its config). The figure
is the instructions of all the server's threads divided by the calls or events, and of its main
thread (the event loop: Python, grpc.aio's Cython and the calls into grpc core made from it).

Unlike CPU time, an instruction count does not move with the load of a shared machine: it
settles differences of a few per cent that wall-clock figures there cannot (they swing by
±30 % between runs). It counts neither the kernel's work (system calls; ``strace -c`` shows
they are the same per call on each server) nor cache misses.

* ``unary``: unary Gets of ``bench/value``, one in flight (the count then depends least on
  timing).
* ``fanout``: 100 Listen streams of ``bench/value`` over four connections, one-by-one unary
  Sets; per event delivered. ``floor`` is :mod:`bench.fanout`'s server.
* ``session-fanout``: the same with each Listen a request inside a Session of its own (the
  gateway only: neither the bare server nor the floor has Listens in Sessions).
* ``session``: Gets of ``bench/value`` over one Session stream, one request a message, one
  at a time; ``echo``: the same messages over the bare server's echo (grpc.aio's floor for a
  Get over a bidirectional stream, ``bench.baseline.ECHO_METHOD``; ``--servers bare``).
* ``batched-fanout``: 100 Listen streams of the ten ``bench/v0`` .. ``bench/v9`` each, and bursts
  of ten Sets (one to each) in one Session message, as the batched mode of part (c); per event
  delivered (the gateway and the floor send a burst's ten events in one message, the bare server
  one message each).
* ``proxied``: unary Gets of ``speed`` of a device behind the gateway's TCP line proxy, one in
  flight (the gateway only). The device is :data:`bench.line.DEVICE_ARGV`, the Python line-protocol
  device server of part (e) of ``python -m bench``, in a process of its own on loopback and not
  under valgrind: only the gateway's instructions are counted (the gRPC call in, the line out to
  the device, its reply read back). The proxy's keep-alive is off, so that no PING falls into a
  measured batch.

Needs valgrind (``apt-get install valgrind``); without it the command says so and exits 2.
"""

from __future__ import annotations

import argparse
import asyncio
import glob
import os
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import grpc

from bench.baseline import ECHO_METHOD
from bench.line import DEVICE, DEVICE_ARGV
from bench.line import PROPERTY as DEVICE_PROPERTY
from bench.listen import CHANNEL_OPTIONS
from bench.measure import STREAM_END
from bench.servers import ROOT, ServerProcess
from bench.target import BATCH_PROPERTIES, SERVICE, VALUE_PROPERTY
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

SERVERS = {
    "bare": ["bench.baseline"],
    "gateway": ["bench.gateway_server"],
    "floor": ["bench.fanout", "--serve"],
}
#: What each server can be measured on: the floor serves only a fan-out, and only the gateway
#: has Listens inside Sessions and a line proxy.
SERVES = {
    "bare": ("unary", "fanout", "batched-fanout", "session", "echo"),
    "gateway": ("unary", "fanout", "session-fanout", "batched-fanout", "session", "proxied"),
    "floor": ("fanout", "batched-fanout"),
}
#: Seconds a server under valgrind may take to print its address (it starts about fifty times slower;
#: on a 2-core machine running other work beside it, the gateway has taken over 180 s).
START_TIMEOUT = 600.0
#: Seconds one call may take under valgrind.
CALL_TIMEOUT = 120.0
#: Calls a round of ``unary`` measures, Sets a round of ``fanout`` makes (to 100 streams); and with
#: ``--quick``.
UNARY_CALLS = 400
FANOUT_SETS = 40
QUICK_CALLS = 50
QUICK_SETS = 5
SUBSCRIBERS = 100
#: Seconds the server is left alone between two parts it serves.
SETTLE = 2.0
#: Unary parts: one Get per call, counted per Get.
UNARY_PARTS = frozenset({"unary", "session", "echo", "proxied"})


def _summary(dump: str) -> int:
    """The instruction count a callgrind dump file holds."""
    for line in Path(dump).read_text(errors="replace").splitlines():
        if line.startswith(("summary:", "totals:")):
            return int(line.split()[1])
    return 0


class Counted:
    """A server under callgrind: zero its counters, dump them, read what the dump holds."""

    def __init__(self, process: asyncio.subprocess.Process, folder: Path, address: str) -> None:
        self.process = process
        self.folder = folder
        self.address = address
        self._seen: set[str] = set()
        self._drain: asyncio.Task[None] | None = None

    @classmethod
    async def start(cls, argv: list[str], folder: Path) -> Counted:
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH", "")]))
        process = await asyncio.create_subprocess_exec(
            "valgrind",
            "--tool=callgrind",
            "--separate-threads=yes",
            f"--callgrind-out-file={folder}/callgrind.out.%p",
            sys.executable,
            "-m",
            *argv,
            "--listen",
            "127.0.0.1:0",
            cwd=ROOT,
            env=env,
            stdin=asyncio.subprocess.PIPE,  # held open: the servers stop at end of file on stdin
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.PIPE,
        )
        assert process.stderr is not None
        seen: list[str] = []
        try:
            async with asyncio.timeout(START_TIMEOUT):
                while raw := await process.stderr.readline():
                    line = raw.decode(errors="replace").strip()
                    seen.append(line)
                    if line.startswith("listening on "):
                        server = cls(process, folder, line.split()[-1])
                        server._drain = asyncio.create_task(_drain(process.stderr))
                        return server
        except TimeoutError:
            pass
        process.kill()
        await process.wait()
        raise RuntimeError(f"{argv[0]} did not start under valgrind:\n" + "\n".join(seen[-30:]))

    async def _control(self, option: str) -> None:
        control = await asyncio.create_subprocess_exec(
            "callgrind_control",
            option,
            str(self.process.pid),
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.DEVNULL,
        )
        if await control.wait():
            raise RuntimeError(f"callgrind_control {option} {self.process.pid} failed")

    async def zero(self) -> None:
        await self._control("-z")
        self._seen = set(glob.glob(f"{self.folder}/callgrind.out.*"))

    async def dumped(self) -> tuple[int, int]:
        """Dump the counters; (all threads, main thread) since :meth:`zero`."""
        await self._control("-d")
        await asyncio.sleep(0.5)
        total = main = 0
        for name in set(glob.glob(f"{self.folder}/callgrind.out.*")) - self._seen:
            count = _summary(name)
            total += count
            main += count if name.endswith("-01") else 0  # thread 1: the event loop's
        return total, main

    async def stop(self) -> None:
        if self.process.stdin is not None:
            self.process.stdin.close()
        try:
            async with asyncio.timeout(30):
                await self.process.wait()
        except TimeoutError:
            self.process.kill()
            await self.process.wait()
        if self._drain is not None:
            self._drain.cancel()


async def _drain(stream: asyncio.StreamReader) -> None:
    # Keep reading: a server whose stderr pipe fills up would block.
    while await stream.readline():
        pass


async def unary_round(server: Counted, channel: grpc.aio.Channel, calls: int) -> tuple[float, float]:
    """Instructions per unary Get (all threads, main thread), ``calls`` Gets one at a time."""
    return await _gets(server, channel, pb.GetRequest(service=SERVICE, property=VALUE_PROPERTY), calls)


async def proxied_round(server: Counted, channel: grpc.aio.Channel, calls: int) -> tuple[float, float]:
    """The same of a device's property, through the gateway's TCP line proxy."""
    return await _gets(server, channel, pb.GetRequest(service=DEVICE, property=DEVICE_PROPERTY), calls)


async def _gets(
    server: Counted, channel: grpc.aio.Channel, request: pb.GetRequest, calls: int
) -> tuple[float, float]:
    stub = pb_grpc.PropertyServiceStub(channel)
    await server.zero()
    for _ in range(calls):
        await stub.Get(request, timeout=CALL_TIMEOUT)
    total, main = await server.dumped()
    return total / calls, main / calls


async def _stream_round(server: Counted, call: Any, calls: int) -> tuple[float, float]:
    """Instructions per Get over an open bidirectional stream, one Get a message, one at a time."""
    for number in range(1, 21):  # warm up: the first messages import and cache
        await call.write(_session_get(number))
        await call.read()
    await server.zero()
    for number in range(21, 21 + calls):
        await call.write(_session_get(number))
        await call.read()
    total, main = await server.dumped()
    await call.done_writing()
    return total / calls, main / calls


def _session_get(number: int) -> pb.SessionRequest:
    message = pb.SessionRequest()
    message.requests.add(id=number, get=pb.GetRequest(service=SERVICE, property=VALUE_PROPERTY))
    return message


async def session_round(server: Counted, channel: grpc.aio.Channel, calls: int) -> tuple[float, float]:
    """Instructions per Get over a Session, one request a message, one at a time."""
    return await _stream_round(server, pb_grpc.PropertyServiceStub(channel).Session(), calls)


async def echo_round(server: Counted, channel: grpc.aio.Channel, calls: int) -> tuple[float, float]:
    """The same over the bare server's echo (``bench.baseline.ECHO_METHOD``): grpc.aio's floor."""
    echo = channel.stream_stream(
        ECHO_METHOD,
        request_serializer=pb.SessionRequest.SerializeToString,
        response_deserializer=pb.SessionResponse.FromString,
    )
    return await _stream_round(server, echo(), calls)


async def fanout_round(
    server: Counted,
    channel: grpc.aio.Channel,
    sets: int,
    *,
    in_sessions: bool = False,
    properties: tuple[str, ...] = (VALUE_PROPERTY,),
) -> tuple[float, float]:
    """Instructions per event delivered to 100 Listens (all threads, main thread), ``sets`` Sets;
    each Listen a stream of its own, or with ``in_sessions`` a request inside a Session of its own.

    With several ``properties`` each Listen follows them all, and each of the ``sets`` is a burst:
    one Session message with a Set to each property (``sets * len(properties)`` Sets in all)."""
    setter = pb_grpc.PropertyServiceStub(channel)
    streams = [grpc.aio.insecure_channel(server.address, options=CHANNEL_OPTIONS) for _ in range(4)]
    more = [pb.PropertyRef(service=SERVICE, property=prop) for prop in properties[1:]]
    request = pb.ListenRequest(service=SERVICE, property=properties[0], more=more)
    stubs = [pb_grpc.PropertyServiceStub(streams[n % 4]) for n in range(SUBSCRIBERS)]
    calls: list[Any] = []
    events = [0]
    expected = sets * len(properties) * SUBSCRIBERS
    delivered = asyncio.Event()

    def count(response: pb.ListenResponse) -> bool:
        events[0] += len(response.events)
        if events[0] >= expected:
            delivered.set()
        return response.sync

    async def read(call: Any, synced: asyncio.Event) -> None:
        while (response := await call.read()) is not STREAM_END:
            replies = [reply.listen for reply in response.replies] if in_sessions else [response]
            if any([count(listened) for listened in replies]):
                synced.set()

    syncs = [asyncio.Event() for _ in stubs]
    tasks: list[asyncio.Task[None]] = []
    bursts = setter.Session() if len(properties) > 1 else None
    try:
        for stub in stubs:
            if in_sessions:
                call = stub.Session()
                await call.write(pb.SessionRequest(requests=[pb.Request(id=1, listen=request)]))
            else:
                call = stub.Listen(request)
            calls.append(call)
        tasks = [asyncio.create_task(read(call, synced)) for call, synced in zip(calls, syncs, strict=True)]
        async with asyncio.timeout(CALL_TIMEOUT):
            await asyncio.gather(*(synced.wait() for synced in syncs))
        events[0] = 0
        await server.zero()
        for n in range(sets):
            value = f"{time.monotonic_ns()}{n}"
            if bursts is None:
                await setter.Set(
                    pb.SetRequest(service=SERVICE, property=properties[0], value=value), timeout=CALL_TIMEOUT
                )
            else:
                await _burst(bursts, properties, value)
        async with asyncio.timeout(CALL_TIMEOUT):
            await delivered.wait()
        total, main = await server.dumped()
    finally:
        if bursts is not None:
            bursts.cancel()
        for task in tasks:
            task.cancel()
        for call in calls:
            call.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for stream in streams:
            await stream.close(None)
    return total / events[0], main / events[0]


async def _burst(session: Any, properties: tuple[str, ...], value: str) -> None:
    """One Session message with a Set of ``value`` to each of ``properties``; wait for every reply."""
    message = pb.SessionRequest()
    for number, prop in enumerate(properties, start=1):
        message.requests.add(id=number, set=pb.SetRequest(service=SERVICE, property=prop, value=value))
    async with asyncio.timeout(CALL_TIMEOUT):
        await session.write(message)
        replies = 0
        while replies < len(properties):
            response = await session.read()
            if response is STREAM_END:
                raise RuntimeError(f"the setter's Session ended: {await session.code()}")
            replies += len(response.replies)


async def batched_fanout_round(server: Counted, channel: grpc.aio.Channel, sets: int) -> tuple[float, float]:
    """:func:`fanout_round` with each Listen following the ten batch properties, ``sets`` bursts."""
    return await fanout_round(server, channel, sets, properties=BATCH_PROPERTIES)


async def session_fanout_round(server: Counted, channel: grpc.aio.Channel, sets: int) -> tuple[float, float]:
    """:func:`fanout_round` with each Listen inside a Session of its own."""
    return await fanout_round(server, channel, sets, in_sessions=True)


PARTS: dict[str, Callable[[Counted, grpc.aio.Channel, int], Awaitable[tuple[float, float]]]] = {
    "unary": unary_round,
    "fanout": fanout_round,
    "session-fanout": session_fanout_round,
    "session": session_round,
    "echo": echo_round,
    "batched-fanout": batched_fanout_round,
    "proxied": proxied_round,
}


def _device_config(device_address: str) -> str:
    """A gateway config serving the device at ``device_address`` as service :data:`DEVICE`.

    No keep-alive PING: one falling into a measured batch would be counted; and a call timeout
    that a gateway under valgrind cannot reach."""
    return (
        f'[[services]]\nname = "{DEVICE}"\nurl = "tcp://{device_address}"\n'
        f"options = {{ keepalive = 0, timeout = {CALL_TIMEOUT} }}\n"
    )


async def _answering(stub: pb_grpc.PropertyServiceStub, request: pb.GetRequest) -> None:
    """Wait until the gateway answers ``request``: its proxy connects to the device after it starts."""
    async with asyncio.timeout(START_TIMEOUT):
        while True:
            try:
                await stub.Get(request, timeout=CALL_TIMEOUT)
                return
            except grpc.aio.AioRpcError as error:
                if error.code() != grpc.StatusCode.UNAVAILABLE:
                    raise
            await asyncio.sleep(0.5)


def _size(part: str, quick: bool) -> int:
    """Calls (unary parts) or Sets (fan-out parts) one round of ``part`` makes."""
    if part in UNARY_PARTS:
        return QUICK_CALLS if quick else UNARY_CALLS
    return QUICK_SETS if quick else FANOUT_SETS


async def measure(
    parts: list[str], kind: str, rounds: int, quick: bool
) -> dict[str, list[tuple[float, float]]]:
    """``rounds`` counts of each of ``parts`` on one ``kind`` of server under callgrind, by part.

    One server process serves every part, one after the other (a server under valgrind takes tens
    of seconds to start); the counters are zeroed and dumped around each measured batch, so what a
    part before it did is not counted. ``proxied`` alone gets a server of its own, configured with
    the device: every other part is measured on the server as it runs without one."""
    counts: dict[str, list[tuple[float, float]]] = {}
    plain = [part for part in parts if part != "proxied"]
    if plain:
        counts.update(await _measure_on_one_server(plain, kind, rounds, quick, device=False))
    if "proxied" in parts:
        counts.update(await _measure_on_one_server(["proxied"], kind, rounds, quick, device=True))
    return {part: counts[part] for part in parts}


async def _measure_on_one_server(
    parts: list[str], kind: str, rounds: int, quick: bool, *, device: bool
) -> dict[str, list[tuple[float, float]]]:
    """:func:`measure` on one server process; with ``device``, the gateway serves a line device."""
    proxy: ServerProcess | None = None
    with tempfile.TemporaryDirectory(prefix="callgrind-") as folder:
        argv = SERVERS[kind]
        if device:
            proxy = await ServerProcess.start(
                "device", [*DEVICE_ARGV, "--exit-with-parent"], address_on="stdout"
            )
            config = Path(folder) / "gateway.toml"
            config.write_text(_device_config(proxy.address))
            argv = [*argv, "--config", str(config)]
        try:
            server = await Counted.start(argv, Path(folder))
        except BaseException:
            if proxy is not None:
                await proxy.stop()
            raise
        try:
            async with grpc.aio.insecure_channel(server.address) as channel:
                stub = pb_grpc.PropertyServiceStub(channel)
                for prop in (VALUE_PROPERTY, *BATCH_PROPERTIES):  # the bare server makes them on a Set
                    first = pb.SetRequest(service=SERVICE, property=prop, value="0")
                    await stub.Set(first, timeout=CALL_TIMEOUT)
                counts: dict[str, list[tuple[float, float]]] = {}
                for number, part in enumerate(parts):
                    if number:
                        # Let the server finish tearing down the part before (its streams are
                        # cancelled as it ends), so that none of it falls into this part's batch.
                        await asyncio.sleep(SETTLE)
                    get = pb.GetRequest(service=SERVICE, property=VALUE_PROPERTY)
                    if part == "proxied":
                        get = pb.GetRequest(service=DEVICE, property=DEVICE_PROPERTY)
                        await _answering(stub, get)
                    # Warm up: the first calls import and cache.
                    for _ in range(20 if part in {"unary", "proxied"} else 0):
                        await stub.Get(get, timeout=CALL_TIMEOUT)
                    counts[part] = [
                        await PARTS[part](server, channel, _size(part, quick)) for _ in range(rounds)
                    ]
                return counts
        finally:
            await server.stop()
            if proxy is not None:
                await proxy.stop()


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m bench.instructions``."""
    parser = argparse.ArgumentParser(prog="python -m bench.instructions", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--parts",
        default="unary,fanout",
        help="unary, fanout, session-fanout, batched-fanout, session, echo, proxied (default unary,fanout)",
    )
    parser.add_argument(
        "--servers", default="bare,gateway", help="bare, gateway, floor (default bare,gateway)"
    )
    parser.add_argument("--rounds", type=int, default=3, help="measured rounds per server (default 3)")
    parser.add_argument(
        "--quick", action="store_true", help=f"{QUICK_CALLS} Gets and {QUICK_SETS} Sets a round (a smoke run)"
    )
    args = parser.parse_args(argv)
    missing = [tool for tool in ("valgrind", "callgrind_control") if shutil.which(tool) is None]
    if missing:
        print(f"needs {' and '.join(missing)} (apt-get install valgrind)", file=sys.stderr)
        return 2
    parts = [p for p in args.parts.split(",") if p]
    kinds = [k for k in args.servers.split(",") if k]
    unknown = [p for p in parts if p not in PARTS] + [k for k in kinds if k not in SERVERS]
    if unknown:
        parser.error(f"unknown part or server: {', '.join(unknown)}")
    per = {
        "unary": "Get",
        "fanout": "event",
        "session-fanout": "event",
        "batched-fanout": "event",
        "session": "Get",
        "echo": "Get",
        "proxied": "Get",
    }
    # Each server starts once and serves all its parts; the figures are then shown part by part.
    counts = {
        kind: asyncio.run(measure([p for p in parts if p in SERVES[kind]], kind, args.rounds, args.quick))
        for kind in kinds
        if any(p in SERVES[kind] for p in parts)
    }
    for part in parts:
        medians: dict[str, float] = {}
        for kind in kinds:
            if part not in SERVES[kind]:
                print(f"{part:6} {kind:8} (not measured: it serves {', '.join(SERVES[kind])} only)")
                continue
            medians[kind] = statistics.median(total for total, _ in counts[kind][part])
            shown = ", ".join(f"{total:,.0f} ({main:,.0f} main)" for total, main in counts[kind][part])
            print(f"{part:6} {kind:8} instructions per {per[part]}: {shown}; median {medians[kind]:,.0f}")
        if "bare" in medians:
            for kind, median in medians.items():
                print(f"{part:6} {kind:8} {median / medians['bare']:.3f} x the bare server")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
