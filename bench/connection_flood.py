"""Idle connections from one address against a gateway with its default caps: what a bystander sees.

One gateway process (default config plus a simulated robot ``bot``, the HTTP front end and the
line listener on free ports). The bystander, from 127.0.0.1, measures the p99 of 200 gRPC Gets
and of 200 HTTP Gets of ``bot/location`` and the time a device takes to dial in and be
``up``, before and while ``--connections`` connections (default 10,000) from 127.0.0.2 sit
idle on one port (``--port http``, ``grpc`` or ``line``). The gateway's RSS is read before, with
the flood open, and after it is closed. Run with::

    python -m bench.connection_flood [--connections 10000] [--port http]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import aiohttp
import grpc

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

ROOT = Path(__file__).resolve().parents[1]
ATTACKER = "127.0.0.2"
SAMPLES = 200
WAIT = 30.0


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status", encoding="ascii") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _p99(times: list[float]) -> float:
    times = sorted(times)
    return times[int(0.99 * (len(times) - 1))] * 1e3


async def _grpc_p99(stub: pb_grpc.PropertyServiceStub) -> float:
    times = []
    for _ in range(SAMPLES):
        began = time.perf_counter()
        await stub.Get(pb.GetRequest(service="bot", property="location"), timeout=WAIT)
        times.append(time.perf_counter() - began)
    return _p99(times)


async def _http_p99(base: str) -> float:
    times = []
    async with aiohttp.ClientSession(base_url=base) as session:
        for _ in range(SAMPLES):
            began = time.perf_counter()
            async with session.get("/api/v1/services/bot/properties/location") as response:
                await response.read()
                assert response.status == 200, response.status
            times.append(time.perf_counter() - began)
    return _p99(times)


def _start_device(line: str, name: str) -> subprocess.Popen[bytes]:
    argv = [sys.executable, "-m", "services.device", "--service", "sim-robot", "--name", name]
    return subprocess.Popen(
        [*argv, "--connect", line], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )


def _start_gateway(config: Path) -> subprocess.Popen[str]:
    argv = ["-m", "gateway.cli", "serve", "--config", str(config), "--listen", "127.0.0.1:0"]
    return subprocess.Popen(
        [sys.executable, *argv, "--http", "127.0.0.1:0"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


async def _dial_in(stub: pb_grpc.PropertyServiceStub, line: str, name: str) -> float:
    """Seconds from starting a device that dials in to its being ``up`` in the registry."""
    began = time.perf_counter()
    device = _start_device(line, name)
    try:
        while time.perf_counter() - began < WAIT:
            with contextlib.suppress(grpc.aio.AioRpcError):
                reply = await stub.Get(
                    pb.GetRequest(service="registry", property=f"services.{name}.state"), timeout=WAIT
                )
                if reply.value == "up":
                    return time.perf_counter() - began
            await asyncio.sleep(0.05)
        return float("inf")
    finally:
        device.terminate()
        device.wait(10)


async def _ends_within(reader: asyncio.StreamReader, seconds: float) -> bool:
    """Whether the gateway closed this connection (having refused it) within ``seconds``."""
    try:
        await asyncio.wait_for(reader.read(), seconds)
    except TimeoutError:
        return False
    except ConnectionError:
        pass
    return True


async def _bystander(stub: pb_grpc.PropertyServiceStub, base: str, line: str, name: str) -> str:
    grpc_p99 = await _grpc_p99(stub)
    http_p99 = await _http_p99(base)
    dial = await _dial_in(stub, line, name)
    return f"gRPC Get p99 {grpc_p99:.1f} ms, HTTP Get p99 {http_p99:.1f} ms, device up in {dial:.2f} s"


async def main(connections: int, target: str) -> None:
    line_port = _free_port()
    with tempfile.TemporaryDirectory() as folder:
        config = Path(folder) / "flood.toml"
        config.write_text(
            f'[gateway]\nline_listen = "127.0.0.1:{line_port}"\n'
            '[[services]]\nname = "bot"\ntype = "sim-robot"\n'
        )
        gateway = _start_gateway(config)
        assert gateway.stdout is not None
        grpc_address = http_url = ""
        while not (grpc_address and http_url):
            line = gateway.stdout.readline()
            if not line:
                raise SystemExit("the gateway did not start")
            if m := re.match(r"^listening on (\S+:\d+)$", line.strip()):
                grpc_address = m.group(1)
            if m := re.match(r"^HTTP front end and console on (\S+)$", line.strip()):
                http_url = m.group(1)
        log_lines: list[str] = []
        reader = asyncio.get_running_loop().run_in_executor(None, lambda: log_lines.extend(gateway.stdout))  # type: ignore[arg-type]
        try:
            ports = {
                "http": int(http_url.rstrip("/").rpartition(":")[2]),
                "grpc": int(grpc_address.rpartition(":")[2]),
                "line": line_port,
            }
            line_address = f"127.0.0.1:{line_port}"
            async with grpc.aio.insecure_channel(grpc_address) as channel:
                stub = pb_grpc.PropertyServiceStub(channel)
                await _grpc_p99(stub)  # warm up
                rss_before = _rss_mb(gateway.pid)
                print(
                    f"before: RSS {rss_before:.1f} MB; "
                    + await _bystander(stub, http_url, line_address, "d1")
                )
                flood = []
                began = time.perf_counter()
                for _ in range(connections):
                    try:
                        flood.append(
                            await asyncio.open_connection(
                                "127.0.0.1", ports[target], local_addr=(ATTACKER, 0)
                            )
                        )
                    except OSError as exc:
                        print(f"the flood stopped at {len(flood)} connections: {exc}")
                        break
                ended = await asyncio.gather(*(_ends_within(reader, 2.0) for reader, _ in flood))
                still_open = ended.count(False)
                print(
                    f"{len(flood)} connections to the {target} port from {ATTACKER} in"
                    f" {time.perf_counter() - began:.1f} s; the gateway holds {still_open} of them"
                )
                rss_during = _rss_mb(gateway.pid)
                print(
                    f"during: RSS {rss_during:.1f} MB; "
                    + await _bystander(stub, http_url, line_address, "d2")
                )
                for _, writer in flood:
                    writer.close()
                await asyncio.sleep(2.0)
                print(f"after: RSS {_rss_mb(gateway.pid):.1f} MB")
        finally:
            gateway.terminate()
            gateway.wait(10)
            await reader
        refusals = sum("refused" in line for line in log_lines)
        print(f"gateway log: {len(log_lines)} lines, {refusals} about refused connections")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connections", type=int, default=10_000)
    parser.add_argument("--port", choices=("http", "grpc", "line"), default="http")
    args = parser.parse_args()
    asyncio.run(main(args.connections, args.port))
