"""Part (p): what the Prometheus metrics cost on the unary Get path — the gateway with and without them.

Two gateway processes serve the same bench service side by side, one with ``[metrics]``
on (the default: every call counted, latencies in a histogram) and one with it off; the
same client code drives both with unary Gets, several in flight, in pairs of batches (one
on each, the order alternating), so that load from elsewhere on the machine falls on both
halves of a pair alike. The figure is the median of the pairs' ratios (a best batch is an
extreme, and swung from 0.56 to 1.25 between runs on a loaded machine where the median stayed
within 0.80-1.03); every pair's own ratio and the ratio of the best batches are kept beside it,
and so is the in-process cost of counting
one call (``counting_ns_per_call``) and its share of one core at the throughput without metrics.
Half way both are started afresh in the other order (on a shared machine the first process
started can come out slower whatever it runs). The gateway with metrics is scraped at the end of
each half, so that the exposition is shown to reflect the Gets (``scraped_get_calls``: the two
scrapes summed, warm-ups included).
"""

from __future__ import annotations

import asyncio
import math
import re
import statistics
import time
import urllib.request
from time import perf_counter
from typing import Any

from bench.servers import ServerProcess
from bench.unary import run_unary
from gateway.metrics.counts import MethodCounts

#: The two gateways: the same command, metrics on (the default) and off.
WAYS: dict[str, list[str]] = {
    "metrics-on": ["bench.gateway_server", "--listen", "127.0.0.1:0", "--metrics", "127.0.0.1:0"],
    "metrics-off": ["bench.gateway_server", "--listen", "127.0.0.1:0", "--no-metrics"],
}

_OK_GETS = re.compile(r'^psgateway_grpc_calls_total\{code="OK",method="Get"\} (\S+)$', re.MULTILINE)


def _scrape(url: str) -> str:
    with urllib.request.urlopen(url, timeout=10) as response:
        text: str = response.read().decode()
    return text


async def run_metrics(*, calls: int, inflight: int, rounds: int, time_limit: float) -> dict[str, Any]:
    """Unary Gets on a gateway with and without metrics, in pairs of batches; the median of the
    pairs' ratios, beside every pair's own ratio and the ratio of each way's best batch.

    Both gateways run side by side; each pair is a batch on one and then on the other (the order
    alternates), so that a change of load on the machine falls on both halves of a pair alike.
    Half way the two are started afresh in the other order: on a shared machine the first process
    started can come out slower whatever it runs, and this way each way is first for half the pairs.
    """
    batches = max(5 * rounds, 10)
    per_batch = max(calls // batches, 100)
    figures: dict[str, list[dict[str, Any]]] = {way: [] for way in WAYS}
    ratios: list[float] = []
    scraped = 0.0
    for half in range(2):
        ways = list(WAYS) if half == 0 else list(reversed(WAYS))
        servers = {way: await ServerProcess.start(f"gateway {way}", WAYS[way]) for way in ways}
        try:
            for number in range(batches // 2):
                order = ways if number % 2 == 0 else list(reversed(ways))
                pair: dict[str, float] = {}
                for way in order:
                    result = (
                        await run_unary(
                            servers[way],
                            calls=per_batch,
                            inflight=inflight,
                            warmup=max(per_batch // 10, 10),
                            time_limit=time_limit / batches,
                        )
                    ).as_dict()
                    if result.get("errors"):
                        raise RuntimeError(f"{way}: {result['errors']} calls failed")
                    figures[way].append(result)
                    pair[way] = float(result["throughput_per_s"])
                ratios.append(pair["metrics-on"] / pair["metrics-off"])
            found = _OK_GETS.search(
                await asyncio.to_thread(_scrape, _metrics_url(servers["metrics-on"].log_tail))
            )
            scraped += float(found.group(1)) if found else 0.0
        finally:
            for server in servers.values():
                await server.stop()
    best = {way: max(results, key=lambda d: float(d["throughput_per_s"])) for way, results in figures.items()}
    on, off = (float(best[way]["throughput_per_s"]) for way in ("metrics-on", "metrics-off"))
    counting_ns = counting_cost()
    return {
        **best,
        "pairs": len(ratios),
        "calls_per_batch": per_batch,
        "ratio": round(statistics.median(ratios), 3),
        "pair_ratios": [round(r, 3) for r in ratios],
        "best_batch_ratio": round(on / off, 3),
        "scraped_get_calls": scraped,
        # Server CPU per call is less swayed by other load than the rate: the median batch of each way.
        "cpu_us_per_call": {
            way: statistics.median(float(d["server_cpu_us_per_call"]) for d in results)
            for way, results in figures.items()
        },
        "counting_ns_per_call": counting_ns,
        # The counting's share of one core at the throughput without metrics: what it can cost at most.
        "counting_share": round(counting_ns * off / 1e9, 5),
    }


def counting_cost(calls: int = 200_000) -> float:
    """Nanoseconds the counting of one unary call takes in this process (the clock twice, one code
    count and one histogram bucket): what the gateway adds to each Get, without the noise of a run."""
    counts = MethodCounts()
    best = math.inf
    for _ in range(3):
        started = time.perf_counter_ns()
        for _ in range(calls):
            began = perf_counter()
            counts.done(0, perf_counter() - began)
        best = min(best, (time.perf_counter_ns() - started) / calls)
    loop = math.inf
    for _ in range(3):
        started = time.perf_counter_ns()
        for _ in range(calls):
            pass
        loop = min(loop, (time.perf_counter_ns() - started) / calls)
    return round(best - loop, 1)


def _metrics_url(log: str) -> str:
    found = re.search(r"metrics on (http://\S+/metrics)", log)
    if found is None:
        raise RuntimeError(f"the gateway did not say where its metrics are:\n{log}")
    return found.group(1)
