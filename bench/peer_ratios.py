"""The gateway's figures against each peer's, measured in the same run with the same client pattern.

Each comparison names a figure, the gateway's way of getting it (unary or
Session, one-by-one or batched) and the bare server's figure of the same
way, and is printed as gateway / peer for every peer measured. None of them
is a target: the peers are anchors that say where the gateway stands among
other ways of doing the same job (docs/performance.md says what each
compares and what it does not).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

#: results[server][part] as the benchmark keeps it (bench.report.Results).
Results = dict[str, dict[str, dict[str, Any]]]
Figure = Callable[[dict[str, dict[str, Any]]], float]


@dataclass(frozen=True)
class Comparison:
    """One figure, read from a gRPC server's parts and from a peer's patterns."""

    figure: str
    way: str
    #: From a gRPC server's parts (the gateway's, and the bare server's of the same way).
    server: Figure
    #: From a peer's patterns (results[peer]["peers"]).
    peer: Callable[[dict[str, Any]], float]
    lower_is_better: bool


def _sequential(way: str, key: str) -> Figure:
    return lambda parts: float(parts["sequential"]["ways"][way]["latency"][key])


def _rate(part: str, key: str) -> Figure:
    return lambda parts: float(parts[part][key])


def _p50(part: str) -> Figure:
    return lambda parts: float(parts[part]["latency"]["p50_us"])


COMPARISONS = (
    Comparison(
        "Get one at a time, p50 µs",
        "unary",
        _sequential("unary", "p50_us"),
        lambda p: float(p["sequential"]["latency"]["p50_us"]),
        True,
    ),
    Comparison(
        "Get one at a time, p50 µs",
        "Session",
        _sequential("session", "p50_us"),
        lambda p: float(p["sequential"]["latency"]["p50_us"]),
        True,
    ),
    Comparison(
        "Get one at a time, p99 µs",
        "unary",
        _sequential("unary", "p99_us"),
        lambda p: float(p["sequential"]["latency"]["p99_us"]),
        True,
    ),
    Comparison(
        "Get one at a time, p99 µs",
        "Session",
        _sequential("session", "p99_us"),
        lambda p: float(p["sequential"]["latency"]["p99_us"]),
        True,
    ),
    Comparison(
        "Gets/s, 8 in flight",
        "unary",
        _rate("unary", "throughput_per_s"),
        lambda p: float(p["unary"]["throughput_per_s"]),
        False,
    ),
    Comparison(
        "Gets/s, 8 in flight",
        "Session, batched",
        _rate("session", "throughput_per_s"),
        lambda p: float(p["unary"]["throughput_per_s"]),
        False,
    ),
    Comparison(
        "fan-out, events/s",
        "one-by-one",
        _rate("listen", "events_per_s"),
        lambda p: float(p["listen"]["events_per_s"]),
        False,
    ),
    Comparison(
        "fan-out, events/s",
        "batched",
        _rate("batched", "events_per_s"),
        lambda p: float(p["listen"]["events_per_s"]),
        False,
    ),
    Comparison(
        "paced Set→delivery p50 µs",
        "Listen",
        _p50("paced"),
        lambda p: float(p["paced"]["latency"]["p50_us"]),
        True,
    ),
)


def measured_peers(results: Results) -> dict[str, dict[str, Any]]:
    """The peers whose part (s) ran: name → its patterns (skipped ones and errors left out)."""
    return {
        name: parts["peers"]
        for name, parts in results.items()
        if "peers" in parts and "skipped" not in parts["peers"] and "error" not in parts["peers"]
    }


def _read(read: Callable[[Any], float], data: Any) -> float | None:
    try:
        value = read(data)
    except (KeyError, TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def compare(results: Results) -> list[dict[str, Any]]:
    """Each comparison's figures (None where a part did not run) and the gateway / peer ratios."""
    peers = measured_peers(results)
    rows = []
    for comparison in COMPARISONS:
        gateway = _read(comparison.server, results.get("gateway", {}))
        bare = _read(comparison.server, results.get("baseline", {}))
        figures = {name: _read(comparison.peer, data) for name, data in peers.items()}
        rows.append(
            {
                "figure": comparison.figure,
                "way": comparison.way,
                "lower_is_better": comparison.lower_is_better,
                "baseline": bare,
                "gateway": gateway,
                "peers": figures,
                "gateway_over_peer": {
                    name: round(gateway / value, 3) if gateway is not None and value else None
                    for name, value in figures.items()
                },
            }
        )
    return rows
