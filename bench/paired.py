"""The unary tax in pairs: the gateway and the bare server side by side, batch for batch.

Run ``python -m bench.paired`` (``--pairs N``, ``--calls N``). Part (a) of ``python -m bench``
measures one server after the other; on a shared machine a change of load between the two
moves their ratio by ±30 %. Here both run at once, and the same client code (part (a)'s
:func:`bench.unary.run_unary`) makes a batch of unary Gets on one and then on the other, the
order alternating, so that load from elsewhere falls on both halves of a pair alike (the
design of part (p)). Half way both are started afresh in the other order. For 1 and for 8
Gets in flight the figures are the median over the pairs of the gateway's p50 over the bare
server's and of its Gets/s over the bare server's, with the spread of the pairs beside them.
``--control`` runs the same with two bare servers (an A/A run: how far the design resolves).
"""

from __future__ import annotations

import argparse
import asyncio
import statistics

from bench.servers import ServerProcess
from bench.unary import UnaryResult, run_unary

SERVERS = {
    "bare": ["bench.baseline", "--listen", "127.0.0.1:0"],
    "gateway": ["bench.gateway_server", "--listen", "127.0.0.1:0"],
}


async def pairs(
    sides: dict[str, list[str]], *, inflight: int, pairs: int, calls: int
) -> list[tuple[float, float]]:
    """``pairs`` pairs of batches of ``calls`` Gets; each pair's (p50, Gets/s) ratio, second side / first."""
    first, second = sides
    ratios: list[tuple[float, float]] = []
    for half in (0, 1):
        order = (first, second) if half == 0 else (second, first)
        servers = {name: await ServerProcess.start(name, sides[name]) for name in order}
        try:
            for server in servers.values():  # warm up, not counted
                await run_unary(server, calls=200, inflight=inflight, warmup=100, time_limit=60)
            for n in range(pairs // 2 if half == 0 else pairs - pairs // 2):
                results: dict[str, UnaryResult] = {}
                for name in order if n % 2 == 0 else order[::-1]:
                    results[name] = await run_unary(
                        servers[name], calls=calls, inflight=inflight, warmup=0, time_limit=60
                    )
                a, b = results[first], results[second]
                ratios.append((b.latency.p50_us / a.latency.p50_us, b.throughput / a.throughput))
        finally:
            for server in servers.values():
                await server.stop()
    return ratios


def _spread(values: list[float]) -> str:
    return f"median {statistics.median(values):.3f}, pairs {min(values):.2f}-{max(values):.2f}"


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m bench.paired``."""
    parser = argparse.ArgumentParser(prog="python -m bench.paired", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--pairs", type=int, default=10, help="pairs of batches per in-flight count (default 10)"
    )
    parser.add_argument("--calls", type=int, default=2000, help="Gets per batch (default 2,000)")
    parser.add_argument("--control", action="store_true", help="two bare servers (an A/A run)")
    args = parser.parse_args(argv)
    sides = {"bare": SERVERS["bare"], "other bare": SERVERS["bare"]} if args.control else SERVERS
    label = "bare / bare" if args.control else "gateway / bare"
    for inflight in (1, 8):
        ratios = asyncio.run(pairs(sides, inflight=inflight, pairs=args.pairs, calls=args.calls))
        print(f"{inflight} in flight, {label}: p50 {_spread([p for p, _ in ratios])}")
        print(f"{inflight} in flight, {label}: Gets/s {_spread([t for _, t in ratios])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
