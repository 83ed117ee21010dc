"""Wildcard Listens and a device that cannot be reached: how soon it is followed again, what waiting costs.

Run ``python -m bench.unreachable`` (``--quick`` for a short run). One gateway process serves an
in-process robot (``scout1``) and a line-protocol device (``rover``, a simulated robot in a
process of its own, on TCP, registered with the proxy's default reconnect backoff,
0.2 s doubling to 10 s). Two figures:

* **back**: the device is killed, a ``*/location`` Listen is opened (it opens at once, without
  the device), the device stays away for ``away`` seconds and is started again on the same
  port; the figure is the time from the restart to the device's location arriving on the
  stream (marked ``gap``), beside the time to the first Get it answers (its proxy has
  reconnected, after its own backoff). The stream tries the device again as soon as the
  proxy is connected, and at the latest after its retry pause (0.5 s doubling to 10 s).
* **waiting**: ``streams`` ``*/location`` Listens stay open for ``window`` seconds, first with
  the device away (each stream tries it again, at most every 10 s), then with it back; the
  figure is the gateway's CPU time in each window.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import signal
import socket
import sys
import tempfile
import time
from pathlib import Path

import grpc

from bench.servers import ServerProcess
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

CONFIG = """
[gateway]
call_timeout = 2.0

[limits]
max_streams = 2000

[[services]]
name = "scout1"
type = "sim-robot"

[[services]]
name = "rover"
url = "tcp://127.0.0.1:{port}"
"""


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port: int = sock.getsockname()[1]
    return port


async def start_device(port: int) -> ServerProcess:
    argv = ["services.device", "--service", "sim-robot", "--name", "rover"]
    argv += ["--tcp", f"127.0.0.1:{port}"]
    return await ServerProcess.start("device", argv, address_on="stdout")


def kill(device: ServerProcess) -> None:
    """A power cut: SIGKILL, no goodbye."""
    with contextlib.suppress(ProcessLookupError):
        os.kill(device.pid, signal.SIGKILL)


async def read_until_sync(call: grpc.aio.UnaryStreamCall) -> set[str]:
    services = set()
    while True:
        msg = await call.read()
        services.update(e.service for e in msg.events)
        if msg.sync:
            return services


async def wait_unreachable(stub: pb_grpc.PropertyServiceStub) -> None:
    for _ in range(200):
        try:
            await stub.Get(pb.GetRequest(service="rover", property="location"), timeout=2)
        except grpc.aio.AioRpcError as exc:
            if exc.code() == grpc.StatusCode.UNAVAILABLE:
                return
        await asyncio.sleep(0.05)
    raise RuntimeError("the gateway never noticed that the device went away")


async def measure_back(
    stub: pb_grpc.PropertyServiceStub, port: int, device: ServerProcess, away: float
) -> tuple[float, float, ServerProcess]:
    """Seconds from the device's restart to its location on a ``*/location`` stream opened without it,
    seconds to the first Get it answers (its proxy reconnected), and the device started again."""
    kill(device)
    await device.stop()
    await wait_unreachable(stub)
    call = stub.Listen(pb.ListenRequest(service="*", property="location"))
    try:
        seen = await asyncio.wait_for(read_until_sync(call), 10)
        if "rover" in seen:
            raise RuntimeError("the stream has the device that is away")
        await asyncio.sleep(away)
        restarted = time.perf_counter()
        device = await start_device(port)
        answering = asyncio.create_task(first_answer(stub))
        async with asyncio.timeout(60):
            while True:
                msg = await call.read()
                if any(e.service == "rover" and e.gap for e in msg.events):
                    back = time.perf_counter() - restarted
                    return back, await answering - restarted, device
    finally:
        call.cancel()


async def first_answer(stub: pb_grpc.PropertyServiceStub) -> float:
    """When a Get of the device first answers (its proxy has reconnected), asking every 20 ms."""
    async with asyncio.timeout(60):
        while True:
            try:
                await stub.Get(pb.GetRequest(service="rover", property="location"), timeout=2)
                return time.perf_counter()
            except grpc.aio.AioRpcError:
                await asyncio.sleep(0.02)


async def measure_waiting(
    stub: pb_grpc.PropertyServiceStub, gateway: ServerProcess, streams: int, window: float
) -> float:
    """The gateway's CPU seconds over ``window`` seconds with ``streams`` ``*/location`` Listens open."""
    calls = [stub.Listen(pb.ListenRequest(service="*", property="location")) for _ in range(streams)]
    try:
        await asyncio.gather(*(asyncio.wait_for(read_until_sync(c), 60) for c in calls))
        await asyncio.sleep(12)  # past the longest retry pause: the steady state is measured
        before = gateway.cpu_seconds()
        await asyncio.sleep(window)
        return gateway.cpu_seconds() - before
    finally:
        for c in calls:
            c.cancel()


async def main(quick: bool) -> None:
    aways = (1.0, 5.0) if quick else (1.0, 5.0, 30.0)
    streams, window = (100, 10.0) if quick else (500, 30.0)
    port = free_port()
    device = await start_device(port)
    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "gateway.toml"
        config.write_text(CONFIG.format(port=port))
        argv = ["gateway.cli", "serve", "--config", str(config), "--listen", "127.0.0.1:0"]
        gateway = await ServerProcess.start("gateway", argv, address_on="stdout")
        try:
            async with grpc.aio.insecure_channel(gateway.address) as channel:
                stub = pb_grpc.PropertyServiceStub(channel)
                first = pb.GetRequest(service="rover", property="location")
                await stub.Get(first, timeout=10, wait_for_ready=True)
                print("back: seconds from the device's restart to its location on a */location stream")
                print("      (and to the first Get it answers: the proxy's reconnect backoff)")
                for away in aways:
                    seconds, answered, device = await measure_back(stub, port, device, away)
                    print(f"  away {away:4.0f} s: back after {seconds:5.2f} s", end=" ")
                    print(f"(Get answers after {answered:5.2f} s)")
                print(f"waiting: gateway CPU over {window:.0f} s with {streams} */location streams open")
                alive = await measure_waiting(stub, gateway, streams, window)
                kill(device)
                await device.stop()
                await wait_unreachable(stub)
                away_cpu = await measure_waiting(stub, gateway, streams, window)
                print(f"  device there: {alive:6.3f} s CPU ({100 * alive / window:.2f} % of a core)")
                print(f"  device away:  {away_cpu:6.3f} s CPU ({100 * away_cpu / window:.2f} % of a core)")
        finally:
            await gateway.stop()
            await device.stop()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="python -m bench.unreachable", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer and shorter rounds")
    asyncio.run(main(parser.parse_args().quick))
    sys.exit(0)
