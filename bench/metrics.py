"""Part (p): what the Prometheus metrics cost on the unary Get path — the gateway with and without them.

Two gateway processes serve the same bench service side by side, one with ``[metrics]``
on (the default: every call counted, latencies in a histogram) and one with it off; the
same client code drives both with unary Gets, several in flight, in pairs of batches (one
on each, the order alternating), so that load from elsewhere on the machine falls on both
halves of a pair alike. The figure is the median of the pairs' ratios; the table shows each
way's best batch. The gateway with metrics is scraped at the end, so that the exposition is
shown to reflect the Gets (``scraped_get_calls``: warm-ups included).
"""

from __future__ import annotations

import asyncio
import re
import statistics
import urllib.request
from typing import Any

from bench.servers import ServerProcess
from bench.unary import run_unary

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
    """Unary Gets on a gateway with and without metrics, in pairs of batches; the median pair's ratio.

    Both gateways run side by side; each pair is a batch on one and then on the other (the order
    alternates), so that a change of load on the machine falls on both halves of a pair alike.
    """
    batches = max(2 * rounds, 6)
    per_batch = max(calls // batches, 100)
    servers = {way: await ServerProcess.start(f"gateway {way}", argv) for way, argv in WAYS.items()}
    try:
        figures: dict[str, list[dict[str, Any]]] = {way: [] for way in WAYS}
        ratios = []
        for number in range(batches):
            order = list(WAYS) if number % 2 == 0 else list(reversed(WAYS))
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
        scraped = float(found.group(1)) if found else 0.0
    finally:
        for server in servers.values():
            await server.stop()
    best = {way: max(results, key=lambda d: float(d["throughput_per_s"])) for way, results in figures.items()}
    return {
        **best,
        "pairs": len(ratios),
        "calls_per_batch": per_batch,
        "pair_ratios": [round(r, 3) for r in ratios],
        "ratio": round(statistics.median(ratios), 3),
        "scraped_get_calls": scraped,
    }


def _metrics_url(log: str) -> str:
    found = re.search(r"metrics on (http://\S+/metrics)", log)
    if found is None:
        raise RuntimeError(f"the gateway did not say where its metrics are:\n{log}")
    return found.group(1)
