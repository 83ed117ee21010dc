"""Bursts of concurrent unary Gets against a gateway process: how many end with which status.

One gateway process (default config plus a simulated robot ``bot``). ``--calls`` Gets of
``bot/location`` (default 5,000) are started at once over ``--connections`` channels (default
1 and 10, one run each), with a deadline of 60 s; the status codes are counted. Run with::

    python -m bench.call_burst [--calls 5000] [--connections 1 10]
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import grpc

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

ROOT = Path(__file__).resolve().parents[1]


def _start_gateway(config: Path) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "gateway.cli", "serve", "--config", str(config), "--listen", "127.0.0.1:0"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


async def burst(address: str, calls: int, connections: int) -> str:
    # A local subchannel pool: each channel its own connection.
    options = [("grpc.use_local_subchannel_pool", 1)]
    channels = [grpc.aio.insecure_channel(address, options=options) for _ in range(connections)]
    try:
        stubs = [pb_grpc.PropertyServiceStub(channel) for channel in channels]
        request = pb.GetRequest(service="bot", property="location")
        began = time.perf_counter()
        results = await asyncio.gather(
            *(stubs[i % connections].Get(request, timeout=60) for i in range(calls)), return_exceptions=True
        )
        took = time.perf_counter() - began
    finally:
        for channel in channels:
            await channel.close()
    codes = collections.Counter(
        r.code().name if isinstance(r, grpc.aio.AioRpcError) else "OK" for r in results
    )
    shown = ", ".join(f"{code} {count}" for code, count in codes.most_common())
    return f"{calls} Gets over {connections} connection(s) in {took:.1f} s: {shown}"


async def main(calls: int, connections: list[int]) -> None:
    with tempfile.TemporaryDirectory() as folder:
        config = Path(folder) / "burst.toml"
        config.write_text('[[services]]\nname = "bot"\ntype = "sim-robot"\n')
        gateway = _start_gateway(config)
        try:
            assert gateway.stdout is not None
            address = ""
            while not address:
                line = gateway.stdout.readline()
                if not line:
                    raise SystemExit("the gateway did not start")
                if m := re.match(r"^listening on (\S+:\d+)$", line.strip()):
                    address = m.group(1)
            for count in connections:
                print(await burst(address, calls, count))
        finally:
            gateway.terminate()
            gateway.wait(10)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=5000)
    parser.add_argument("--connections", type=int, nargs="+", default=[1, 10])
    args = parser.parse_args()
    asyncio.run(main(args.calls, args.connections))
