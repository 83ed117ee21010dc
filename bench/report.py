"""The machine, the tables of absolute figures, the ratios against the targets, and the JSON file."""

from __future__ import annotations

import json
import math
import os
import platform
import sys
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any, TextIO

from bench.peer_ratios import compare, measured_peers

#: results[server][part] is a part's ``as_dict()``, or {"error": "..."}.
Results = dict[str, dict[str, dict[str, Any]]]


def machine() -> dict[str, Any]:
    """What the figures were measured on."""
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass

    def version(name: str) -> str:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            return "not installed"

    return {
        "cpu_model": model,
        "logical_cores": os.cpu_count(),
        "usable_cores": len(os.sched_getaffinity(0)),
        "memory_gib": round(_psutil().virtual_memory().total / 2**30, 1),
        "os": f"{platform.system()} {platform.release()}",
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        "grpcio": version("grpcio"),
        "protobuf": version("protobuf"),
        "load_average_at_start": [round(x, 2) for x in os.getloadavg()],
    }


@dataclass(frozen=True)
class Target:
    """One target of the benchmark: a figure computed from the results, and its bound."""

    name: str
    description: str
    figure: Callable[[Results], float]
    #: "min": the figure must be at least ``bound``; "max": at most.
    kind: str
    bound: float
    unit: str
    needs: tuple[tuple[str, str], ...]
    #: A bound the results choose (the machine they ran on), in place of ``bound``.
    bound_of: Callable[[Results], float] | None = None


def _get(results: Results, server: str, part: str, key: str) -> float:
    return float(results[server][part][key])


def _ratio(
    name: str,
    description: str,
    *,
    top: tuple[str, str],
    bottom: tuple[str, str],
    key: str,
    kind: str,
    bound: float,
) -> Target:
    """A target on the ratio of one figure (``key``) between two (server, part) results."""
    return Target(
        name,
        description,
        lambda r: _get(r, *top, key) / _get(r, *bottom, key),
        kind,
        bound,
        "x",
        (top, bottom),
    )


TARGETS: tuple[Target, ...] = (
    _ratio(
        "unary-get",
        "unary Get throughput, gateway / bare server",
        top=("gateway", "unary"),
        bottom=("baseline", "unary"),
        key="throughput_per_s",
        kind="min",
        bound=0.80,
    ),
    _ratio(
        "session-get",
        "Gets over Session / unary Gets, both on the gateway",
        top=("gateway", "session"),
        bottom=("gateway", "unary"),
        key="throughput_per_s",
        kind="min",
        bound=3.0,
    ),
    _ratio(
        "listen-fanout",
        "Listen events/s, one-by-one, gateway / bare server",
        top=("gateway", "listen"),
        bottom=("baseline", "listen"),
        key="events_per_s",
        kind="min",
        bound=0.80,
    ),
    _ratio(
        "listen-batched",
        "Listen events/s, bursts (gateway batches), gateway / bare server",
        top=("gateway", "batched"),
        bottom=("baseline", "batched"),
        key="events_per_s",
        kind="min",
        bound=3.0,
    ),
    Target(
        "idle-listen-memory",
        "gateway RSS per idle Listen stream",
        lambda r: _get(r, "gateway", "memory", "per_stream_kib"),
        "max",
        16.0,
        "KiB",
        (("gateway", "memory"),),
    ),
)


def _line(results: Results, way: str, inflight: str) -> dict[str, Any]:
    table: dict[str, Any] = results[way]["line"]["inflight"]
    key = max(table, key=int) if inflight == "most" else inflight
    return dict(table[key])


def _largest(results: Results, server: str, part: str) -> dict[str, Any]:
    sizes: list[dict[str, Any]] = results[server][part]["sizes"]
    return sizes[-1]


def _ceiling(hop: float, device: float) -> float:
    """Two stages a batch crosses in turn, at ``hop`` and ``device`` Gets/s alone: their rate
    together, f·d / (f + d), over the device's own."""
    return hop / (hop + device)


def _exponent(results: Results, server: str, part: str, size: str, figure: str) -> float:
    """How the figure grows with the size between the smallest and the largest run: 1.0 = linearly."""
    sizes: list[dict[str, Any]] = results[server][part]["sizes"]
    if len(sizes) < 2:
        return math.nan
    first, last = sizes[0], sizes[-1]
    return math.log(float(last[figure]) / float(first[figure])) / math.log(last[size] / first[size])


TARGETS += (
    Target(
        "line-get-p50",
        "unary Get p50 with 1 in flight, through the gateway's TCP proxy / straight to the device",
        lambda r: (
            _line(r, "gateway", "1")["latency"]["p50_us"] / _line(r, "direct", "1")["latency"]["p50_us"]
        ),
        "max",
        2.0,
        "x",
        (("gateway", "line"), ("direct", "line")),
    ),
    Target(
        "line-get-inflight",
        "unary Gets/s with 8 in flight, through the gateway's TCP proxy / straight to the device",
        lambda r: (
            _line(r, "gateway", "most")["throughput_per_s"] / _line(r, "direct", "most")["throughput_per_s"]
        ),
        "min",
        0.5,
        "x",
        (("gateway", "line"), ("direct", "line")),
    ),
    Target(
        "line-session-p50",
        "Get p50 with 1 in flight, over a Session through the gateway's TCP proxy / straight to the device",
        lambda r: (
            _line(r, "gateway-session", "1")["latency"]["p50_us"]
            / _line(r, "direct", "1")["latency"]["p50_us"]
        ),
        "max",
        2.0,
        "x",
        (("gateway-session", "line"), ("direct", "line")),
    ),
    Target(
        "line-session-inflight",
        "Gets/s with 8 in flight, over a Session through the gateway's TCP proxy / straight to the device",
        lambda r: (
            _line(r, "gateway-session", "most")["throughput_per_s"]
            / _line(r, "direct", "most")["throughput_per_s"]
        ),
        "min",
        0.5,
        "x",
        (("gateway-session", "line"), ("direct", "line")),
    ),
    Target(
        "line-session-proxy-cost",
        "Session Get p50 with 1 in flight through the TCP proxy minus the in-process Session Get p50 "
        "(the floor, same gateway, same run), over the direct line-protocol p50",
        lambda r: (
            (
                _line(r, "gateway-session", "1")["latency"]["p50_us"]
                - _line(r, "session-floor", "1")["latency"]["p50_us"]
            )
            / _line(r, "direct", "1")["latency"]["p50_us"]
        ),
        "max",
        2.0,
        "x",
        (("gateway-session", "line"), ("session-floor", "line"), ("direct", "line")),
    ),
    Target(
        "line-inflight-ceiling",
        "the most the proxied Session path can reach with 8 in flight, / direct: a batch crosses "
        "grpc.aio's own hop (bare server's Session, f) and the device (direct, d) in turn, f·d/(f+d)",
        lambda r: _ceiling(
            _line(r, "bare-session", "most")["throughput_per_s"],
            _line(r, "direct", "most")["throughput_per_s"],
        ),
        "min",
        0.5,
        "x",
        (("bare-session", "line"), ("direct", "line")),
    ),
    Target(
        "group-moveto",
        "group behaviors.moveto, time per member at the largest group",
        lambda r: _largest(r, "in-process", "group")["us_per_member"],
        "max",
        1000.0,
        "µs",
        (("in-process", "group"),),
    ),
    Target(
        "group-scaling",
        "log-log slope of moveto time over members (1 = linear), smallest to largest group",
        lambda r: _exponent(r, "in-process", "group", "members", "seconds"),
        "max",
        1.2,
        "slope",
        (("in-process", "group"),),
    ),
    Target(
        "find-p99",
        "find p99 over the largest registry",
        lambda r: _largest(r, "in-process", "find")["p99_us"] / 1000.0,
        "max",
        10.0,
        "ms",
        (("in-process", "find"),),
    ),
    Target(
        "find-scaling",
        "log-log slope of find p50 over entries (1 = linear), smallest to largest registry",
        lambda r: _exponent(r, "in-process", "find", "entries", "p50_us"),
        "max",
        1.0,
        "slope",
        (("in-process", "find"),),
    ),
    Target(
        "register-rate",
        "registrations over raw TCP per second, largest run",
        lambda r: _largest(r, "gateway", "register")["per_s"],
        "min",
        100.0,
        "/s",
        (("gateway", "register"),),
    ),
    Target(
        "register-scaling",
        "registrations/s at the largest size / at the smallest, same run (1 = flat)",
        lambda r: _largest(r, "gateway", "register")["per_s"] / r["gateway"]["register"]["sizes"][0]["per_s"],
        "min",
        0.8,
        "x",
        (("gateway", "register"),),
    ),
    Target(
        "register-memory",
        "gateway RSS per member registered over raw TCP (live connection), largest run",
        lambda r: _largest(r, "gateway", "register")["kib_per_member"],
        "max",
        64.0,
        "KiB",
        (("gateway", "register"),),
    ),
)


#: SSE fan-out against gRPC Listen fan-out on one gateway: JSON text per event and one HTTP
#: connection per client cost more than protobuf over a few HTTP/2 connections; within these
#: bounds a browser is served about as well as a gRPC client (figures in docs/performance.md).
SSE_FANOUT_BOUND = 0.5
SSE_LATENCY_BOUND = 2.0


def _tls(results: Results, way: str, call: str) -> float:
    return float(results["gateway"]["tls"][way][call]["throughput_per_s"])


TARGETS += (
    Target(
        "tls-unary",
        "unary Gets/s with mTLS and a bearer token (checked, one rule) / plaintext, both on the gateway",
        lambda r: _tls(r, "mtls-token", "unary") / _tls(r, "plaintext", "unary"),
        "min",
        0.5,
        "x",
        (("gateway", "tls"),),
    ),
    Target(
        "tls-session",
        "Gets/s over a Session with mTLS and a bearer token / plaintext, both on the gateway",
        lambda r: _tls(r, "mtls-token", "session") / _tls(r, "plaintext", "session"),
        "min",
        0.5,
        "x",
        (("gateway", "tls"),),
    ),
)


def _storage(results: Results, size: str, op: str) -> float:
    return float(results["gateway"]["storage"]["sizes"][size][f"{op}_ratio"])


# A Set is bounded by the disk (two fsyncs), so the gateway's share of it can be held to a small
# factor; a Get of a cached file is a memory copy beside a gRPC round trip, so its ratio is shown
# in table (j) but not judged (the cost of a unary call: docs/performance.md).
TARGETS += (
    Target(
        "storage-set-1k",
        "Set of a 1 KiB file through the gateway / an atomic write (temp, fsync, rename, fsync), p50",
        lambda r: _storage(r, "1k", "set"),
        "max",
        5.0,
        "x",
        (("gateway", "storage"),),
    ),
    Target(
        "storage-set-1m",
        "Set of a 1 MiB text file through the gateway / an atomic write (temp, fsync, rename, fsync), p50",
        lambda r: _storage(r, "1m", "set"),
        "max",
        8.0,
        "x",
        (("gateway", "storage"),),
    ),
)


def _sse(results: Results, way: str, figure: str) -> float:
    data: dict[str, Any] = results["gateway"]["sse"][way]
    if figure.endswith("_us"):
        return float(data["latency"][figure])
    return float(data[figure])


TARGETS += (
    Target(
        "sse-fanout",
        "events/s to SSE clients / to gRPC Listen streams, same subscribers, property and gateway",
        lambda r: _sse(r, "sse", "events_per_s") / _sse(r, "grpc", "events_per_s"),
        "min",
        SSE_FANOUT_BOUND,
        "x",
        (("gateway", "sse"),),
    ),
    Target(
        "sse-latency-p50",
        "Set-to-delivery p50, SSE / gRPC Listen, in the same run",
        lambda r: _sse(r, "sse", "p50_us") / _sse(r, "grpc", "p50_us"),
        "max",
        SSE_LATENCY_BOUND,
        "x",
        (("gateway", "sse"),),
    ),
    Target(
        "sse-latency-p99",
        "Set-to-delivery p99, SSE / gRPC Listen, in the same run",
        lambda r: _sse(r, "sse", "p99_us") / _sse(r, "grpc", "p99_us"),
        "max",
        SSE_LATENCY_BOUND,
        "x",
        (("gateway", "sse"),),
    ),
)


#: rosbridge fan-out against gRPC Listen fan-out on one gateway: like SSE, JSON text per message and
#: one connection per client, plus WebSocket framing; held to SSE's bounds (figures in
#: docs/performance.md).
ROSBRIDGE_FANOUT_BOUND = SSE_FANOUT_BOUND
ROSBRIDGE_LATENCY_BOUND = SSE_LATENCY_BOUND


def _rosbridge(results: Results, way: str, figure: str) -> float:
    data: dict[str, Any] = results["gateway"]["rosbridge"][way]
    if figure.endswith("_us"):
        return float(data["latency"][figure])
    return float(data[figure])


TARGETS += (
    Target(
        "rosbridge-fanout",
        "events/s to rosbridge subscribers / to gRPC Listen streams, same subscribers, property and gateway",
        lambda r: _rosbridge(r, "rosbridge", "events_per_s") / _rosbridge(r, "grpc", "events_per_s"),
        "min",
        ROSBRIDGE_FANOUT_BOUND,
        "x",
        (("gateway", "rosbridge"),),
    ),
    Target(
        "rosbridge-latency-p50",
        "Set-to-delivery p50, rosbridge / gRPC Listen, in the same run",
        lambda r: _rosbridge(r, "rosbridge", "p50_us") / _rosbridge(r, "grpc", "p50_us"),
        "max",
        ROSBRIDGE_LATENCY_BOUND,
        "x",
        (("gateway", "rosbridge"),),
    ),
)

TARGETS += (
    # A bare in-process Set is the cheapest call there is (a few µs, no I/O); a transition also
    # selects, exits, enters, evaluates a guard and an assignment and queues an event. Bound: one
    # transition with its Set costs at most 50 bare Sets (still several times less than one gRPC Set).
    Target(
        "statemachine",
        "chart transitions/s (each Sets an in-process property) / bare Sets/s on the same service",
        lambda r: (
            _get(r, "in-process", "statemachine", "transitions_per_s")
            / _get(r, "in-process", "statemachine", "bare_sets_per_s")
        ),
        "min",
        0.02,
        "x",
        (("in-process", "statemachine"),),
    ),
)


def _scheduler_ratio(r: Results) -> float:
    sizes = r["in-process"]["scheduler"]["sizes"]
    largest = max(sizes, key=lambda d: d["entries"])
    return float(largest["request_p50_us"] / largest["find_p50_us"])


TARGETS += (
    # A plain ``find`` over the same registry is the registry's cheapest look-up of candidates
    # (numpy over type, state and location); a decision also ranks by cost and QoS, covers the
    # capability set, applies the rules and grants a licence. Bound: at most 5 finds' worth at the
    # largest size (10,000 entries in a full run).
    Target(
        "scheduler",
        "scheduler request p50 / registry find p50, same registry, largest size",
        _scheduler_ratio,
        "max",
        5.0,
        "x",
        (("in-process", "scheduler"),),
    ),
)


def _camera(results: Results, key: str) -> float:
    return float(results["gateway"]["camera"][key])


TARGETS += (
    # The issue's anchor: a remote driver's video, 30 frames/s of 640x480 JPEG to 10 viewers, with
    # the gateway (rendering and encoding included: the camera runs in it) under one core.
    Target(
        "camera-fps",
        "frames/s received by the slowest of 10 gRPC Listeners on a 640x480 camera at 30 Hz",
        lambda r: _camera(r, "fps_min"),
        "min",
        29.0,
        "fps",
        (("gateway", "camera"),),
    ),
    Target(
        "camera-cores",
        "gateway CPU while serving them (render, encode and 10 streams), cores",
        lambda r: _camera(r, "gateway_cores"),
        "max",
        1.0,
        "cores",
        (("gateway", "camera"),),
    ),
)


TARGETS += (
    # The recorder is off to the side: a recording of 10,000 changes a second should cost the
    # gateway little beside not recording (docs/recording.md, docs/performance.md).
    Target(
        "recording-cpu",
        "gateway CPU recording 100 properties at 100 Hz / not recording, same run",
        lambda r: float(r["gateway"]["recording"]["ratio"]),
        "max",
        1.10,
        "x",
        (("gateway", "recording"),),
    ),
)


def _fusion_scaling(r: Results) -> float:
    sizes = r["in-process"]["fusion"]["sizes"]
    smallest = min(sizes, key=lambda d: d["markers"])
    largest = max(sizes, key=lambda d: d["markers"])
    return float(largest["us_per_observation"] / smallest["us_per_observation"])


TARGETS += (
    # The environment model associates through a spatial hash: an observation looks at the 3×3
    # cells around it, whatever the number of markers, so its cost should stay flat from 100 to
    # 10,000 markers (a scan of every marker grows a hundredfold). Bound: at most 3× (cache
    # misses of a larger table, and the machine's noise).
    Target(
        "fusion-scaling",
        "environment model µs per observation at the largest size / at the smallest (100 markers)",
        _fusion_scaling,
        "max",
        3.0,
        "x",
        (("in-process", "fusion"),),
    ),
)


TARGETS += (
    Target(
        "metrics-unary",
        "unary Get throughput, gateway with metrics / without (median of paired batches, same run)",
        lambda r: float(r["gateway"]["metrics"]["ratio"]),
        "min",
        0.95,
        "x",
        (("gateway", "metrics"),),
    ),
)


def _one_at_a_time(results: Results, server: str, way: str, key: str = "p50_us") -> float:
    return float(results[server]["sequential"]["ways"][way]["latency"][key])


def each_round_ratios(results: Results, part: str, key: str) -> list[float]:
    """Gateway / bare server of one top-level figure, round by round (the servers take turns in a round)."""
    gateway = results["gateway"][part].get("each_round", [results["gateway"][part]])
    bare = results["baseline"][part].get("each_round", [results["baseline"][part]])
    return [float(g[key]) / float(b[key]) for g, b in zip(gateway, bare, strict=True)]


def _proxy_allowance(results: Results) -> float:
    """Session Get p50 through the TCP proxy / (grpc.aio's stream floor + 2 × the direct round trip)."""
    direct = _line(results, "direct", "1")["latency"]["p50_us"]
    through = _line(results, "gateway-session", "1")["latency"]["p50_us"]
    return float(through) / (_one_at_a_time(results, "baseline", "echo") + 2 * float(direct))


#: The floors, the unary tax, fan-out, the proxy path and memory, each against what the same run measured
#: (docs/performance.md, "Floors and peers"). Every figure is judged in one run; the unary ones in every
#: round of it, not only the best.
TARGETS += (
    Target(
        "session-floor-p50",
        "Get p50 one at a time over the gateway's Session / over the bare server's bidirectional echo",
        lambda r: _one_at_a_time(r, "gateway", "session") / _one_at_a_time(r, "baseline", "echo"),
        "max",
        1.05,
        "x",
        (("gateway", "sequential"), ("baseline", "sequential")),
    ),
    Target(
        "session-floor-p99",
        "Get p99 one at a time over the gateway's Session / the bare server's echo p50",
        lambda r: _one_at_a_time(r, "gateway", "session", "p99_us") / _one_at_a_time(r, "baseline", "echo"),
        "max",
        2.0,
        "x",
        (("gateway", "sequential"), ("baseline", "sequential")),
    ),
    Target(
        "unary-p50-rounds",
        "unary Get p50 one at a time, gateway / bare server, the worst round",
        lambda r: max(each_round_ratios(r, "sequential", "unary_p50_us")),
        "max",
        1.10,
        "x",
        (("gateway", "sequential"), ("baseline", "sequential")),
    ),
    Target(
        "unary-inflight-rounds",
        "unary Gets/s with 8 in flight, gateway / bare server, the worst round",
        lambda r: min(each_round_ratios(r, "unary", "throughput_per_s")),
        "min",
        0.90,
        "x",
        (("gateway", "unary"), ("baseline", "unary")),
    ),
    _ratio(
        "fanout-unbatched",
        "Listen events/s to 100 streams, one-by-one, gateway / bare server",
        top=("gateway", "listen"),
        bottom=("baseline", "listen"),
        key="events_per_s",
        kind="min",
        bound=1.0,
    ),
    _ratio(
        "fanout-batched-10x",
        "Listen events/s to 100 streams, bursts (gateway batches), gateway / bare server",
        top=("gateway", "batched"),
        bottom=("baseline", "batched"),
        key="events_per_s",
        kind="min",
        bound=10.0,
    ),
    Target(
        "fanout-paced-p50",
        "Set-to-delivery p50 to 100 streams with paced Sets, gateway / bare server",
        lambda r: (
            float(r["gateway"]["paced"]["latency"]["p50_us"])
            / float(r["baseline"]["paced"]["latency"]["p50_us"])
        ),
        "max",
        1.0,
        "x",
        (("gateway", "paced"), ("baseline", "paced")),
    ),
    Target(
        "proxy-session-p50",
        "Get p50 over a Session through the TCP proxy / (the echo floor's p50 + 2 × the direct line p50)",
        _proxy_allowance,
        "max",
        1.0,
        "x",
        (("gateway-session", "line"), ("direct", "line"), ("baseline", "sequential")),
    ),
    Target(
        "session-listen-memory",
        "gateway RSS per idle Listen carried inside a Session",
        lambda r: _get(r, "gateway", "memory_session", "per_stream_kib"),
        "max",
        2.0,
        "KiB",
        (("gateway", "memory_session"),),
    ),
)


def _cores(results: Results) -> dict[str, Any]:
    """The run of part (t) the cores target judges: K=4 on a machine with 4 free cores, else K=2."""
    cores = results["cluster"]["cores"]
    return next(size for size in cores["sizes"] if size["gateways"] == cores["judged_gateways"])


TARGETS += (
    Target(
        "cluster-cores",
        "Listen events/s from K gateway processes (K-1 forwarding from the first) / from one; "
        "K=4 >= 3 x with 4 free cores, else K=2 >= 1.6 x",
        lambda r: float(_cores(r)["ratio"]),
        "min",
        1.6,
        "x",
        (("cluster", "cores"),),
        bound_of=lambda r: float(r["cluster"]["cores"]["judged_bound"]),
    ),
    Target(
        "cluster-register-rate",
        "registrations/s over raw TCP, spread across 4 gateways sharing a registry in etcd",
        lambda r: _get(r, "cluster", "registry", "register_per_s"),
        "min",
        100.0,
        "/s",
        (("cluster", "registry"),),
    ),
    # A forwarded Get is the local one plus one more gateway hop of the same kind: at most about 2 x,
    # and some room for a loaded machine.
    Target(
        "cluster-forwarded-get",
        "Get p50 through a gateway that forwards to the device's owner / on the owner, same run",
        lambda r: _get(r, "cluster", "registry", "forwarded_ratio"),
        "max",
        2.5,
        "x",
        (("cluster", "registry"),),
    ),
)


def evaluate(results: Results) -> list[dict[str, Any]]:
    """Each target's figure, bound and verdict (PASS, FAIL, or why it could not be judged)."""
    verdicts = []
    for target in TARGETS:
        verdict: dict[str, Any] = {
            "name": target.name,
            "description": target.description,
            "bound": target.bound,
            "kind": target.kind,
            "unit": target.unit,
            "figure": None,
        }
        missing = [f"{s} {p}" for s, p in target.needs if p not in results.get(s, {})]
        failed = [f"{s} {p}" for s, p in target.needs if "error" in results.get(s, {}).get(p, {})]
        incomplete = [
            f"{s} {p}" for s, p in target.needs if results.get(s, {}).get(p, {}).get("complete") is False
        ]
        if missing:
            verdict["verdict"] = "NOT RUN (" + ", ".join(missing) + ")"
        elif failed:
            verdict["verdict"] = "FAIL (error in " + ", ".join(failed) + ")"
        else:
            try:
                figure = target.figure(results)
            except (ZeroDivisionError, KeyError, IndexError, ValueError):
                figure = math.nan
            verdict["figure"] = round(figure, 3)
            bound = target.bound if target.bound_of is None else target.bound_of(results)
            verdict["bound"] = bound
            ok = figure >= bound if target.kind == "min" else figure <= bound
            verdict["verdict"] = "PASS" if ok else "FAIL"
            if incomplete:
                verdict["verdict"] += " (incomplete: " + ", ".join(incomplete) + ")"
        verdicts.append(verdict)
    return verdicts


def _fmt(value: Any, digits: int = 0) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:,.{digits}f}"
    return str(value)


def _table(out: TextIO, title: str, header: list[str], rows: list[list[str]]) -> None:
    full = [row for row in rows if len(row) == len(header)]
    widths = [max([len(h), *(len(r[i]) for r in full)]) for i, h in enumerate(header)]

    def line(cells: list[str]) -> str:
        return "  " + "  ".join(
            c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(cells, widths, strict=False))
        )

    print(f"\n{title}", file=out)
    print(line(header), file=out)
    for row in rows:
        print(line(row) if len(row) == len(header) else "  " + "  ".join(row), file=out)


def _rows(results: Results, part: str, cells: Callable[[dict[str, Any]], list[str]]) -> list[list[str]]:
    rows = []
    for server, parts in results.items():
        if part not in parts:
            continue
        data = parts[part]
        if "error" in data:
            rows.append([server, "error: " + data["error"].splitlines()[0][:60]])
        else:
            rows.append([server, *cells(data)])
    return rows


def print_report(out: TextIO, info: dict[str, Any], results: Results, verdicts: list[dict[str, Any]]) -> None:
    """Print the machine, one table per part and the ratio lines."""
    print(
        f"machine: {info['cpu_model']}, {info['logical_cores']} cores ({info['usable_cores']} usable), "
        f"{info['memory_gib']} GiB; {info['os']}; {info['python']}; grpcio {info['grpcio']}; "
        f"protobuf {info['protobuf']}; load average at start {info['load_average_at_start']}",
        file=out,
    )

    def unary(d: dict[str, Any]) -> list[str]:
        lat, win = d["latency"], d["window"]
        return [
            f"{d['done']:,}",
            _fmt(d["throughput_per_s"]),
            _fmt(lat["p50_us"]),
            _fmt(lat["p99_us"]),
            _fmt(d["server_cpu_us_per_call"]),
            f"{win['server_busy']:.0%}",
            f"{win['client_busy']:.0%}",
            str(d["errors"]),
        ]

    rows = _rows(results, "unary", unary)
    if rows:
        first = next(
            iter(p["unary"] for p in results.values() if "unary" in p and "inflight" in p["unary"]), {}
        )
        _table(
            out,
            f"(a) unary Get, {first.get('inflight', '?')} calls in flight",
            [
                "server",
                "calls",
                "Gets/s",
                "p50 µs",
                "p99 µs",
                "srv CPU µs/call",
                "srv busy",
                "load busy",
                "errors",
            ],
            rows,
        )

    def session(d: dict[str, Any]) -> list[str]:
        lat, win = d["latency"], d["window"]
        return [
            f"{d['done']:,}",
            _fmt(d["throughput_per_s"]),
            _fmt(lat["p50_us"]),
            _fmt(lat["p99_us"]),
            _fmt(d["server_cpu_us_per_get"], 1),
            _fmt(d["replies_per_response"], 1),
            f"{win['server_busy']:.0%}",
            f"{win['client_busy']:.0%}",
            str(d["errors"]),
        ]

    rows = _rows(results, "session", session)
    if rows:
        first = next(iter(p["session"] for p in results.values() if "batch" in p.get("session", {})), {})
        _table(
            out,
            f"(b) Gets over Session, {first.get('batch', '?')} per message, "
            f"{first.get('window_batches', '?')} messages unanswered at most",
            [
                "server",
                "Gets",
                "Gets/s",
                "p50 µs",
                "p99 µs",
                "srv CPU µs/Get",
                "replies/msg",
                "srv busy",
                "load busy",
                "errors",
            ],
            rows,
        )

    def listen(d: dict[str, Any]) -> list[str]:
        lat, win = d["latency"], d["window"]
        return [
            f"{d['events']:,}/{d['expected_events']:,}",
            f"{d['conflated']:,}",
            _fmt(d["events_per_message"], 2),
            _fmt(d["events_per_s"]),
            _fmt(d["sets_per_s"]),
            _fmt(lat["p50_us"]),
            _fmt(lat["p99_us"]),
            _fmt(d["server_cpu_us_per_event"], 1),
            f"{win['server_busy']:.0%}",
            f"{win['client_busy']:.0%}",
        ]

    header = [
        "server",
        "events",
        "conflated",
        "events/msg",
        "events/s",
        "Sets/s",
        "p50 µs",
        "p99 µs",
        "srv CPU µs/event",
        "srv busy",
        "load busy",
    ]
    for part, label in (
        ("listen", "(c) Listen fan-out, one-by-one"),
        ("batched", "(c) Listen fan-out, batched"),
        ("paced", "(r) Listen fan-out, paced"),
    ):
        rows = _rows(results, part, listen)
        if rows:
            first = next(iter(p[part] for p in results.values() if "subscribers" in p.get(part, {})), {})
            _table(
                out,
                f"{label}: {first.get('subscribers', '?')} subscribers on {first.get('properties', '?')} "
                f"propert{'y' if first.get('properties') == 1 else 'ies'}, {first.get('sets', '?')} Sets in "
                f"bursts of {first.get('burst', '?')}, {first.get('set_rate_per_s', '?')}",
                header,
                rows,
            )

    def memory(d: dict[str, Any]) -> list[str]:
        return [
            f"{d['opened']:,}",
            str(d["channels"]),
            _fmt(d["rss_before_mib"], 1),
            _fmt(d["rss_after_mib"], 1),
            _fmt(d["rss_after_close_mib"], 1),
            _fmt(d["per_stream_kib"], 1),
        ]

    rows = _rows(results, "memory", memory)
    rows += [
        [f"{row[0]} (Listens in Sessions)", *row[1:]] for row in _rows(results, "memory_session", memory)
    ]
    if rows:
        _table(
            out,
            "(d) idle Listen streams",
            [
                "server",
                "Listens",
                "channels",
                "RSS before MiB",
                "RSS open MiB",
                "RSS closed MiB",
                "KiB/stream",
            ],
            rows,
        )

    _issue_tables(out, results)
    _one_at_a_time_table(out, results)
    _peer_tables(out, results)

    print("", file=out)
    for v in verdicts:
        sign = ">=" if v["kind"] == "min" else "<="
        figure = "n/a" if v["figure"] is None else f"{v['figure']:.2f} {v['unit']}"
        print(
            f"ratio {v['name']:<21} {figure:>10}   target {sign} {v['bound']:g} {v['unit']:<4} "
            f"{v['verdict']}   ({v['description']})",
            file=out,
        )


def save_json(path: str, payload: dict[str, Any]) -> None:
    """Write the whole run (machine, command, configuration, results, verdicts) to ``path``."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(payload, indent=2, allow_nan=True) + "\n")


def command_line() -> str:
    return " ".join([Path(sys.executable).name, "-m", "bench", *sys.argv[1:]])


def _error_row(label: str, data: dict[str, Any]) -> list[str]:
    return [label, "error: " + str(data["error"]).splitlines()[0][:60]]


def _issue_tables(out: TextIO, results: Results) -> None:
    """Tables of parts (e)-(h): the line protocol, groups, find, registration over raw TCP."""
    rows: list[list[str]] = []
    for way, label in (
        ("direct", "line protocol, direct"),
        ("gateway", "gRPC via gateway proxy"),
        ("gateway-session", "gRPC Session via gw proxy"),
        ("session-floor", "gRPC Session, in-process"),
        ("bare-session", "gRPC Session, bare server"),
    ):
        data = results.get(way, {}).get("line")
        if data is None:
            continue
        if "error" in data:
            rows.append(_error_row(label, data))
            continue
        for inflight, d in sorted(data["inflight"].items(), key=lambda item: int(item[0])):
            lat = d["latency"]
            rows.append(
                [
                    label,
                    inflight,
                    f"{d['done']:,}",
                    _fmt(d["throughput_per_s"]),
                    _fmt(lat["p50_us"]),
                    _fmt(lat["p99_us"]),
                    _fmt(d["device_cpu_us_per_call"]),
                    _fmt(d["gateway_cpu_us_per_call"]) if way != "direct" else "-",
                    f"{d['client_busy']:.0%}",
                    str(d["errors"]),
                ]
            )
    if rows:
        prop = next(
            (
                results[w]["line"].get("property", "?")
                for w in ("direct", "gateway", "gateway-session")
                if "line" in results.get(w, {})
            ),
            "?",
        )
        _table(
            out,
            f"(e) Get of {prop} on a line-protocol device over raw TCP: straight vs through the gateway",
            [
                "path",
                "in flight",
                "calls",
                "Gets/s",
                "p50 µs",
                "p99 µs",
                "device CPU µs/call",
                "gw CPU µs/call",
                "load busy",
                "errors",
            ],
            rows,
        )

    def sized(part: str, cells: Callable[[dict[str, Any]], list[str]]) -> list[list[str]]:
        found: list[list[str]] = []
        for server, parts in results.items():
            data = parts.get(part)
            if data is None:
                continue
            if "error" in data:
                found.append(_error_row(server, data))
                continue
            found += [[server, *cells(d)] for d in data["sizes"]]
            found += [[server, f"{n:,}", "skipped (time limit)"] for n in data.get("skipped", [])]
        return found

    rows = sized(
        "group",
        lambda d: [
            f"{d['members']:,}",
            f"{d['accepted']:,}",
            _fmt(1000 * d["seconds"], 1),
            _fmt(d["us_per_member"], 1),
        ],
    )
    if rows:
        _table(
            out,
            "(f) group behaviors.moveto (circle) on N simulated in-process members, until all accepted",
            ["where", "members", "accepted", "ms", "µs/member"],
            rows,
        )
    rows = sized(
        "find",
        lambda d: [
            f"{d['entries']:,}",
            f"{d['indexed']:,}",
            f"{d['queries']:,}",
            _fmt(d["p50_us"]),
            _fmt(d["p99_us"]),
            _fmt(d["max_us"]),
            _fmt(d["matches_mean"], 2),
        ],
    )
    if rows:
        _table(
            out,
            "(g) registry find type=mobile_robot near=(x y 0) radius=3, N entries",
            ["where", "entries", "indexed", "queries", "p50 µs", "p99 µs", "max µs", "found/query"],
            rows,
        )
    rows = sized(
        "register",
        lambda d: [
            f"{d['members']:,}",
            str(d["farms"]),
            f"{d['registered']:,}",
            _fmt(d["seconds"], 2),
            _fmt(d["per_s"]),
            _fmt(d["set_p50_ms"], 1),
            _fmt(d["set_p99_ms"], 1),
            _fmt(d["gateway_cpu_us_per_member"]),
            _fmt(d["gateway_idle_cores"], 2),
            _fmt(d["rss_before_mib"], 1),
            _fmt(d["rss_after_mib"], 1),
            _fmt(d["kib_per_member"], 1),
            f"{d['gateway_fds_before']}→{d['gateway_fds_after']}",
            f"{d['fd_limits']['soft']}/{d['fd_limits']['hard']}",
        ],
    )
    if rows:
        concurrency = next(
            (
                p["register"]["sizes"][0]["concurrency"]
                for p in results.values()
                if p.get("register", {}).get("sizes")
            ),
            "?",
        )
        _table(
            out,
            f"(h) members registered over raw TCP by Set on registry services.<name>, "
            f"{concurrency} Sets in flight",
            [
                "server",
                "members",
                "farms",
                "registered",
                "s",
                "per s",
                "Set p50 ms",
                "Set p99 ms",
                "gw CPU µs/member",
                "gw cores at rest",
                "RSS before MiB",
                "RSS after MiB",
                "KiB/member",
                "gw fds",
                "fd soft/hard",
            ],
            rows,
        )
    tls = results.get("gateway", {}).get("tls")
    if tls and "error" not in tls:
        rows = [
            [
                way,
                call,
                f"{tls[way][call]['throughput_per_s']:,.0f}",
                _fmt(tls[way][call]["latency"]["p50_us"]),
                _fmt(tls[way][call]["latency"]["p99_us"]),
            ]
            for way in ("plaintext", "mtls-token")
            for call in ("unary", "session")
        ]
        _table(
            out,
            "(i) the cost of mTLS and a bearer token: unary Gets (8 in flight) and Gets over one Session",
            ["way", "call", "Gets/s", "p50 µs", "p99 µs"],
            rows,
        )
    storage = results.get("gateway", {}).get("storage")
    if storage and "error" not in storage:
        rows = []
        for size, d in storage["sizes"].items():
            for op in ("get", "set"):
                gw, plain = d[f"gateway_{op}"], d[f"plain_{op}"]
                rows.append(
                    [
                        size,
                        op.capitalize(),
                        f"{gw['done']:,}",
                        _fmt(gw["p50_us"]),
                        _fmt(gw["p99_us"]),
                        _fmt(plain["p50_us"], 1),
                        _fmt(plain["p99_us"], 1),
                        _fmt(d[f"{op}_ratio"], 1),
                    ]
                )
        _table(
            out,
            "(j) storage: Get and Set of a file through the gateway, one at a time, beside plain file I/O",
            ["file", "call", "calls", "gw p50 µs", "gw p99 µs", "plain p50 µs", "plain p99 µs", "ratio"],
            rows,
        )
    elif storage:
        _table(out, "(j) storage", ["where", "figures"], [_error_row("gateway", storage)])
    _sse_table(out, results)
    _rosbridge_table(out, results)
    _statemachine_table(out, results)
    _scheduler_table(out, results)
    _camera_table(out, results)
    _recording_table(out, results)
    _fusion_table(out, results)
    _metrics_table(out, results)
    _cores_table(out, results)
    _cluster_registry_table(out, results)


def _cores_table(out: TextIO, results: Results) -> None:
    cores = results.get("cluster", {}).get("cores")
    if not cores:
        return
    if "error" in cores:
        _table(
            out,
            "(t) Listen fan-out from K gateway processes",
            ["where", "error"],
            [_error_row("cluster", cores)],
        )
        return
    runs = [*cores["sizes"], *(d for sizes in cores["other_listeners"].values() for d in sizes)]
    rows = [
        [
            str(d["gateways"]),
            d["listener"],
            f"{d['streams']:,}",
            str(d["listener_processes"]),
            f"{d['events_per_s']:,.0f}",
            _fmt(d["ratio"], 2),
            f"{d['conflated']:,}",
            f"{d['sets_per_s']:,.0f}",
            " ".join(f"{c:.2f}" for c in d["gateway_cores"]),
            _fmt(d["gateway_cpu_us_per_event"], 1),
            _fmt(d["listener_cores"], 2),
            _fmt(d["listener_cpu_us_per_event"], 1),
            str(d["rounds_events_per_s"]),
        ]
        for d in runs
    ]
    rows += [[f"note: {note}"] for note in cores["listener_notes"]]
    _table(
        out,
        "(t) Listen fan-out from K gateway processes, K-1 forwarding bench/value from the first (grpc://); "
        f"{cores['cpu_count']} cores, {cores['usable_cores']} usable, {cores['free_cores']} free "
        f"(load average {cores['load_average']}); judged: the {cores['listener']} listeners",
        [
            "K",
            "listener",
            "streams",
            "listener procs",
            "events/s",
            "x one",
            "conflated",
            "Sets/s",
            "gateway cores",
            "gw CPU µs/event",
            "listener cores",
            "lst CPU µs/event",
            "rounds",
        ],
        rows,
    )


def _cluster_registry_table(out: TextIO, results: Results) -> None:
    cluster = results.get("cluster", {}).get("registry")
    if not cluster:
        return
    title = "(t) devices across gateways sharing a registry in etcd"
    if "error" in cluster:
        _table(out, title, ["where", "error"], [_error_row("cluster", cluster)])
        return
    d = cluster
    _table(
        out,
        f"{title}: {d['devices']:,} devices, {d['gateways']} gateways, lease {d['lease_s']:g} s",
        ["figure", "value"],
        [
            ["registered", f"{d['registered']:,} at {d['register_per_s']:,.0f}/s ({d['register_s']:.1f} s)"],
            ["listed by every gateway after", f"{d['visible_everywhere_s']:.1f} s ({d['listed_by_each']})"],
            *_at_rest_rows(d.get("at_rest")),
            ["find p50 / p99", f"{d['find_p50_ms']:.2f} / {d['find_p99_ms']:.2f} ms ({d['find_queries']:,})"],
            ["Get p50 local / forwarded", f"{d['local_get_p50_us']:,} / {d['forwarded_get_p50_us']:,} µs"],
            [
                "killed gateway's devices owned again",
                f"{d['owned_again']:,} of {d['killed_gateway_devices']:,}: "
                f"first {d.get('owned_again_first_s', math.nan):.2f} s, "
                f"p50 {d['owned_again_p50_s']:.2f} s, all {d['owned_again_s']:.2f} s after SIGKILL",
            ],
            [
                "killed gateway's devices answering again",
                f"{d['answered_again']:,} of {d['killed_gateway_devices']:,}: "
                f"first {d.get('failover_first_s', math.nan):.2f} s, "
                f"p50 {d['failover_p50_s']:.2f} s, all {d['failover_s']:.2f} s after SIGKILL",
            ],
            ["listed after the failover", f"{d['listed_after_failover']:,}"],
            [
                "owner Listens that ended (opened again)",
                f"{d['owner_streams_ended']}"
                + (f" (first: {d['owner_streams_first_end'][:60]})" if d["owner_streams_ended"] else ""),
            ],
        ],
    )


def _at_rest_rows(rest: dict[str, Any] | None) -> list[list[str]]:
    """Rows of (t)'s settled cluster: what each gateway holds at rest (absent from older results)."""
    if not rest:
        return []

    def each(key: str) -> str:
        return " / ".join(f"{v:,}" if isinstance(v, int) else f"{v:g}" for v in rest[key])

    return [
        ["every device up and typed everywhere after", f"{rest['settled_s']:.1f} s"],
        ["RSS per gateway (MiB)", each("rss_mib")],
        ["RSS added per service served (KiB)", each("rss_kib_per_service")],
        ["open files per gateway (added)", f"{each('fds')} ({each('fds_added')})"],
        ["TCP connections to the other gateways", each("connections_to_other_gateways")],
        [f"CPU at rest over {rest['rest_s']:g} s (% of a core)", each("rest_cpu_percent")],
    ]


def _one_at_a_time_table(out: TextIO, results: Results) -> None:
    """Table (q), and the unary ratios of every round (a target must hold in each)."""
    rows: list[list[str]] = []
    for server, parts in results.items():
        data = parts.get("sequential")
        if data is None:
            continue
        if "error" in data:
            rows.append(_error_row(server, data))
            continue
        for way, d in data["ways"].items():
            lat = d["latency"]
            rows.append(
                [
                    server,
                    "echo (the floor)" if way == "echo" else way,
                    f"{d['done']:,}",
                    _fmt(d["throughput_per_s"]),
                    _fmt(lat["p50_us"]),
                    _fmt(lat["p99_us"]),
                    _fmt(d["server_cpu_us_per_call"]),
                    str(d["errors"]),
                ]
            )
    if not rows:
        return
    _table(
        out,
        "(q) Get one at a time: unary, over one Session stream (one request a message), and the bare "
        "server's bidirectional echo",
        ["server", "way", "calls", "Gets/s", "p50 µs", "p99 µs", "srv CPU µs/call", "errors"],
        rows,
    )
    for label, part, key in (
        ("unary Get p50 one at a time", "sequential", "unary_p50_us"),
        ("unary Gets/s with 8 in flight", "unary", "throughput_per_s"),
    ):
        try:
            ratios = each_round_ratios(results, part, key)
        except (KeyError, TypeError, ValueError, ZeroDivisionError):
            continue
        print(
            f"  {label}, gateway / bare server, each round: {', '.join(f'{x:.2f}' for x in ratios)}", file=out
        )


def _peer_tables(out: TextIO, results: Results) -> None:
    """Table (s): each peer's figures; then the gateway's against them, way by way."""
    rows: list[list[str]] = []
    for name, parts in results.items():
        data = parts.get("peers")
        if data is None:
            continue
        if "error" in data:
            rows.append(_error_row(name, data))
            continue
        if "skipped" in data:
            rows.append([name, "skipped: " + data["skipped"]])
            continue
        seq, inflight, fan, paced = data["sequential"], data["unary"], data["listen"], data["paced"]
        rows.append(
            [
                name,
                _fmt(seq["latency"]["p50_us"]),
                _fmt(seq["latency"]["p99_us"]),
                _fmt(inflight["throughput_per_s"]),
                f"{fan['events']:,}/{fan['expected_events']:,}",
                _fmt(fan["events_per_s"]),
                _fmt(fan["latency"]["p50_us"]),
                _fmt(paced["latency"]["p50_us"]),
                _fmt(paced["latency"]["p99_us"]),
                _fmt(inflight["server_cpu_us_per_call"]),
                _fmt(fan["server_cpu_us_per_event"], 1),
            ]
        )
    if not rows:
        return
    first = next((p["peers"] for p in results.values() if "listen" in p.get("peers", {})), None)
    sizes = (
        f"{first['listen']['subscribers']} subscribers, {first['listen']['sets']} Sets unpaced, "
        f"{first['paced']['sets']} at {first['paced']['set_rate_per_s']}/s"
        if first
        else ""
    )
    _table(
        out,
        f"(s) the peers with the same client patterns: Get one at a time and 8 in flight; fan-out, {sizes}",
        [
            "peer",
            "Get p50 µs",
            "Get p99 µs",
            "Gets/s 8 in flight",
            "events",
            "events/s",
            "fan-out p50 µs",
            "paced p50 µs",
            "paced p99 µs",
            "srv CPU µs/Get",
            "srv CPU µs/event",
        ],
        rows,
    )
    peers = sorted(measured_peers(results))
    if not peers:
        return
    comparisons = compare(results)
    _table(
        out,
        "(s) the gateway against the peers, same run: gateway / peer (a ratio below 1 is the gateway's "
        "where lower is better, above 1 where higher is)",
        ["figure", "gateway way", "bare", "gateway", *[c for n in peers for c in (n, f"gw/{n}")]],
        [
            [
                row["figure"],
                row["way"],
                _fmt(row["baseline"]),
                _fmt(row["gateway"]),
                *[
                    cell
                    for n in peers
                    for cell in (_fmt(row["peers"][n]), _fmt(row["gateway_over_peer"][n], 2))
                ],
            ]
            for row in comparisons
        ],
    )


def _metrics_table(out: TextIO, results: Results) -> None:
    metrics = results.get("gateway", {}).get("metrics")
    if not metrics:
        return
    if "error" in metrics:
        _table(out, "(p) metrics", ["where", "figures"], [_error_row("gateway", metrics)])
        return
    rows = [
        [
            way,
            f"{metrics[way]['throughput_per_s']:,.0f}",
            _fmt(metrics[way]["latency"]["p50_us"]),
            _fmt(metrics[way]["latency"]["p99_us"]),
            _fmt(metrics["cpu_us_per_call"][way], 1),
        ]
        for way in ("metrics-on", "metrics-off")
    ]
    _table(
        out,
        "(p) the cost of metrics: unary Gets (8 in flight) on a gateway with and without them",
        ["way", "best Gets/s", "p50 µs", "p99 µs", "server CPU µs/call (median)"],
        rows,
    )
    print(
        f"  ratio of each pair of batches, with / without: {metrics['pair_ratios']}"
        f" (median {metrics['ratio']}; of the best batches {metrics['best_batch_ratio']})",
        file=out,
    )
    print(
        f"  counting one call in-process: {metrics['counting_ns_per_call']} ns,"
        f" {100 * metrics['counting_share']:.2f} % of one core at the Gets/s without metrics",
        file=out,
    )
    print(
        f"  OK Gets the scrape of the gateway with metrics counted: {metrics['scraped_get_calls']:,.0f}",
        file=out,
    )


def _camera_table(out: TextIO, results: Results) -> None:
    camera = results.get("gateway", {}).get("camera")
    if not camera or "error" in camera:
        return
    base = camera["baseline"]
    _table(
        out,
        f"(o) camera: {camera['listeners']} gRPC Listeners on frame, {camera['resolution'][0]}x"
        f"{camera['resolution'][1]} JPEG q{camera['quality']} at {camera['rate_hz']} Hz, "
        f"{camera['window_s']} s; baseline: render+encode alone in this process",
        [
            "fps min",
            "fps mean",
            "frame KiB",
            "MiB/s out",
            "gw cores",
            "gw ms/frame",
            "baseline fps",
            "baseline ms/frame",
        ],
        [
            [
                _fmt(camera["fps_min"], 1),
                _fmt(camera["fps_mean"], 1),
                _fmt(camera["frame_bytes_mean"] / 1024, 1),
                _fmt(camera["mib_per_s"], 1),
                _fmt(camera["gateway_cores"], 2),
                _fmt(camera["gateway_cpu_ms_per_frame"], 2),
                _fmt(base["frames_per_s"]),
                _fmt(base["ms_per_frame"], 2),
            ]
        ],
    )


def _recording_table(out: TextIO, results: Results) -> None:
    recording = results.get("gateway", {}).get("recording")
    if not recording or "error" in recording:
        return
    cores = recording["cores"]
    _table(
        out,
        f"(v) recording: {recording['properties']} properties at {recording['rate_hz']:g} Hz, "
        f"{recording['window_s']} s windows, best of {recording['rounds']}",
        [
            "idle cores",
            "recording cores",
            "one Listen cores",
            "ratio",
            "rec / Listen",
            "writer process cores",
            "events/s",
            "MiB/s",
            "dropped",
        ],
        [
            [
                _fmt(cores["idle"], 3),
                _fmt(cores["recording"], 3),
                _fmt(cores["listen"], 3),
                _fmt(recording["ratio"], 2),
                _fmt(recording["recording_over_listen"], 2),
                _fmt(recording.get("writer_cores"), 3),
                _fmt(recording["events_per_s"]),
                _fmt(recording["mib_per_s"], 2),
                _fmt(recording["dropped"]),
            ]
        ],
    )


def _sse_table(out: TextIO, results: Results) -> None:
    sse = results.get("gateway", {}).get("sse")
    if not sse or "error" in sse:
        return
    rows = []
    for way, label in (("grpc", "gRPC Listen"), ("sse", "Server-Sent Events")):
        d = sse[way]
        lat, win = d["latency"], d["window"]
        rows.append(
            [
                label,
                f"{d['events']:,}/{d['expected_events']:,}",
                f"{d['conflated']:,}",
                _fmt(d["events_per_s"]),
                _fmt(d["sets_per_s"]),
                _fmt(lat["p50_us"]),
                _fmt(lat["p99_us"]),
                _fmt(d["server_cpu_us_per_event"], 1),
                f"{win['server_busy']:.0%}",
                f"{win['client_busy']:.0%}",
            ]
        )
    first = sse["sse"]
    _table(
        out,
        f"(k) fan-out to {first['subscribers']} subscribers on one property of one gateway, "
        f"{first['sets']} Sets: gRPC Listen streams and SSE clients (one HTTP connection each)",
        [
            "way",
            "events",
            "conflated",
            "events/s",
            "Sets/s",
            "p50 µs",
            "p99 µs",
            "srv CPU µs/event",
            "srv busy",
            "load busy",
        ],
        rows,
    )
    idle = sse.get("idle")
    if idle:
        print(
            f"  {idle['streams']} idle SSE streams on a fresh gateway: RSS {idle['rss_before_mib']} → "
            f"{idle['rss_after_mib']} MiB, {idle['per_stream_kib']} KiB per stream",
            file=out,
        )


def _rosbridge_table(out: TextIO, results: Results) -> None:
    part = results.get("gateway", {}).get("rosbridge")
    if not part or "error" in part:
        return
    rows = []
    for way, label in (("grpc", "gRPC Listen"), ("sse", "Server-Sent Events"), ("rosbridge", "rosbridge")):
        d = part[way]
        lat, win = d["latency"], d["window"]
        rows.append(
            [
                label,
                f"{d['events']:,}/{d['expected_events']:,}",
                _fmt(d["events_per_s"]),
                _fmt(d["sets_per_s"]),
                _fmt(lat["p50_us"]),
                _fmt(lat["p99_us"]),
                _fmt(d["server_cpu_us_per_event"], 1),
                f"{win['server_busy']:.0%}",
                f"{win['client_busy']:.0%}",
            ]
        )
    first = part["rosbridge"]
    _table(
        out,
        f"(u) fan-out to {first['subscribers']} subscribers on one property of one gateway, "
        f"{first['sets']} Sets: gRPC Listen streams, SSE clients and rosbridge WebSocket subscribers",
        [
            "way",
            "events",
            "events/s",
            "Sets/s",
            "p50 µs",
            "p99 µs",
            "srv CPU µs/event",
            "srv busy",
            "load busy",
        ],
        rows,
    )
    ros, grpc_, sse = part["rosbridge"], part["grpc"], part["sse"]

    def ratio(top: float, bottom: float) -> str:
        return f"{top / bottom:.2f}" if bottom else "n/a"

    print(
        "  rosbridge / gRPC Listen: events/s "
        f"{ratio(ros['events_per_s'], grpc_['events_per_s'])}, p50 "
        f"{ratio(ros['latency']['p50_us'], grpc_['latency']['p50_us'])}; rosbridge / SSE: events/s "
        f"{ratio(ros['events_per_s'], sse['events_per_s'])}, p50 "
        f"{ratio(ros['latency']['p50_us'], sse['latency']['p50_us'])}",
        file=out,
    )
    trip = part.get("cmd_vel")
    if trip:
        lat = trip["latency"]
        print(
            f"  cmd_vel round trip (publish Twist on rosbridge -> the robot's velocity message back): "
            f"{trip['done']:,}/{trip['trips']:,} trips, p50 {_fmt(lat['p50_us'])} µs, "
            f"p99 {_fmt(lat['p99_us'])} µs",
            file=out,
        )


def _statemachine_table(out: TextIO, results: Results) -> None:
    machine = results.get("in-process", {}).get("statemachine")
    if machine and "error" not in machine:
        _table(
            out,
            "(l) a chart whose every transition Sets an in-process property, beside bare Sets on it",
            ["transitions", "transitions/s", "µs/transition", "bare Sets/s", "µs/bare Set", "complete"],
            [
                [
                    f"{machine['transitions']:,}",
                    f"{machine['transitions_per_s']:,.0f}",
                    _fmt(machine["us_per_transition"], 1),
                    f"{machine['bare_sets_per_s']:,.0f}",
                    _fmt(machine["us_per_bare_set"], 1),
                    str(machine["complete"]),
                ]
            ],
        )


def _scheduler_table(out: TextIO, results: Results) -> None:
    scheduler = results.get("in-process", {}).get("scheduler")
    if scheduler and "error" not in scheduler:
        _table(
            out,
            "(m) scheduler: a request (decision and licence) beside a plain find, same registry",
            [
                "entries",
                "rounds",
                "request p50 µs",
                "request p99 µs",
                "find p50 µs",
                "find p99 µs",
                "ratio p50",
            ],
            [
                [
                    f"{d['entries']:,}",
                    f"{d['rounds']:,}",
                    _fmt(d["request_p50_us"], 1),
                    _fmt(d["request_p99_us"], 1),
                    _fmt(d["find_p50_us"], 1),
                    _fmt(d["find_p99_us"], 1),
                    _fmt(d["ratio_p50"], 2),
                    _fmt(d["first_request_us"], 1),
                ]
                for d in scheduler["sizes"]
            ],
        )


def _fusion_table(out: TextIO, results: Results) -> None:
    fusion = results.get("in-process", {}).get("fusion")
    if fusion and "error" not in fusion:
        _table(
            out,
            "(n) environment model: one observation fused (association and update) beside a bare numpy "
            "distance (baseline) and a numpy scan of every marker",
            [
                "markers",
                "observations",
                "µs/observation",
                "baseline µs",
                "scan µs",
                "ratio to baseline",
                "new markers",
            ],
            [
                [
                    f"{d['markers']:,}",
                    f"{d['observations']:,}",
                    _fmt(d["us_per_observation"], 2),
                    _fmt(d["baseline_us"], 2),
                    _fmt(d["scan_us"], 2),
                    _fmt(d["ratio_to_baseline"], 2),
                    f"{d['created']:,}",
                ]
                for d in fusion["sizes"]
            ],
        )
        if fusion.get("scaling") is not None:
            print(
                f"  µs per observation at the largest size / at the smallest: {fusion['scaling']}", file=out
            )


def _psutil() -> Any:
    # Imported when measuring, so that `python -m bench --help` needs only the runtime packages.
    import psutil  # type: ignore[import-untyped,unused-ignore]

    return psutil
