"""What line-protocol flow control costs: Gets through the TCP proxy to a device that states it, and not.

A Python device process (``python -m services.device --service
sim-robot --tcp 127.0.0.1:0``) is started once per setting of its greeting:
no flow-control fields (as a 1.0 device), ``inflight=1`` (what a serial
device that states nothing gets) and ``rxbuf=32`` (a 32-byte receive buffer).
This process holds a :class:`gateway.proxies.TcpProxy` to it and makes
``calls`` Gets of ``speed`` with ``concurrency`` of them in flight; it prints
calls per second and the median latency of each setting.

    python -m bench.line_flow_control --calls 2000 --concurrency 16
"""

from __future__ import annotations

import argparse
import asyncio
import re
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence

from gateway.proxies import TcpProxy, open_tcp_backend

SETTINGS: dict[str, list[str]] = {
    "1.0 (no fields)": [],
    "inflight=1": ["--inflight", "1"],
    "rxbuf=32": ["--rxbuf", "32"],
}


async def measure(port: int, calls: int, concurrency: int) -> tuple[float, float]:
    """(calls per second, median latency in ms) of ``calls`` Gets, ``concurrency`` at a time."""
    proxy = open_tcp_backend("dev", f"tcp://127.0.0.1:{port}", {"timeout": 30.0})
    assert isinstance(proxy, TcpProxy)
    await proxy.start()
    try:
        await proxy.wait_connected(10)
        latencies: list[float] = []
        todo = iter(range(calls))

        async def worker() -> None:
            for _ in todo:
                start = time.perf_counter()
                await proxy.get("speed")
                latencies.append(time.perf_counter() - start)

        began = time.perf_counter()
        await asyncio.gather(*(worker() for _ in range(concurrency)))
        elapsed = time.perf_counter() - began
    finally:
        await proxy.aclose()
    return calls / elapsed, statistics.median(latencies) * 1000


def run(calls: int, concurrency: int) -> list[tuple[str, float, float]]:
    rows = []
    for label, extra in SETTINGS.items():
        argv = [
            sys.executable,
            "-m",
            "services.device",
            "--service",
            "sim-robot",
            "--tcp",
            "127.0.0.1:0",
        ]
        device = subprocess.Popen([*argv, *extra], stdout=subprocess.PIPE, text=True)
        try:
            assert device.stdout is not None
            match = re.fullmatch(r"listening on .+:(\d+)", device.stdout.readline().strip())
            assert match, "the device did not start"
            rate, median = asyncio.run(measure(int(match.group(1)), calls, concurrency))
        finally:
            device.terminate()
            device.wait(10)
        rows.append((label, rate, median))
    return rows


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=2000)
    parser.add_argument("--concurrency", type=int, default=16)
    args = parser.parse_args(argv)
    print(f"{args.calls} Gets of speed, {args.concurrency} callers at once, through one TcpProxy")
    print(f"{'device greeting':<18} {'calls/s':>9} {'median ms':>10}")
    for label, rate, median in run(args.calls, args.concurrency):
        print(f"{label:<18} {rate:>9.0f} {median:>10.2f}")


if __name__ == "__main__":
    main()
