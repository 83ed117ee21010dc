"""``python -m bench``: measure the gateway beside the bare server and print the ratios.

Each server runs in its own process, one at a time, on 127.0.0.1; this
process is the load generator and drives both with the generated stubs.
Part (d) gets a freshly started server of its own. Parts (e)-(h) start
their own processes (a line-protocol device and a gateway; device farms and
a gateway) or run in this process (groups, find); see their modules. Parts
(q) and (r) take turns with (a)-(c) on the same servers; part (s) starts the
peers' servers, one process each, after them.
"""

from __future__ import annotations

import argparse
import asyncio
import math
import os
import sys
import time
import traceback
from collections.abc import Awaitable, Callable
from typing import Any

from bench import report
from bench.camera import run_camera
from bench.cluster import run_cores
from bench.cluster_listeners import KINDS as LISTENER_KINDS
from bench.cluster_registry import ETCD_MISSING, etcd_binary, measure_registry
from bench.fusion import run_fusion
from bench.groups import run_scaling
from bench.line import WAYS as LINE_WAYS
from bench.line import run_line
from bench.listen import run_listen
from bench.memory import run_memory, run_session_memory
from bench.metrics import run_metrics
from bench.peer_measure import PeerSizes
from bench.peer_ratios import compare as compare_with_peers
from bench.peers import BY_NAME as PEERS_BY_NAME
from bench.peers import run_peer
from bench.recording import run_recording
from bench.register import run_register
from bench.rosbridge import run_rosbridge
from bench.scheduler import run_scheduler
from bench.sequential import run_sequential
from bench.servers import ServerProcess
from bench.session import run_session
from bench.sse import run_sse
from bench.statemachine import run_statemachine
from bench.storage import run_storage
from bench.target import BATCH_PROPERTIES, VALUE_PROPERTY
from bench.tls import run_tls
from bench.unary import run_unary

#: Parts (a)-(d) compare the gateway with the bare server; (e)-(h) are the line protocol and registry parts.
SERVER_PARTS = ("unary", "session", "listen", "batched", "memory")
PARTS = (
    *SERVER_PARTS,
    "line",
    "group",
    "find",
    "register",
    "tls",
    "storage",
    "sse",
    "rosbridge",
    "recording",
    "statemachine",
    "scheduler",
    "camera",
    "fusion",
    "metrics",
    "cluster",
)
#: (q) Gets one at a time beside the bare server's echo floor; (r) Listen fan-out with paced Sets.
SERVER_PARTS += ("sequential", "paced")
#: (s) the peers: ``peers`` is both of them.
PARTS += ("sequential", "paced", "peers", *PEERS_BY_NAME)
#: (t) scale-out: ``cluster`` is both its measurements, the cores and the registry on etcd.
PARTS += ("cluster-cores", "cluster-registry")
SERVERS = {
    "baseline": ["bench.baseline", "--listen", "127.0.0.1:0"],
    "gateway": ["bench.gateway_server", "--listen", "127.0.0.1:0"],
}

#: Sizes of the full run and of ``--quick``.
PROFILES: dict[str, dict[str, Any]] = {
    "full": {
        "calls": 20_000,
        "warmup": 1_000,
        "session_gets": 100_000,
        "subscribers": 100,
        "sets": 2_000,
        "paced_sets": 250,
        "peer_sets": 500,
        "streams": 1_000,
        "time_limit": 60.0,
        "rounds": 2,
        "line_calls": 5_000,
        "group_sizes": (100, 1_000, 10_000),
        "find_sizes": (100, 1_000, 10_000),
        "find_queries": 1_000,
        "register_sizes": (1_000, 10_000),
        "storage_calls": 1_000,
        "transitions": 20_000,
        "scheduler_sizes": (100, 10_000),
        "scheduler_rounds": 1_000,
        "camera_seconds": 10.0,
        "cmd_vel_trips": 1_000,
        "recording_seconds": 5.0,
        "fusion_sizes": (100, 10_000),
        "fusion_observations": 20_000,
        "cluster_gateways": (1, 2, 4),
        "cluster_streams": 400,
        # Enough listener processes that the clients are not what limits the gateways on a larger machine.
        "cluster_listeners": max(4, len(os.sched_getaffinity(0)) // 2),
        "cluster_seconds": 5.0,
        "cluster_devices": 10_000,
        "cluster_queries": 1_000,
    },
    "quick": {
        "calls": 2_000,
        "warmup": 200,
        "session_gets": 10_000,
        "subscribers": 100,
        "sets": 200,
        "paced_sets": 50,
        "peer_sets": 100,
        "streams": 200,
        "time_limit": 15.0,
        "rounds": 1,
        "line_calls": 500,
        "group_sizes": (100, 1_000),
        "find_sizes": (100, 1_000),
        "find_queries": 200,
        "register_sizes": (1_000, 2_000),
        "storage_calls": 200,
        "transitions": 2_000,
        "scheduler_sizes": (100, 10_000),
        "scheduler_rounds": 100,
        "camera_seconds": 3.0,
        "cmd_vel_trips": 200,
        "recording_seconds": 2.0,
        "fusion_sizes": (100, 10_000),
        "fusion_observations": 2_000,
        "cluster_gateways": (1, 2, 4),
        "cluster_streams": 100,
        "cluster_listeners": 2,
        "cluster_seconds": 2.0,
        "cluster_devices": 400,
        "cluster_queries": 200,
    },
}


def _csv(choices: tuple[str, ...]) -> Callable[[str], list[str]]:
    def parse(text: str) -> list[str]:
        names = [name.strip() for name in text.split(",") if name.strip()]
        unknown = [name for name in names if name not in choices]
        if unknown or not names:
            raise argparse.ArgumentTypeError(f"choose from {', '.join(choices)} (comma-separated)")
        return names

    return parse


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError("must be at least 1")
    return value


def _sizes(text: str) -> tuple[int, ...]:
    try:
        sizes = tuple(int(part.replace("_", "")) for part in text.split(",") if part.strip())
    except ValueError:
        sizes = ()
    if not sizes or min(sizes) < 2 or list(sizes) != sorted(set(sizes)):
        raise argparse.ArgumentTypeError(
            "expected increasing sizes of at least 2, comma-separated, e.g. 100,1000"
        )
    return sizes


def _gateway_counts(text: str) -> tuple[int, ...]:
    try:
        counts = tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError:
        counts = ()
    if len(counts) < 2 or counts[0] != 1 or list(counts) != sorted(set(counts)) or counts[-1] > 16:
        raise argparse.ArgumentTypeError(
            "expected increasing numbers of gateways from 1 to at most 16, e.g. 1,2,4"
        )
    return counts


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m bench",
        description="Benchmark the gateway beside a bare grpc.aio server of the same contract: "
        "(a) unary Get, (b) Gets over Session, (c) Listen fan-out one-by-one and batched, "
        "(d) memory per idle Listen stream; (e) Get through the gateway's TCP proxy beside the line "
        "protocol straight to the device; (f) group moveto, (g) registry find, (h) registration over raw "
        "TCP at growing sizes; (i) mTLS and a token; (j) a storage service's Get and Set beside plain file "
        "I/O; (k) Server-Sent-Events fan-out beside gRPC Listen; (l) chart transitions with a Set each; "
        "(m) scheduler decisions; (n) environment model fusion per observation, growing numbers of markers; "
        "(o) camera frames to 10 Listeners and the gateway's CPU; (p) unary Get with and without metrics; "
        "(q) Gets one at a time, unary and over Session, beside the bare server's bidirectional echo "
        "(the floor); (r) Listen fan-out with paced Sets; (s) the peers, OPC UA (asyncua) and Zenoh, "
        "with the same patterns; "
        "(t) Listen fan-out from 1, 2 and 4 gateway processes, the others forwarding from the first, and "
        "devices across 4 gateways sharing a registry in etcd (registration, find, forwarded Get, failover); "
        "(u) rosbridge subscribers beside gRPC Listen and SSE, and a cmd_vel round trip to a robot; "
        "(v) the gateway's CPU recording 100 properties changing at 100 Hz, beside not recording. "
        "Prints figures, ratios and targets.",
    )
    parser.add_argument(
        "--quick", action="store_true", help="small sizes: a smoke run of well under a minute"
    )
    parser.add_argument(
        "--parts",
        type=_csv(PARTS),
        default=list(PARTS),
        help=f"parts to run, comma-separated (default: all of {','.join(PARTS)})",
    )
    parser.add_argument(
        "--servers",
        type=_csv(tuple(SERVERS)),
        default=list(SERVERS),
        help="servers to measure in parts unary..memory, comma-separated (default: baseline,gateway)",
    )
    parser.add_argument("--json", metavar="FILE", help="also save the results as JSON to FILE")
    parser.add_argument("--strict", action="store_true", help="exit with status 1 when a target is missed")
    sizes = parser.add_argument_group("sizes (defaults: full run / --quick)")
    full, quick = PROFILES["full"], PROFILES["quick"]

    def both(key: str) -> str:
        return f"(default {full[key]:,} / {quick[key]:,})"

    sizes.add_argument("--calls", type=_positive, help=f"(a) measured unary Gets {both('calls')}")
    sizes.add_argument("--warmup", type=_positive, help=f"(a, b) calls before measuring {both('warmup')}")
    sizes.add_argument("--inflight", type=_positive, default=8, help="(a) unary calls in flight (default 8)")
    sizes.add_argument("--session-gets", type=_positive, help=f"(b) Gets over Session {both('session_gets')}")
    sizes.add_argument(
        "--session-batch", type=_positive, default=100, help="(b) Gets per message (default 100)"
    )
    sizes.add_argument(
        "--session-window", type=_positive, default=4, help="(b) messages unanswered at most (default 4)"
    )
    sizes.add_argument(
        "--subscribers", type=_positive, help=f"(c, j) Listen and SSE subscribers {both('subscribers')}"
    )
    sizes.add_argument("--sets", type=_positive, help=f"(c, j) Sets made by the setter {both('sets')}")
    sizes.add_argument(
        "--set-rate",
        type=float,
        default=0.0,
        help="(c) Sets per second; 0 = as fast as the server answers, one Set (or burst) at a time "
        "(default 0)",
    )
    sizes.add_argument(
        "--listen-channels",
        type=_positive,
        help="(c) connections for the subscribers (default: 25 per connection)",
    )
    sizes.add_argument(
        "--paced-sets", type=_positive, help=f"(r, s) Sets at --paced-rate {both('paced_sets')}"
    )
    sizes.add_argument(
        "--paced-rate", type=float, default=50.0, help="(r, s) Sets per second when paced (default 50)"
    )
    sizes.add_argument(
        "--peer-sets", type=_positive, help=f"(s) Sets of each peer's unpaced fan-out {both('peer_sets')}"
    )
    sizes.add_argument("--streams", type=_positive, help=f"(d) idle Listen streams {both('streams')}")
    sizes.add_argument(
        "--memory-channels",
        type=_positive,
        help="(d) connections for the streams (default: 50 per connection)",
    )
    sizes.add_argument(
        "--line-calls", type=_positive, help=f"(e) Gets per way and per in-flight count {both('line_calls')}"
    )

    def listed(key: str) -> str:
        return f"(default {','.join(map(str, full[key]))} / {','.join(map(str, quick[key]))})"

    sizes.add_argument("--group-sizes", type=_sizes, help=f"(f) group members {listed('group_sizes')}")
    sizes.add_argument("--find-sizes", type=_sizes, help=f"(g) registry entries {listed('find_sizes')}")
    sizes.add_argument("--find-queries", type=_positive, help=f"(g) queries per size {both('find_queries')}")
    sizes.add_argument(
        "--register-sizes",
        type=lambda text: _sizes(text) if "," in text else (_positive(text),),
        help=f"(h) devices registered over raw TCP {listed('register_sizes')}",
    )
    sizes.add_argument(
        "--register-concurrency",
        type=_positive,
        default=32,
        help="(h) registration Sets in flight (default 32)",
    )
    sizes.add_argument(
        "--storage-calls",
        type=_positive,
        help=f"(j) Gets and Sets of the 1 KiB file each way, a tenth for 1 MiB {both('storage_calls')}",
    )
    sizes.add_argument(
        "--transitions", type=_positive, help=f"(l) chart transitions, each with a Set {both('transitions')}"
    )
    sizes.add_argument(
        "--scheduler-sizes",
        type=_sizes,
        help=f"(m) registry entries the scheduler picks from {listed('scheduler_sizes')}",
    )
    sizes.add_argument(
        "--scheduler-rounds",
        type=_positive,
        help=f"(m) requests (and finds) per size {both('scheduler_rounds')}",
    )
    sizes.add_argument(
        "--camera-seconds",
        type=float,
        help=f"(o) seconds 10 Listeners count a 640x480 30 Hz camera's frames {both('camera_seconds')}",
    )
    sizes.add_argument(
        "--cmd-vel-trips",
        type=_positive,
        help=f"(u) Twists published on cmd_vel, each awaited on velocity {both('cmd_vel_trips')}",
    )
    sizes.add_argument(
        "--recording-seconds",
        type=float,
        help=f"(v) seconds of each window: idle, recording, one Listen {both('recording_seconds')}",
    )
    sizes.add_argument(
        "--fusion-sizes",
        type=_sizes,
        help=f"(n) markers the environment model holds {listed('fusion_sizes')}",
    )
    sizes.add_argument(
        "--fusion-observations",
        type=_positive,
        help=f"(n) observations fused per size {both('fusion_observations')}",
    )
    sizes.add_argument(
        "--cluster-gateways",
        type=_gateway_counts,
        help=f"(t) gateway processes sharing the fan-out, in turn {listed('cluster_gateways')}",
    )
    sizes.add_argument(
        "--cluster-streams", type=_positive, help=f"(t) Listen streams in all {both('cluster_streams')}"
    )
    sizes.add_argument(
        "--cluster-listeners",
        type=_positive,
        help=f"(t) processes that open the Listen streams {both('cluster_listeners')}",
    )
    sizes.add_argument(
        "--cluster-listener",
        type=_csv(LISTENER_KINDS),
        default=["auto"],
        help="(t) the program of the listener processes, comma-separated to compare them in the same "
        "rounds (the first is judged): go (bench/go_listeners, built on first use), python "
        "(bench.fanout_listeners), auto (go where it can be built, else python) (default: auto)",
    )
    sizes.add_argument(
        "--cluster-seconds",
        type=float,
        help=f"(t) seconds the listeners count events {both('cluster_seconds')}",
    )
    sizes.add_argument(
        "--cluster-devices",
        type=_positive,
        help=f"(t) devices registered across 4 gateways sharing a registry in etcd {both('cluster_devices')}",
    )
    sizes.add_argument(
        "--cluster-queries",
        type=_positive,
        help=f"(t) finds, and Gets each way (local and forwarded), on that cluster {both('cluster_queries')}",
    )
    sizes.add_argument("--time-limit", type=float, help=f"seconds any one part may run {both('time_limit')}")
    sizes.add_argument(
        "--rounds",
        type=_positive,
        help=f"rounds of parts (a)-(c), (q), (r) and (s), servers taking turns; the best round counts "
        f"{both('rounds')}",
    )
    args = parser.parse_args(argv)
    profile = PROFILES["quick" if args.quick else "full"]
    for key, value in profile.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if args.listen_channels is None:
        args.listen_channels = math.ceil(args.subscribers / 25)
    if args.memory_channels is None:
        args.memory_channels = math.ceil(args.streams / 50)
    return args


#: The figure that picks the best round of a part.
HEADLINE = {
    "unary": "throughput_per_s",
    "session": "throughput_per_s",
    "listen": "events_per_s",
    "batched": "events_per_s",
}
HEADLINE["sequential"] = "throughput_per_s"
#: Parts whose best round is the one with the lowest Set-to-delivery p50 (their rate is fixed).
LOWEST_P50 = ("paced",)


async def _part(server: ServerProcess, part: str, run: Callable[[], Awaitable[Any]]) -> dict[str, Any]:
    async def figures() -> dict[str, Any]:
        data: dict[str, Any] = (await run()).as_dict()
        return data

    return await _timed(f"{server.kind}: {part}", figures, server=server, headline=HEADLINE.get(part))


def _best(rounds: list[dict[str, Any]], part: str) -> dict[str, Any]:
    """The round with the best headline figure; every round's figure is kept beside it.

    ``each_round`` keeps every round's top-level figures too, for the targets
    that must hold in every round, not only in the best.
    """
    good = [(n, data) for n, data in enumerate(rounds, start=1) if "error" not in data]
    if not good:
        return rounds[-1]
    if part in LOWEST_P50:
        number, best = min(good, key=lambda item: float(item[1]["latency"]["p50_us"]))
        figures: list[Any] = [
            data["latency"]["p50_us"] if "error" not in data else "error" for data in rounds
        ]
    else:
        headline = HEADLINE[part]
        number, best = max(good, key=lambda item: float(item[1][headline]))
        figures = [data.get(headline, "error") for data in rounds]
    each = [
        {key: value for key, value in data.items() if not isinstance(value, dict | list)} for data in rounds
    ]
    return {**best, "best_round": number, "rounds": figures, "each_round": each}


async def run(args: argparse.Namespace) -> report.Results:
    """Run the chosen parts on each chosen server, one server process at a time.

    With several rounds the servers take turns (baseline, gateway, baseline,
    ...), each round on a fresh process, so that load from elsewhere on the
    machine falls on both alike; each part reports its best round.
    """
    loads = [p for p in args.parts if p in SERVER_PARTS and p != "memory"]
    seen: dict[str, dict[str, list[dict[str, Any]]]] = {kind: {} for kind in args.servers}
    for number in range(1, args.rounds + 1):
        if not loads:
            break
        for kind in args.servers:
            server = await ServerProcess.start(kind, SERVERS[kind])
            print(f"round {number}: {kind} server, pid {server.pid}, on {server.address}", file=sys.stderr)
            try:
                for part in loads:
                    seen[kind].setdefault(part, []).append(
                        await _part(server, part, _runner(args, server, part))
                    )
            finally:
                await server.stop()
    results: report.Results = {
        kind: {part: _best(rounds, part) for part, rounds in parts.items()} for kind, parts in seen.items()
    }
    await _issue_parts(args, results)
    await _peer_parts(args, results)
    if "memory" in args.parts:
        for kind in args.servers:
            server = await ServerProcess.start(kind, SERVERS[kind])
            print(
                f"{kind} server (fresh, for memory), pid {server.pid}, on {server.address}", file=sys.stderr
            )
            try:
                results[kind]["memory"] = await _part(server, "memory", _runner(args, server, "memory"))
            finally:
                await server.stop()
        if "gateway" in args.servers:
            # The same number of idle Listens, carried inside Sessions (the bare server has no Listen there).
            server = await ServerProcess.start("gateway", SERVERS["gateway"])
            print(f"gateway server (fresh, for Listens in Sessions), pid {server.pid}", file=sys.stderr)
            try:
                results["gateway"]["memory_session"] = await _part(
                    server,
                    "memory in sessions",
                    lambda: run_session_memory(
                        server,
                        listens=args.streams,
                        channels=args.memory_channels,
                        time_limit=args.time_limit,
                    ),
                )
            finally:
                await server.stop()
    return results


async def _timed(
    label: str,
    run: Callable[[], Awaitable[dict[str, Any]]],
    *,
    server: ServerProcess | None = None,
    headline: str | None = None,
) -> dict[str, Any]:
    """Run one measurement, saying on stderr how long it took (and its ``headline`` figure).

    A failure becomes ``{"error": ...}`` in the results, with the end of
    ``server``'s log on stderr, so that the other parts still run.
    """
    started = time.perf_counter()
    print(f"  {label} ...", end="", file=sys.stderr, flush=True)
    try:
        data = await run()
    except Exception as exc:
        detail = "".join(traceback.format_exception_only(exc)).strip()
        tail = f"\n{server.log_tail}" if server is not None else ""
        print(f" error: {detail}{tail}", file=sys.stderr, flush=True)
        return {"error": detail}
    shown = f", {data[headline]:,.0f} {headline.removesuffix('_per_s')}/s" if headline else ""
    print(f" {time.perf_counter() - started:.1f} s{shown}", file=sys.stderr, flush=True)
    return data


async def _issue_parts(args: argparse.Namespace, results: report.Results) -> None:
    """Parts (e)-(h), each once, in the order given."""
    if "line" in args.parts:
        print("line: device process and gateway process", file=sys.stderr)
        inflights = tuple(sorted({1, args.inflight}))
        ways = await _timed(
            "line, direct and through the gateway (unary and Session)",
            lambda: run_line(
                calls=args.line_calls,
                inflights=inflights,
                warmup=max(args.line_calls // 10, 10),
                rounds=args.rounds,
                time_limit=args.time_limit,
            ),
        )
        for way in LINE_WAYS:
            results.setdefault(way, {})["line"] = ways if "error" in ways else ways[way]
    if "group" in args.parts:
        results.setdefault("in-process", {})["group"] = await _timed(
            f"group moveto, {_listing(args.group_sizes)} members",
            lambda: run_scaling("group", args.group_sizes, 4 * args.time_limit),
        )
    if "find" in args.parts:
        results.setdefault("in-process", {})["find"] = await _timed(
            f"find, {_listing(args.find_sizes)} entries",
            lambda: run_scaling("find", args.find_sizes, 4 * args.time_limit, queries=args.find_queries),
        )
    if "tls" in args.parts:
        results.setdefault("gateway", {})["tls"] = await _timed(
            "tls: plaintext and mTLS + token gateways, unary and Session",
            lambda: run_tls(
                calls=args.calls,
                gets=args.session_gets,
                inflight=args.inflight,
                batch=args.session_batch,
                window_batches=args.session_window,
                rounds=args.rounds,
                time_limit=args.time_limit,
            ),
        )
    if "storage" in args.parts:
        results.setdefault("gateway", {})["storage"] = await _timed(
            "storage: 1 KiB and 1 MiB files through the gateway and with plain file I/O",
            lambda: run_storage(calls=args.storage_calls, time_limit=args.time_limit),
        )
    if "sse" in args.parts:
        results.setdefault("gateway", {})["sse"] = await _timed(
            f"sse: {args.subscribers} SSE clients and {args.subscribers} gRPC Listens on one property",
            lambda: run_sse(
                subscribers=args.subscribers,
                sets=args.sets,
                set_rate=args.set_rate,
                rounds=max(args.rounds, 2),
                time_limit=args.time_limit,
            ),
        )
    if "rosbridge" in args.parts:
        results.setdefault("gateway", {})["rosbridge"] = await _timed(
            f"rosbridge: {args.subscribers} rosbridge subscribers, SSE clients and gRPC Listens on one "
            f"property; {args.cmd_vel_trips:,} cmd_vel round trips",
            lambda: run_rosbridge(
                subscribers=args.subscribers,
                sets=args.sets,
                set_rate=args.set_rate,
                rounds=max(args.rounds, 2),
                time_limit=args.time_limit,
                trips=args.cmd_vel_trips,
            ),
        )
    if "statemachine" in args.parts:
        results.setdefault("in-process", {})["statemachine"] = await _timed(
            f"statemachine, {args.transitions:,} transitions each with a Set, and as many bare Sets",
            lambda: run_statemachine(args.transitions, args.time_limit),
        )
    if "scheduler" in args.parts:
        results.setdefault("in-process", {})["scheduler"] = await _timed(
            f"scheduler, {_listing(args.scheduler_sizes)} entries, "
            f"{args.scheduler_rounds:,} requests and finds each",
            lambda: run_scheduler(args.scheduler_sizes, args.scheduler_rounds, args.time_limit),
        )
    if "camera" in args.parts:
        results.setdefault("gateway", {})["camera"] = await _timed(
            f"camera: 10 gRPC Listens on a 640x480 camera's frame at 30 Hz for {args.camera_seconds:g} s",
            lambda: run_camera(seconds=args.camera_seconds, time_limit=args.time_limit),
        )
    if "recording" in args.parts:
        results.setdefault("gateway", {})["recording"] = await _timed(
            f"recording: 100 properties at 100 Hz recorded to MCAP, beside not recording, "
            f"{args.recording_seconds:g} s windows",
            lambda: run_recording(
                seconds=args.recording_seconds, rounds=max(args.rounds, 1), time_limit=args.time_limit
            ),
        )
    if "fusion" in args.parts:
        results.setdefault("in-process", {})["fusion"] = await _timed(
            f"fusion, {_listing(args.fusion_sizes)} markers, {args.fusion_observations:,} observations each",
            lambda: run_fusion(args.fusion_sizes, args.fusion_observations, args.time_limit),
        )
    if "metrics" in args.parts:
        results.setdefault("gateway", {})["metrics"] = await _timed(
            "metrics: unary Gets on gateways with and without metrics",
            lambda: run_metrics(
                calls=args.calls,
                inflight=args.inflight,
                rounds=max(args.rounds, 2),
                time_limit=args.time_limit,
            ),
        )
    if "cluster" in args.parts or "cluster-cores" in args.parts:
        results.setdefault("cluster", {})["cores"] = await _timed(
            f"cluster: Listen fan-out of {args.cluster_streams} streams from "
            f"{_listing(args.cluster_gateways)} gateway processes",
            lambda: run_cores(
                args.cluster_gateways,
                listener_kinds=args.cluster_listener,
                streams=args.cluster_streams,
                listeners=args.cluster_listeners,
                seconds=args.cluster_seconds,
                warmup=min(1.0, args.cluster_seconds / 2),
                rounds=args.rounds,
                time_limit=4 * args.time_limit,
            ),
        )
    if "cluster" in args.parts or "cluster-registry" in args.parts:
        if etcd_binary() is None:
            print(f"  cluster registry: not run: {ETCD_MISSING}", file=sys.stderr)
        else:
            results.setdefault("cluster", {})["registry"] = await _timed(
                f"cluster: {args.cluster_devices:,} devices across 4 gateways sharing a registry in etcd",
                lambda: measure_registry(
                    args.cluster_devices,
                    gateways=4,
                    queries=args.cluster_queries,
                    gets=args.cluster_queries,
                    time_limit=10 * args.time_limit,
                ),
            )
    if "register" in args.parts:
        results.setdefault("gateway", {})["register"] = await _timed(
            f"register over raw TCP, {_listing(args.register_sizes)} members",
            lambda: run_register(
                args.register_sizes,
                concurrency=args.register_concurrency,
                time_limit=args.time_limit,
                rounds=args.rounds,
            ),
        )


async def _peer_parts(args: argparse.Namespace, results: report.Results) -> None:
    """Part (s): each peer asked for (``peers``: both), on fresh servers; skipped without its client."""
    names = [name for name in PEERS_BY_NAME if name in args.parts or "peers" in args.parts]
    sizes = PeerSizes(
        calls=args.calls,
        inflight=args.inflight,
        warmup=args.warmup,
        subscribers=args.subscribers,
        channels=args.listen_channels,
        sets=args.peer_sets,
        paced_sets=args.paced_sets,
        set_rate=args.paced_rate,
        time_limit=args.time_limit,
    )
    for name in names:
        peer = PEERS_BY_NAME[name]
        results.setdefault(name, {})["peers"] = await _timed(
            f"{peer.title}: Gets one at a time and {args.inflight} in flight, fan-out to "
            f"{args.subscribers} subscribers, paced Sets, {args.rounds} round(s)",
            lambda peer=peer: run_peer(peer, args.rounds, sizes),
        )


def _listing(sizes: tuple[int, ...]) -> str:
    return ", ".join(f"{n:,}" for n in sizes)


def _runner(args: argparse.Namespace, server: ServerProcess, part: str) -> Callable[[], Awaitable[Any]]:
    if part == "sequential":
        return lambda: run_sequential(
            server,
            calls=args.calls,
            warmup=args.warmup,
            time_limit=args.time_limit,
            floor=server.kind == "baseline",
        )
    if part == "paced":
        return lambda: run_listen(
            server,
            mode="paced",
            properties=(VALUE_PROPERTY,),
            subscribers=args.subscribers,
            sets=args.paced_sets,
            channels=args.listen_channels,
            set_rate=args.paced_rate,
            time_limit=args.time_limit,
        )
    if part == "unary":
        return lambda: run_unary(
            server, calls=args.calls, inflight=args.inflight, warmup=args.warmup, time_limit=args.time_limit
        )
    if part == "session":
        return lambda: run_session(
            server,
            gets=args.session_gets,
            batch=args.session_batch,
            window_batches=args.session_window,
            warmup=args.warmup * 10,
            time_limit=args.time_limit,
        )
    if part in ("listen", "batched"):
        return lambda: run_listen(
            server,
            mode="one-by-one" if part == "listen" else "batched",
            properties=(VALUE_PROPERTY,) if part == "listen" else BATCH_PROPERTIES,
            subscribers=args.subscribers,
            sets=args.sets,
            channels=args.listen_channels,
            set_rate=args.set_rate,
            time_limit=args.time_limit,
        )
    return lambda: run_memory(
        server, streams=args.streams, channels=args.memory_channels, time_limit=args.time_limit
    )


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; exit 0 when every part ran (and, with ``--strict``, met its target)."""
    args = parse_args(argv)
    try:
        import psutil  # type: ignore[import-untyped,unused-ignore]  # noqa: F401 - needed by the measuring
    except ImportError:
        print(
            "python -m bench measures memory with psutil, a test extra: pip install -e '.[test]'",
            file=sys.stderr,
        )
        return 2
    info = report.machine()
    started = time.perf_counter()
    results = asyncio.run(run(args))
    info["load_average_at_end"] = [round(x, 2) for x in os.getloadavg()]
    verdicts = report.evaluate(results)
    report.print_report(sys.stdout, info, results, verdicts)
    elapsed = time.perf_counter() - started
    print(f"\ncommand: {report.command_line()}   ({elapsed:.0f} s)")
    if args.json:
        config = {key: value for key, value in vars(args).items() if key != "json"}
        report.save_json(
            args.json,
            {
                "command": report.command_line(),
                "machine": info,
                "config": config,
                "results": results,
                "targets": verdicts,
                "peer_ratios": compare_with_peers(results),
                "elapsed_s": round(elapsed, 1),
            },
        )
        print(f"results saved to {args.json}")
    errors = any("error" in part for parts in results.values() for part in parts.values())
    missed = any(
        not v["verdict"].startswith("PASS") for v in verdicts if not v["verdict"].startswith("NOT RUN")
    )
    return 1 if errors or (args.strict and missed) else 0


if __name__ == "__main__":
    raise SystemExit(main())
