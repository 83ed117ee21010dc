"""Binary values on the line protocol: a file's bytes read from a line device through the gateway.

Run ``python -m bench.line_binary`` (``--quick`` for a short run). A device process serves the
storage service (``psgateway device --service storage``) on TCP; its ``blob`` property is a file
as bytes, sent on the line as ``\\=`` and base64 (docs/device-spec.md §2.6). One gateway
process proxies it (``tcp://...?maxline=8388608``). For each size (750 bytes: the largest that
fits the default 1024-byte line; 40 kB: a 640×480 JPEG; 1 MB) the figures are Gets per second
and their p50 through the gateway with one call in flight, and the CPU time per Get of the
gateway and of the device; each Get's bytes are compared with the file's.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import grpc

from bench.servers import ServerProcess
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

#: A line of 8 MiB holds the base64 of the largest value one gRPC message carries (4 MiB).
MAX_LINE = 8 * 1024 * 1024
#: (bytes, Gets in a full run): the largest value of a default line, a 640×480 JPEG, 1 MB.
SIZES = ((750, 3000), (40_000, 1500), (1_000_000, 100))


async def measure(stub: pb_grpc.PropertyServiceStub, name: str, data: bytes, count: int) -> list[float]:
    """Seconds of each of ``count`` Gets of ``blob`` (``name=...``), one at a time."""
    request = pb.GetRequest(service="files", property="blob", parameters={"name": name})
    times = []
    for _ in range(count):
        start = time.perf_counter()
        reply = await stub.Get(request, timeout=10)
        times.append(time.perf_counter() - start)
        if reply.data != data:
            raise RuntimeError(f"{name}: the bytes read differ from the file's")
    return times


async def main(quick: bool) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "files"
        folder.mkdir()
        argv = ["services.device", "--service", "storage", "--option", f"directory={folder}"]
        argv += ["--name", "files", "--tcp", "127.0.0.1:0", "--max-line", str(MAX_LINE)]
        device = await ServerProcess.start("device", argv, address_on="stdout")
        config = Path(tmp) / "gateway.toml"
        config.write_text(
            f'[[services]]\nname = "files"\nurl = "tcp://{device.address}?maxline={MAX_LINE}"\n', "utf-8"
        )
        argv = ["gateway.cli", "serve", "--config", str(config), "--listen", "127.0.0.1:0"]
        gateway = await ServerProcess.start("gateway", argv, address_on="stdout")
        try:
            options = [("grpc.max_receive_message_length", 8 * 1024 * 1024)]
            async with grpc.aio.insecure_channel(gateway.address, options=options) as channel:
                stub = pb_grpc.PropertyServiceStub(channel)
                print(f"load average {os.getloadavg()[0]:.2f} at the start")
                print(
                    "bytes      line bytes  Gets  Gets/s  p50 ms   MB/s"
                    "  gateway µs CPU/Get  device µs CPU/Get"
                )
                for size, full in SIZES:
                    count = max(10, full // 10) if quick else full
                    data = os.urandom(size)
                    name = f"value{size}.bin"
                    (folder / name).write_bytes(data)
                    await measure(stub, name, data, min(count, 20))  # warm up (and wait for the device)
                    gateway_cpu, device_cpu = gateway.cpu_seconds(), device.cpu_seconds()
                    start = time.perf_counter()
                    times = await measure(stub, name, data, count)
                    elapsed = time.perf_counter() - start
                    gateway_cpu = gateway.cpu_seconds() - gateway_cpu
                    device_cpu = device.cpu_seconds() - device_cpu
                    line = len("#ffffffff OK \\=") + 4 * -(-size // 3) + 1
                    print(
                        f"{size:>9,}  {line:>10,}  {count:>4}  {count / elapsed:6,.0f}  "
                        f"{statistics.median(times) * 1e3:6.2f}  {size * count / elapsed / 1e6:5.1f}  "
                        f"{gateway_cpu / count * 1e6:18,.0f}  {device_cpu / count * 1e6:17,.0f}"
                    )
        finally:
            await gateway.stop()
            await device.stop()


def run() -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.line_binary", description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a tenth of the Gets")
    args = parser.parse_args()
    print(f"command: {' '.join(['python -m bench.line_binary', *sys.argv[1:]])}")
    asyncio.run(main(args.quick))


if __name__ == "__main__":
    run()
